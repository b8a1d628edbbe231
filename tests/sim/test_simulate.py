"""Scenario files, the simulated world and the `dfusion simulate` command."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from dfusion.cli import main
from dfusion.errors import ScenarioError
from dfusion.sim import run_scenario
from dfusion.scenario import load_scenario
from dfusion.sim import simulate_world

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "topologies").glob("*.scenario.toml"))


def small(**over):
    d = {
        "duration": 3.0, "dt": 0.1, "seed": 1, "window": 50,
        "target": {"motion": "constant_velocity", "q": 0.1, "initial_mean": [0, 0, 1, 0], "initial_cov_diag": [1, 1, 1, 1]},
        "nodes": [
            {"name": "a", "sensor": "position", "std": 0.5, "rate": 5.0, "send_period": 0.5},
            {"name": "b", "sensor": "position", "std": 0.5, "rate": 5.0, "send_period": 0.5},
        ],
        "links": [{"between": ["a", "b"], "latency": 0.1}],
    }
    d.update(over)
    return d


def is_chain(g: nx.Graph) -> bool:
    return nx.is_tree(g) and g.number_of_nodes() >= 3 and max(dict(g.degree).values()) == 2


def is_star(g: nx.Graph) -> bool:
    n = g.number_of_nodes()
    return nx.is_tree(g) and n >= 4 and max(dict(g.degree).values()) == n - 1


def is_deeper_tree(g: nx.Graph) -> bool:
    """Neither a chain nor a star: branches and a diameter of at least 3 hops."""
    return nx.is_tree(g) and not is_chain(g) and not is_star(g) and nx.diameter(g) >= 3


def test_at_least_three_shipped_scenarios_load():
    assert len(SHIPPED) >= 3
    scenarios = {path.name: load_scenario(path) for path in SHIPPED}
    for sc in scenarios.values():
        assert sc.graph.number_of_nodes() == len(sc.nodes)
        # a fixed tree, or the links that exist at the start when links change (no tree needed)
        assert nx.is_tree(sc.graph) or sc.dynamic
    # the three shapes: a chain, a star, a deeper tree with an outage
    assert any(is_chain(sc.graph) for sc in scenarios.values())
    assert any(is_star(sc.graph) for sc in scenarios.values())
    assert any(is_deeper_tree(sc.graph) and sc.outages() for sc in scenarios.values())
    assert is_chain(scenarios["chain3.scenario.toml"].graph)
    assert is_star(scenarios["star5.scenario.toml"].graph)
    assert is_deeper_tree(scenarios["tree7-outage.scenario.toml"].graph)
    assert scenarios["tree7-outage.scenario.toml"].outages()


@pytest.mark.parametrize(
    "change, words",
    [
        ({"duration": -1.0}, "duration"),
        ({"dt": "fast"}, "dt"),
        ({"window": 0}, "window"),
        ({"seed": -3}, "seed"),
        ({"fusion": "magic"}, "fusion"),
        ({"target": {"motion": "teleport"}}, "teleport"),
        ({"target": {"motion": "constant_velocity", "initial_mean": [0, 0, 0]}}, "initial_mean"),
        ({"target": {"motion": "constant_velocity", "initial_cov_diag": [1, 1, -1, 1]}}, "initial_cov_diag"),
        ({"nodes": [{"name": "a", "sensor": "sonar"}, {"name": "b"}]}, "sonar"),
        ({"nodes": [{"name": "a", "sensor": "position", "rate": -1}, {"name": "b"}]}, "rate"),
        ({"nodes": [{"name": "a", "sensor": "position", "std": 0}, {"name": "b"}]}, "std"),
        ({"nodes": [{"name": "a", "active": [[5, 1]]}, {"name": "b"}]}, "active"),
        ({"links": [{"between": ["a", "b"], "drop": 1.5}]}, "drop"),
        ({"links": [{"between": ["a", "b"], "bandwidth": 3}]}, "bandwidth"),
        ({"links": [{"between": ["a", "b"]}, {"between": ["b", "c"]}, {"between": ["c", "a"]}]}, "cycle"),
        ({"links": []}, "connected"),
    ],
)
def test_invalid_scenarios_raise_scenario_error(change, words):
    with pytest.raises(ScenarioError) as info:
        load_scenario(small(**change))
    assert words in str(info.value)


def test_bad_file_and_bad_toml(tmp_path):
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    p = tmp_path / "bad.toml"
    p.write_text("duration = = 3")
    with pytest.raises(ScenarioError, match="invalid TOML"):
        load_scenario(p)


def test_world_is_deterministic_and_measurements_follow_the_spec():
    sc = load_scenario(small(nodes=[
        {"name": "a", "sensor": "position", "std": 0.5, "rate": 5.0, "active": [[0.0, 1.0]]},
        {"name": "b", "sensor": "position", "std": 0.5, "rate": 2.0, "delay": 0.3},
    ]))
    w1, w2 = simulate_world(sc), simulate_world(sc)
    np.testing.assert_array_equal(w1.states, w2.states)
    assert [(m.t, m.node) for m in w1.measurements] == [(m.t, m.node) for m in w2.measurements]
    a = [m.t for m in w1.measurements if m.node == "a"]
    b = [m for m in w1.measurements if m.node == "b"]
    assert np.allclose(a, [0.2, 0.4, 0.6, 0.8, 1.0])            # rate 5/s while active
    assert np.allclose([m.t for m in b], [0.5, 1.0, 1.5, 2.0, 2.5, 3.0])
    assert all(0 <= m.arrival - m.t <= 0.3 for m in b)
    other = simulate_world(load_scenario(small(), seed=2))
    assert not np.array_equal(other.states, simulate_world(load_scenario(small())).states)


def test_measurement_noise_statistics_match_the_sensor():
    sc = load_scenario(small(duration=200.0, nodes=[
        {"name": "a", "sensor": "position", "std": 0.7, "rate": 10.0}, {"name": "b"}]))
    w = simulate_world(sc)
    err = np.array([m.z - w.truth(m.t)[:2] for m in w.measurements])
    assert len(err) == 2000
    assert abs(err.std() - 0.7) < 0.03 and abs(err.mean()) < 0.03


def test_simulate_json_has_the_documented_keys_and_converges(tmp_path):
    out = tmp_path / "r.json"
    png = tmp_path / "r.png"
    code = main(["simulate", str(ROOT / "topologies" / "chain3.scenario.toml"), "--seed", "3", "--duration", "25",
                 "--json", str(out), "--plot", str(png), "-q"])
    assert code == 0
    data = json.loads(out.read_text())
    for key in ("rmse", "anees"):
        assert data["centralized"][key] > 0
    assert set(data["nodes"]) == {"a", "b", "c"}
    for v in data["nodes"].values():
        assert {"rmse", "anees", "final_gap"} <= set(v)
        assert v["final_gap"] < 1e-6
    assert data["messages"] > 0 and data["bytes"] > data["messages"]
    assert data["seed"] == 3 and data["steps"] == 251
    assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the figures are those of the run, recomputed here with numpy (deterministic for a seed)
    res = run_scenario(load_scenario(ROOT / "topologies" / "chain3.scenario.toml", seed=3, duration=25.0))

    def rmse_ref(mean):
        return float(np.sqrt(np.mean(np.sum((mean[:, :2] - res.truth[:, :2]) ** 2, axis=1))))

    def anees_ref(mean, cov):
        e = mean - res.truth
        return float(np.mean([ek @ np.linalg.solve(Pk, ek) for ek, Pk in zip(e, cov)]))

    assert data["centralized"]["rmse"] == pytest.approx(rmse_ref(res.central_mean), rel=1e-9)
    assert data["centralized"]["anees"] == pytest.approx(anees_ref(res.central_mean, res.central_cov), rel=1e-9)
    for name, v in data["nodes"].items():
        assert v["rmse"] == pytest.approx(rmse_ref(res.node_mean[name]), rel=1e-9)
        assert v["anees"] == pytest.approx(anees_ref(res.node_mean[name], res.node_cov[name]), rel=1e-9)
    assert data["messages"] == sum(v["messages"] for v in data["nodes"].values())
    assert data["bytes"] == sum(v["bytes"] for v in data["nodes"].values())
    assert isinstance(data["messages"], int) and isinstance(data["bytes"], int)


def test_simulate_prints_the_table(capsys):
    code = main(["simulate", str(ROOT / "topologies" / "star5.scenario.toml"), "--duration", "5", "-q"])
    assert code == 0
    out = capsys.readouterr().out
    header = out.splitlines()[0]
    assert header.split()[:3] == ["node", "RMSE", "[m]"]
    for col in ("ANEES [-]", "final gap pos [m]", "final gap vel [m/s]", "mean gap pos [m]", "sent [msgs]",
                "sent [bytes]"):
        assert col in header, col
    for name in ("h", "s1", "s2", "s3", "s4", "centralized"):
        assert any(line.split()[:1] == [name] for line in out.splitlines()), name
    assert "messages" in out and "bytes" in out


def test_naive_selectable_in_scenario_and_on_the_command_line():
    sc = load_scenario(small(fusion="naive"))
    assert sc.fusion == "naive"
    res = run_scenario(sc)
    assert all(v["final_gap"] > 1e-6 for v in res.metrics["nodes"].values())
    assert load_scenario(small(), fusion="naive").fusion == "naive"
    # the channel filter on the same world converges; naive fusion does not
    exact = run_scenario(load_scenario(small()))
    assert all(v["final_gap"] < 1e-9 for v in exact.metrics["nodes"].values())


def test_naive_selectable_with_the_cli_flag(tmp_path):
    out = tmp_path / "naive.json"
    code = main(["simulate", str(ROOT / "topologies" / "chain3.scenario.toml"), "--fusion", "naive",
                 "--duration", "10", "--json", str(out), "-q"])
    assert code == 0
    data = json.loads(out.read_text())
    assert data["fusion"] == "naive"
    assert all(v["final_gap"] > 1e-6 for v in data["nodes"].values())   # rumour propagation


def test_cli_reports_errors_cleanly(tmp_path, capsys):
    bad = tmp_path / "cyc.toml"
    bad.write_text('[[links]]\nbetween=["a","b"]\n[[links]]\nbetween=["b","c"]\n[[links]]\nbetween=["c","a"]\n')
    assert main(["simulate", str(bad)]) == 2
    assert "cycle" in capsys.readouterr().err


def test_console_script_entry_point():
    r = subprocess.run([sys.executable, "-m", "dfusion", "simulate", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--json" in r.stdout


def test_cyclic_graph_fused_over_its_spanning_tree_on_request():
    links = [{"between": ["a", "b"], "quality": 0.9}, {"between": ["b", "c"], "quality": 0.8},
             {"between": ["c", "a"], "quality": 0.3}]
    nodes = [{"name": n, "sensor": "position", "std": 0.5, "rate": 5.0} for n in "abc"]
    with pytest.raises(ScenarioError, match="cycle"):
        load_scenario(small(links=links, nodes=nodes))
    sc = load_scenario(small(links=links, nodes=nodes, spanning_tree=True))
    assert sorted(map(sorted, sc.graph.edges)) == [["a", "b"], ["b", "c"]]   # the weakest link goes
    assert set(sc.links) == {("a", "b"), ("b", "c")}
    res = run_scenario(sc)
    assert all(v["final_gap"] < 1e-9 for v in res.metrics["nodes"].values())


def test_policy_selected_per_node_in_the_scenario():
    from dfusion.policies import InformationFusionPolicy, Policy
    from dfusion.scenario import build_nodes
    from dfusion.scenario import Kinds, builtin_kinds

    class Loudest(Policy):
        name = "loudest"

        def __init__(self, floor=0.0):
            self.floor = floor

        def decide(self, fused, sources):
            return fused

    kinds = builtin_kinds().merged(Kinds({}, {"loudest": lambda p: Loudest(**p)}, {}), "test")
    nodes = [{"name": "a", "sensor": "position", "policy": {"kind": "loudest", "floor": 0.3}},
             {"name": "b", "sensor": "position", "policy": "fusion"}]
    sc = load_scenario(small(nodes=nodes), kinds=kinds)
    built = build_nodes(sc)
    assert isinstance(built["a"].policy, Loudest) and built["a"].policy.floor == 0.3
    assert isinstance(built["b"].policy, InformationFusionPolicy)
    with pytest.raises(ScenarioError, match="unknown policy"):
        load_scenario(small(nodes=[{"name": "a", "policy": "oracle"}, {"name": "b"}]), kinds=kinds)
    with pytest.raises(ScenarioError, match="policy"):
        load_scenario(small(nodes=[{"name": "a", "policy": {"kind": "loudest", "volume": 11}}, {"name": "b"}]),
                      kinds=kinds)
    with pytest.raises(ScenarioError, match="unknown policy"):   # nothing was registered globally
        load_scenario(small(nodes=nodes))


# ----------------------------------------------------------------------------- clutter: references, diagnostics
def test_fair_reference_gets_every_detection_and_the_oracle_only_true_ones():
    from dfusion.scenario.build import build_front_ends
    from dfusion.sim.runner import References, frames
    from tests.frontends.test_camera import camera_scenario

    sc = load_scenario(camera_scenario(false_detection_rate=0.8), seed=2)
    w = simulate_world(sc)
    refs = References(sc, build_front_ends(sc))
    groups = frames(w.measurements)
    for i, fr in enumerate(groups):
        refs.add(fr, seq=i)
        assert len({(m.node, m.t, m.arrival) for m in fr}) == 1
    cam_frames = [fr for fr in groups if fr[0].node == "cam"]
    assert sum(len(fr) > 1 for fr in cam_frames) > 5               # frames with several detections
    assert len(refs.fair) == len(cam_frames)                       # one PDA update per frame
    assert len(refs.oracle) == sum(not m.clutter for m in w.measurements)


def test_without_clutter_and_gate_the_fair_reference_is_the_oracle():
    """No false detections and no gate: a frame holds the true detection alone and PDA with
    beta_0 = 0 is the plain EKF update, so both references agree to rounding."""
    from tests.frontends.test_camera import camera_scenario

    res = run_scenario(load_scenario(camera_scenario(gate=1.0), seed=5))
    assert np.max(np.abs(res.central_mean - res.oracle_mean)) < 1e-9
    assert res.metrics["centralized"]["rmse"] == pytest.approx(res.metrics["centralized_oracle"]["rmse"], rel=1e-9)


def test_a_cluttered_run_reports_both_references_and_the_documented_diagnostics():
    from tests.frontends.test_camera import camera_scenario

    sc = load_scenario(camera_scenario(false_detection_rate=0.5), seed=3)
    res = run_scenario(sc)
    m = res.metrics
    assert set(m["centralized_oracle"]) == {"rmse", "anees"}
    cam = m["nodes"]["cam"]
    assert cam["gated"] > 0 and cam["detections"] > cam["gated"]
    assert cam["health"] in ("ok", "degraded", "lost") and sum(cam["health_steps"].values()) == len(res.times)
    assert m["nodes"]["relay"]["tests"] > 0 and m["nodes"]["relay"]["gated"] is None
    assert "NIS" in res.table() and "central oracle" in res.table()
    documented = (ROOT / "docs" / "scenarios.md").read_text()
    for key in set(cam):
        assert f"`nodes.<name>.{key}`" in documented or f", `.{key}`" in documented or f"`{key}`" in documented, key
    for key in set(m) - {"nodes"}:
        assert f"`{key}`" in documented or f"`{key}." in documented, key
    off = run_scenario(load_scenario(camera_scenario(false_detection_rate=0.5), seed=3, protection=False))
    assert off.metrics["protection"] == "off" and off.metrics["nodes"]["cam"]["nis_mean"] is None


def test_warning_lines_name_lost_and_inconsistent_nodes():
    from dfusion.sim.runner import warning_lines

    m = {"nees_interval": [0.5, 11.0], "nodes": {
        "a": {"anees": 4.0, "health": "ok", "health_steps": {"ok": 10, "degraded": 0, "lost": 0}},
        "b": {"anees": 40.0, "health": "ok", "health_steps": {"ok": 7, "degraded": 0, "lost": 3}},
        "c": {"anees": 0.1}}}
    lines = warning_lines(m)
    assert len(lines) == 3 and all(line.startswith("WARNING ") for line in lines)
    assert "b: lost during 3 steps" in lines[0] and "over-confident" in lines[1] and "c: inconsistent" in lines[2]


def test_no_protection_on_the_command_line(tmp_path, capsys):
    out = tmp_path / "off.json"
    corridor = ROOT / "topologies" / "clutter-corridor.scenario.toml"
    assert main(["simulate", str(corridor), "--duration", "8", "--no-protection", "--json", str(out), "-q"]) == 0
    data = json.loads(out.read_text())
    assert data["protection"] == "off"
    assert all(v["tests"] is None and v["health"] == "ok" for v in data["nodes"].values())
    assert "protection: off" in capsys.readouterr().out


def test_progress_off_a_terminal_is_a_line_every_interval_and_one_at_the_end():
    """dfusion.sim.runner.Progress (simulate, replay and dfusion run's launcher) on a stream that is
    not a terminal: a line when PROGRESS_INTERVAL has passed since the last one, the last count once
    at the end (by update or close), nothing on a bar."""
    import io

    from dfusion.sim.runner import PROGRESS_INTERVAL, Progress

    assert PROGRESS_INTERVAL == 10.0

    stream = io.StringIO()
    clock = iter([0.0, 3.0, 11.0, 12.0, 25.0, 26.0, 27.0, 28.0])   # PROGRESS_INTERVAL = 10 s
    p = Progress(10, stream=stream)
    p._clock = lambda: next(clock)
    p.start = p._last = p._clock()
    p.update(2, "alive 3/3")   # 3 s: nothing yet
    p.update(4, "alive 3/3")   # 11 s: a line
    p.update(5)                # 12 s: nothing
    p.update(6, "alive 2/3")   # 25 s: a line (14 s since the last one)
    p.update(7, "alive 2/3")   # 26 s: nothing
    p.close()                  # 27 s: the last count
    p.close()                  # nothing more
    assert stream.getvalue().splitlines() == [
        "progress: 4/10 steps (40 %), 11 s, alive 3/3", "progress: 6/10 steps (60 %), 25 s, alive 2/3",
        "progress: 7/10 steps (70 %), 27 s, alive 2/3"]
    stream = io.StringIO()
    p = Progress(3, stream=stream)
    for k in (1, 2, 3, 3, 3):   # the end reached and repeated (the launcher polls): one line
        p.update(k)
    p.close()
    assert stream.getvalue().count("progress: 3/3 steps (100 %)") == 1 and stream.getvalue().count("\n") == 1
