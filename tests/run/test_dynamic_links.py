"""``dfusion run`` with links that change (real processes over Zenoh, loopback).

A link exists while the scenario allows it (``dfusion.scenario.links.LinkSchedule``: the
rule ``simulate`` uses) and both ends see each other's liveliness token; the nodes keep the
fusion links a tree by the tree rule. Checked here: a SIGKILLed node is dropped from the
tree within two lease periods and its neighbours re-attach around it, the restarted node
joins again; a partition of two halves for 20 s heals; and every node ends on the
centralized EKF (computed by the monitor from the world, independently of the nodes).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

from dfusion.fusion.tree import NodeTreeState, TreeEpoch, forest_settled  # noqa: E402
from dfusion.run.common import Status, TreeStatus  # noqa: E402
from dfusion.run.launcher import Launcher, Restart, RunOptions  # noqa: E402
from dfusion.run.monitor import run_table, tree_metrics  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402
from dfusion.scenario.links import LinkSchedule, peers  # noqa: E402
from dfusion.transport.zenoh import ZenohConfig  # noqa: E402
from dfusion.wire import FrameKey  # noqa: E402

HEAD = """
duration = {duration}
dt = 0.1
seed = 5
window = {window}

[target]
motion = "constant_velocity"
q = 0.05
initial_mean = [0.0, 0.0, 0.5, 0.2]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]
"""

NODE = """
[[nodes]]
name = "{name}"
sensor = "position"
std = {std}
rate = 5.0
send_period = 0.5
{extra}
"""

#: Four nodes on the corners of a 10 m square, radio range 12 m: the links form a cycle
#: a - b - c - d - a (the diagonals, 14.1 m, are out of range) that the tree rule breaks.
SQUARE = {"a": (0.0, 0.0), "b": (10.0, 0.0), "c": (10.0, 10.0), "d": (0.0, 10.0)}


def square(tmp_path: Path, duration: float, window: int) -> Path:
    text = HEAD.format(duration=duration, window=window)
    for i, (name, (x, y)) in enumerate(SQUARE.items()):
        text += NODE.format(name=name, std=0.5 + 0.2 * i, extra=f"position = [{x}, {y}]\nradio_range = 12.0")
    path = tmp_path / "square.scenario.toml"
    path.write_text(text)
    return path


def partition(tmp_path: Path, duration: float, window: int, down: float, up: float) -> Path:
    """Halves {a, b} and {c, d}, joined by b - c and a - d (a cycle), cut from ``down`` to ``up``."""
    text = HEAD.format(duration=duration, window=window)
    for i, name in enumerate("abcd"):
        text += NODE.format(name=name, std=0.5 + 0.2 * i, extra="")
    for a, b in (("a", "b"), ("c", "d"), ("b", "c"), ("a", "d")):
        text += f'\n[[links]]\nbetween = ["{a}", "{b}"]\nlatency = 0.02\n'
    for kind, t in (("link_down", down), ("link_up", up)):
        for a, b in (("b", "c"), ("a", "d")):
            text += f'\n[[events]]\nt = {t}\n{kind} = ["{a}", "{b}"]\n'
    path = tmp_path / "partition.scenario.toml"
    path.write_text(text)
    return path


def states_at(records, k: int) -> dict[str, TreeStatus]:
    return {n: r.tree[k] for n, r in records.items() if r.tree[k] is not None}


def settled_at(records, k: int, names: set[str]) -> bool:
    """The published states at step ``k`` are exactly ``names`` and form a settled tree on the links
    both ends report (checked with the tree rule's own definition of settled)."""
    st = states_at(records, k)
    if set(st) != names:
        return False
    links = {tuple(sorted((a, b))) for a, s in st.items() for b in s.links if b in st and a in st[b].links}
    view = {n: NodeTreeState(n, TreeEpoch(s.term, s.root), s.parent, frozenset(s.tree_links)) for n, s in st.items()}
    return forest_settled(view, links)[0]


def test_the_schedule_and_the_peers_of_a_square_with_radio_ranges(tmp_path):
    sc = load_scenario(square(tmp_path, 4.0, 60))
    assert sc.dynamic
    sched = LinkSchedule(sc)
    assert sched.links(0.0) == {("a", "b"), ("b", "c"), ("c", "d"), ("a", "d")}
    assert sched.neighbours("a", 1.0) == {"b", "d"}
    assert peers(sc, "a") == ("b", "c", "d")   # c is out of range now, but ranges may bring it in


def test_partition_schedule_cuts_and_heals(tmp_path):
    sc = load_scenario(partition(tmp_path, 10.0, 60, 2.0, 6.0))
    sched = LinkSchedule(sc)
    assert sched.links(1.0) == {("a", "b"), ("c", "d"), ("b", "c"), ("a", "d")}
    assert sched.links(3.0) == {("a", "b"), ("c", "d")}
    assert sched.links(6.5) == sched.links(1.0)
    assert peers(sc, "b") == ("a", "c")


def test_a_restarted_node_with_changing_links_is_built_once_and_claims_one_epoch(tmp_path, monkeypatch):
    """A node process started after the common start time (a restart) of a scenario whose links
    change builds one FusionNode, as a joining node (alone in the join epoch, no links yet: it adopts
    its neighbours' epoch), and claims one incarnation epoch in its state directory; a node whose
    start time passes only after it was built on time is rebuilt as a joining node with the same
    incarnation epoch (no second claim)."""
    import time

    from dfusion.fusion.tree import JOIN_TERM
    from dfusion.run import node_process
    from dfusion.run.node_process import NodeProcess

    sc = load_scenario(square(tmp_path, 20.0, 60))
    claims = []
    real_claim = node_process.claim_epoch

    def counting_claim(state_dir, name, *a, **kw):
        claims.append(name)
        return real_claim(state_dir, name, *a, **kw)

    monkeypatch.setattr(node_process, "claim_epoch", counting_claim)
    monkeypatch.setattr(NodeProcess, "_publish", lambda self, phase, k: None)   # no Zenoh session here

    # started 5 s (scenario time) after the common start: a restart
    state = tmp_path / "state"
    proc = NodeProcess(sc, "b", start=time.time() - 5.0, state_dir=state, run_id="r", measurements=[])
    built = proc.node
    assert built.tree.epoch == TreeEpoch(JOIN_TERM, "b") and built.tree.parent is None and not built.tree_links
    wait = next(proc.program())   # start, catch up to now, wait for the next step
    assert proc.node is built and proc.t_started > 4.0 and wait.deadline > proc.start + 4.0
    assert claims == ["b"] and int((state / "b.epoch").read_text()) == built.epoch

    # on time at construction (start in the future), late by the time it starts: rebuilt, same epoch
    claims.clear()
    proc = NodeProcess(sc, "c", start=time.time() + 3600.0, state_dir=state, run_id="r", measurements=[])
    on_time = proc.node
    assert on_time.tree.epoch.term > JOIN_TERM and set(on_time.tree_links) <= {"b", "d"} and on_time.tree_links
    proc.start = time.time() - 5.0
    next(proc.program())
    assert proc.node is not on_time and proc.node.epoch == on_time.epoch
    assert proc.node.tree.epoch == TreeEpoch(JOIN_TERM, "c") and not proc.node.tree_links
    assert claims == ["c"] and int((state / "c.epoch").read_text()) == on_time.epoch


def test_tree_status_travels_in_the_monitor_message():
    st = Status("a", 7, "run", 3, 0.3, np.zeros(2), np.eye(2), tree=TreeStatus(2, "c", "d", ("b", "d"), ("d",)))
    key = FrameKey(b"k" * 16, "net", "run-1")
    back = Status.decode(st.encode(key), key)
    assert back.tree == st.tree
    assert Status.from_json(st.to_json()).tree == st.tree
    root = TreeStatus(1, "a", None, ("b",), ("b",))
    assert Status.decode(Status("a", 1, "run", 1, 0.1, np.zeros(2), np.eye(2), tree=root).encode()).tree == root


def test_sigkilled_node_leaves_the_tree_within_two_leases_and_rejoins_after_its_restart(tmp_path):
    """b (a's child and c's parent on the tree of the square) is SIGKILLed at t=6 s and restarted
    2 s later by the launcher. a and c drop it within two lease periods, c re-attaches through
    d, the four nodes settle on one tree again once b is back, and every node ends on the
    centralized estimate."""
    speed, lease = 2.0, ZenohConfig().lease_ms / 1000
    scenario = square(tmp_path, 24.0, 260)   # the window spans the run: exact re-convergence
    launcher = Launcher(RunOptions(scenario=str(scenario), speed=speed, run_dir=str(tmp_path / "run"),
                                   restarts=[Restart("b", 6.0, 2.0)]))
    result = launcher.run()
    assert result is not None
    records = launcher.monitor.records
    dt = 0.1
    k_kill = int(round(6.0 / dt))
    first = states_at(records, 5)
    assert first["b"].parent == "a" and first["c"].parent == "b", first   # the initial tree
    # dropped: the first step after the kill at which neither a nor c has a link to b
    k_drop = next(k for k in range(k_kill, len(records["a"].tree))
                  if all(records[n].tree[k] is not None and "b" not in records[n].tree[k].links for n in "ac"))
    assert (k_drop - k_kill) * dt / speed <= 2 * lease, (k_drop - k_kill) * dt / speed
    # re-attached: a, c, d settle on a tree without b (c's parent or child is now d)
    k_alone = next(k for k in range(k_drop, len(records["a"].tree)) if settled_at(records, k, {"a", "c", "d"}))
    assert "d" in states_at(records, k_alone)["c"].tree_links
    # joined again: b back and all four settled on one tree, b among the tree links
    def one_tree(k: int) -> bool:
        st = states_at(records, k)
        return settled_at(records, k, set("abcd")) and len({(s.term, s.root) for s in st.values()}) == 1

    k_back = next(k for k in range(k_alone, len(records["a"].tree)) if one_tree(k))
    assert states_at(records, k_back)["b"].tree_links
    m = result.metrics
    assert m["run"]["nodes"]["b"]["incarnations"] == 2
    for name, v in m["nodes"].items():
        assert v["final_gap"] < 1e-6, (name, v["final_gap"], m["run"])
    lk = m["links"]
    gone = [c for c in lk["changes"] if "b gone" in c["what"]]
    assert gone and gone[0]["tree_settled_send_periods"] is not None, lk["changes"]
    assert "links that change" in result.table() and "liveliness" in run_table(result)
    print(f"b dropped {(k_drop - k_kill) * dt / speed:.2f} s wall after the kill (lease {lease:g} s); "
          f"a, c, d settled {(k_alone - k_kill) * dt:.1f} s scenario time after it; all four "
          f"{(k_back - k_kill) * dt:.1f} s after it")
    print(result.table())


def test_a_partition_of_two_halves_for_20s_heals_and_reconverges(tmp_path):
    """The links between {a, b} and {c, d} go down from t=6 s to t=26 s: each half forms its own
    tree (two epochs), they merge into one when the links return, and every node ends within
    1e-9 of the centralized estimate (a linear scenario, a window longer than the run)."""
    speed = 2.0
    scenario = partition(tmp_path, 36.0, 380, 6.0, 26.0)
    launcher = Launcher(RunOptions(scenario=str(scenario), speed=speed, run_dir=str(tmp_path / "run")))
    result = launcher.run()
    assert result is not None
    records = launcher.monitor.records
    mid = states_at(records, int(16.0 / 0.1))
    halves = {n: (s.term, s.root) for n, s in mid.items()}
    assert halves["a"] == halves["b"] and halves["c"] == halves["d"] and halves["a"] != halves["c"], halves
    assert settled_at(records, int(16.0 / 0.1), set("abcd"))
    k_heal = next(k for k in range(int(26.0 / 0.1), len(records["a"].tree)) if settled_at(records, k, set("abcd"))
                  and len({(s.term, s.root) for s in states_at(records, k).values()}) == 1)
    m = result.metrics
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
    print(f"healed: one tree {k_heal * 0.1 - 26.0:.1f} s after the links returned")
    print(result.table())


def test_tree_metrics_from_published_states_by_hand(tmp_path):
    """The monitor's account of a hand-written history of three nodes (a - b - c on a chain of
    scripted links): c goes at step 5 (its links vanish, a - b is settled at once), comes back
    alone at step 8 (not settled: c is in its own epoch), and is adopted at step 10."""
    from types import SimpleNamespace

    text = HEAD.format(duration=1.5, window=30)
    for name in "abc":
        text += NODE.format(name=name, std=0.5, extra="")
    text += '\n[[links]]\nbetween = ["a", "b"]\n\n[[links]]\nbetween = ["b", "c"]\n'
    text += '\n[[events]]\nt = 1.4\nlink_down = ["a", "b"]\n'   # makes the links dynamic; after the history
    path = tmp_path / "chain.scenario.toml"
    path.write_text(text)
    sc = load_scenario(path)
    K = sc.steps + 1
    tree = {n: [None] * K for n in "abc"}
    for k in range(K):
        tree["a"][k] = TreeStatus(1, "a", None, ("b",), ("b",))
        if k < 5:
            tree["b"][k] = TreeStatus(1, "a", "a", ("a", "c"), ("a", "c"))
            tree["c"][k] = TreeStatus(1, "a", "b", ("b",), ("b",))
        elif k < 8:
            tree["b"][k] = TreeStatus(1, "a", "a", ("a",), ("a",))
        elif k < 10:
            tree["b"][k] = TreeStatus(1, "a", "a", ("a", "c"), ("a",))
            tree["c"][k] = TreeStatus(0, "c", None, ("b",), ())
        else:
            tree["b"][k] = TreeStatus(1, "a", "a", ("a", "c"), ("a", "c"))
            tree["c"][k] = TreeStatus(1, "a", "b", ("b",), ("b",))
    records = {n: SimpleNamespace(tree=tree[n]) for n in "abc"}
    lk = tree_metrics(sc, records)
    assert [(c["t"], c["what"]) for c in lk["changes"]] == [(0.5, ["c gone", "b - c down"]),
                                                          (0.8, ["c back", "b - c up"])]
    gone, back = lk["changes"]
    assert gone["tree_changed"] and gone["tree_settled_send_periods"] == 0.0
    assert back["tree_changed"] and back["tree_settled_send_periods"] == round(0.2 / 0.5, 3)
    assert lk["tree_changes"] == 2 and lk["settling_tree_changes"]["count"] == 2
