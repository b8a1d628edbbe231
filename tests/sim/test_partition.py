"""A network partitioned into two halves for 20 s heals and re-converges (dfusion simulate with
scripted [[events]]); and a scenario with a fixed tree runs exactly as the fixed-tree protocol
(no tree fields, beacons or withdrawals)."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.scenario import load_scenario
from dfusion.sim.runner import run_scenario

RING = """
duration = 40.0
dt = 0.1
seed = {seed}
window = 450          # longer than the run: every measurement stays in the window (exact after the heal)
[protection]
enabled = false       # linear sensors, no clutter: nothing to protect against
[target]
motion = "constant_velocity"
q = 0.05
initial_mean = [0.0, 0.0, 0.5, 0.2]
initial_cov_diag = [4.0, 4.0, 0.25, 0.25]
{nodes}
# a ring of six: the radio graph has a cycle, the tree rule drops one of its links
[[links]]
between = ["a", "b"]
[[links]]
between = ["b", "c"]
[[links]]
between = ["c", "d"]
[[links]]
between = ["d", "e"]
[[links]]
between = ["e", "f"]
[[links]]
between = ["f", "a"]
# two halves {{a, b, c}} and {{d, e, f}} from 10 s to 30 s
[[events]]
t = 10.0
link_down = ["c", "d"]
[[events]]
t = 10.0
link_down = ["f", "a"]
[[events]]
t = 30.0
link_up = ["c", "d"]
[[events]]
t = 30.0
link_up = ["a", "f"]
"""
NODE = """[[nodes]]
name = "{name}"
sensor = "position"
std = {std}
rate = 2.0
send_period = 0.5
"""


def ring(tmp_path, seed: int):
    nodes = "".join(NODE.format(name=n, std=0.5 + 0.2 * i) for i, n in enumerate("abcdef"))
    f = tmp_path / "ring.scenario.toml"
    f.write_text(RING.format(seed=seed, nodes=nodes))
    return load_scenario(f)


@pytest.mark.parametrize("seed", [1, 2])
def test_two_halves_for_20_s_heal_and_re_converge(tmp_path, seed):
    sc = ring(tmp_path, seed)
    res = run_scenario(sc)
    times = res.times

    def trace_ratio(t: float) -> float:
        """Mean over the nodes of trace(P_node) / trace(P_central), positions."""
        k = int(np.searchsorted(times, t))
        c = np.trace(res.central_cov[k][:2, :2])
        return float(np.mean([np.trace(res.node_cov[n][k][:2, :2]) / c for n in "abcdef"]))

    # every node lies on the safe side at every step: its covariance is at least the centralized one
    for n in "abcdef":
        for k in range(len(times)):
            ev = np.linalg.eigvalsh(res.node_cov[n][k] - res.central_cov[k])
            assert ev[0] >= -1e-9 * np.abs(res.central_cov[k]).max(), (n, times[k], ev)
    # the partition shows (each half misses the other's measurements) and goes after the heal
    assert trace_ratio(25.0) > 1.15 * trace_ratio(38.0), (trace_ratio(25.0), trace_ratio(38.0))
    # healed: every node ends on the centralized estimate of all measurements (window covers the run)
    for n, v in res.metrics["nodes"].items():
        assert v["final_gap"] < 1e-8, (n, v["final_gap"])
    lk = res.metrics["links"]
    assert lk["link_changes"] == 2 and lk["tree_changes"] >= 1
    heal = [c for c in lk["changes"] if c["t"] == 30.0][0]
    assert heal["info_settled_send_periods"] is not None
    # every node holds everything measured up to the heal, once: within diameter send periods for the
    # new epoch to cross the component and settling_rounds(diameter) = diameter + 2 for the information
    assert heal["info_settled_send_periods"] <= 2 * 5 + 2


def test_a_fixed_tree_runs_the_fixed_tree_protocol(tmp_path):
    """A scenario without events or ranges: nodes without the tree rule (no tree fields, no
    beacons, nothing withdrawn), on the centralized estimate at the end."""
    text = (tmp_path / "x").parent
    nodes = "".join(NODE.format(name=n, std=0.5) for n in "abc")
    f = text / "chain.scenario.toml"
    f.write_text(RING.format(seed=3, nodes=nodes).split("# a ring")[0]
                 + '[[links]]\nbetween = ["a", "b"]\n[[links]]\nbetween = ["b", "c"]\n')
    sc = load_scenario(f)
    assert not sc.dynamic
    res = run_scenario(sc)
    assert res.links is None and "links" not in res.metrics
    for n, v in res.metrics["nodes"].items():
        assert v["final_gap"] < 1e-8


def test_tree_frames_are_taken_after_the_changes_settled(tmp_path):
    from dfusion.viz.treeframes import frame_times, plot_tree_frames

    sc = ring(tmp_path, 1)
    sc.duration = 32.0
    res = run_scenario(sc)
    times = frame_times(res)
    settled = [c.tree_settled for c in res.links.changes if c.tree_changed]
    assert times[0] == 0.0 and set(settled) <= set(times)
    out = plot_tree_frames(res, tmp_path / "frames.png")
    assert out.stat().st_size > 10_000
