"""The consistency guard on the critical path (issue 15): a steady-state message to a node with a
guard is fused at once and its bookkeeping settled later, exactly as the general path does it all
at once; it is tested and judged at once when a failing verdict would complete a quarantine,
else in ``settle()`` (no verdict can then change the belief).

* over random schedules with the guard on every node and, in most, one hostile node (its
  sensor 6 m off with a claimed noise of 0.2 m: its neighbours quarantine it), every
  node's whole state, estimate, guard records and every message it sends are bit for bit
  those of the same run on the general path (``FusionNode.critical_path_first`` and
  ``ChannelFilter.append_plans`` off), step by step;
* the test is not vacuous: guarded steady-state messages take the critical path, most with
  the test left for ``settle()`` (the estimate read before it is already the one after it),
  the message that completes a quarantine falls back to the general path, and a quarantine
  happens;
* :meth:`NeighbourGuard.would_quarantine` predicts :meth:`NeighbourGuard.judge` on random
  sequences of verdicts (a brute-force replay of the rule "k failures among the last m").
"""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.fusion import ChannelFilter, FusionNode, GuardConfig, NeighbourGuard
from dfusion.fusion.guard import (
    _statistic_stacked,
    block_eigen,
    information_statistic,
    split_blocks,
)
from dfusion.models import ConstantVelocity, PositionSensor
from tests.fusion.test_guard import _dense_statistic
from tests.helpers.fusion_harness import (
    Schedule,
    Trace,
    random_tree,
    run_network,
    state_digest,
)

HOSTILE_BIAS = (6.0, 0.0)
HOSTILE_STD = 0.2


def guard_records(node: FusionNode) -> tuple:
    """The node's guard records, every field (``recent`` as a tuple)."""
    return tuple((j, tuple((k, tuple(v) if isinstance(v, deque) else v) for k, v in sorted(vars(r).items())))
                 for j, r in sorted(node.guard.links.items()))


def recorded_run(monkeypatch, graph, kw: dict, general: bool) -> tuple:
    """Run the schedule; returns ``(per-step states, messages sent, rejections, path counts)``, on
    the general path with ``general``."""
    steps: list = []
    sent: list = []
    paths = {"fast": 0, "fallback": 0, "deferred": 0}
    send, steady = FusionNode.message_to, FusionNode._apply_steady

    def message_to(self, neighbor, sent_at=None):
        data = send(self, neighbor, sent_at)
        sent.append((self.name, neighbor, data))
        return data

    def apply_steady(self, *args):
        done = steady(self, *args)
        paths["fast" if done is not None else "fallback"] += 1
        if done is not None and self._pending[-1] is not None:   # the test left for settle()
            paths["deferred"] += 1
            # the belief is final already: the estimate read now is the one after settle()
            now = [x.tobytes() for x in self.estimate()]
            self.settle()
            assert [x.tobytes() for x in self.estimate()] == now
        return done

    def on_step(nodes, measurements, t):
        steps.append({n: (state_digest(node), guard_records(node), *[x.tobytes() for x in node.estimate()])
                      for n, node in nodes.items()})

    with monkeypatch.context() as m:
        m.setattr(FusionNode, "message_to", message_to)
        m.setattr(FusionNode, "_apply_steady", apply_steady)
        m.setattr(FusionNode, "critical_path_first", not general)
        m.setattr(ChannelFilter, "append_plans", not general)
        trace = Trace()
        nodes, _, _ = run_network(graph, Schedule(**kw, on_step=on_step), trace=trace)
        on_step(nodes, None, None)
    quarantines = sum(r.quarantines for node in nodes.values() for r in node.guard.links.values())
    return steps, sent, trace.rejections, paths, quarantines


@st.composite
def schedules(draw) -> tuple:
    n = draw(st.integers(2, 5))
    seed = draw(st.integers(0, 2**31 - 1))
    steps = 24
    graph = random_tree(n, seed)
    names = sorted(graph.nodes)
    hostile = draw(st.sampled_from([None] + names))
    restarts = tuple(sorted(draw(st.lists(st.tuples(st.integers(2, steps), st.sampled_from(names)), max_size=1))))
    kw = {
        "seed": seed, "steps": steps, "truth": True, "guard": GuardConfig(release=draw(st.integers(1, 4))),
        "drop": draw(st.floats(0.0, 0.4)), "max_consecutive_drops": draw(st.integers(1, 3)),
        "duplicate": draw(st.floats(0.0, 0.3)), "max_latency": draw(st.sampled_from([0.0, 0.1, 0.3])),
        "send_every": draw(st.integers(1, 2)), "irregular": draw(st.booleans()),
        "outage": draw(st.sampled_from([0.0, 0.1])), "outage_steps": draw(st.integers(2, 5)), "restarts": restarts,
        "window": draw(st.sampled_from([5, 12, 50]))}
    if hostile is not None:
        kw.update(bias={hostile: HOSTILE_BIAS}, stds={hostile: HOSTILE_STD})
    return graph, kw


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(case=schedules())
def test_the_guard_on_the_critical_path_changes_no_result(monkeypatch, case):
    graph, kw = case
    fast = recorded_run(monkeypatch, graph, kw, general=False)
    slow = recorded_run(monkeypatch, graph, kw, general=True)
    assert fast[1] == slow[1]   # every message, byte for byte
    assert fast[0] == slow[0]   # every node's state, guard records and estimate after every step
    assert fast[2] == slow[2]   # the rejections
    assert fast[4] == slow[4]   # the quarantines
    assert slow[3] == {"fast": 0, "fallback": 0, "deferred": 0}


def test_guarded_messages_take_the_critical_path_and_a_quarantine_falls_back(monkeypatch):
    """Not vacuous: a chain a - b - c whose c is hostile, lossless, a message every step. Most
    messages take the critical path with the guard on, the quarantining ones fall back to the
    general path, c is quarantined, and the run equals the general path's bit for bit."""
    import networkx as nx
    graph = nx.path_graph(["a", "b", "c"])
    kw = {"seed": 3, "steps": 30, "truth": True, "guard": GuardConfig(), "drop": 0.0, "duplicate": 0.0, "max_latency": 0.0,
              "send_every": 1, "max_meas_delay": 0.0, "meas_prob": 1.0, "irregular": False, "window": 50,
              "bias": {"c": HOSTILE_BIAS}, "stds": {"c": HOSTILE_STD}}
    fast = recorded_run(monkeypatch, graph, kw, general=False)
    slow = recorded_run(monkeypatch, graph, kw, general=True)
    assert fast[:3] == slow[:3] and fast[4] == slow[4]
    assert fast[4] >= 1                       # b quarantined c (and c, holding the lie, b)
    # a fallback is a quarantine completed on the general path (other quarantining messages, not
    # steady-state ones, took it anyway)
    assert 1 <= fast[3]["fallback"] <= fast[4]
    assert fast[3]["fast"] > 50               # the guarded steady state on the critical path
    # most of them with the test left for settle(); those of a link one failure from quarantine
    # (c's, failing) tested at once
    # (here the blocks mostly reach b one step late, at a state before its newest: tested at once)
    assert fast[3]["deferred"] >= 1


def hop_run(monkeypatch, general: bool, steps: int = 160) -> tuple:
    """The hop of benchmarks/hop_cpu.py: a predicts, measures and sends, b predicts to a's time
    and fuses the message (its block at b's newest state), then b acknowledges; guards on both.
    a's sensor is 6 m off with a claimed noise of 0.2 m in steps 60-69 (b quarantines a and
    later takes it back). Returns per step b's state digest, guard records and estimate read
    right after receive (before settle), and the path counts."""
    from tests.helpers.fusion_harness import PRIOR, Q_PSD, CVTruth, make_node
    paths = {"fast": 0, "fallback": 0, "deferred": 0}
    steady = FusionNode._apply_steady

    def apply_steady(self, *args):
        done = steady(self, *args)
        paths["fast" if done is not None else "fallback"] += 1
        paths["deferred"] += done is not None and self._pending[-1] is not None
        return done

    out = []
    with monkeypatch.context() as m:
        m.setattr(FusionNode, "_apply_steady", apply_steady)
        m.setattr(FusionNode, "critical_path_first", not general)
        m.setattr(ChannelFilter, "append_plans", not general)
        a = make_node("a", ["b"], epoch=1, window=20, guard=GuardConfig(release=3))
        b = make_node("b", ["a"], epoch=2, window=20, guard=GuardConfig(release=3))
        rng = np.random.default_rng(5)
        truth = CVTruth(rng)
        assert PRIOR[0] == 0.0 and Q_PSD > 0
        for k in range(1, steps + 1):
            t = round(0.1 * k, 9)
            x = truth.at(t)
            a.predict(t)
            hostile = 60 <= k < 70
            z = x[:2] + (HOSTILE_STD if hostile else 0.5) * rng.standard_normal(2) + (HOSTILE_BIAS if hostile else 0.0)
            a.update(t, z, PositionSensor(2, HOSTILE_STD if hostile else 0.5))
            data = a.message_to("b", sent_at=t)
            a.settle()
            b.predict(t)
            b.receive(data)
            now = [v.tobytes() for v in b.estimate()]
            a.receive(b.message_to("a", sent_at=t))
            out.append((state_digest(b), guard_records(b), now, [v.tobytes() for v in b.estimate()]))
        quarantines = b.guard.links["a"].quarantines
    return out, paths, quarantines


def test_the_deferred_test_of_the_hop_changes_no_result(monkeypatch):
    """The steady-state hop (a block at the receiver's newest state): most messages leave their
    test for settle(), a link one failure from quarantine is tested at once, a hostile stretch
    quarantines a; every step bit for bit the general path's, the estimate read before settle()
    included, and equal to the estimate after it."""
    fast, paths, quarantines = hop_run(monkeypatch, general=False)
    slow, none, slow_quarantines = hop_run(monkeypatch, general=True)
    assert fast == slow
    assert none == {"fast": 0, "fallback": 0, "deferred": 0}
    assert quarantines == slow_quarantines >= 1
    assert all(now == after for _, _, now, after in fast)
    assert paths["deferred"] > 100                      # the healthy steady state: deferred
    assert paths["fast"] > paths["deferred"]            # some tested at once (a link at risk)
    assert paths["fallback"] >= 1                       # the quarantining message: the general path


@settings(max_examples=200, deadline=None)
@given(cfg=st.tuples(st.integers(1, 5), st.integers(1, 8)).filter(lambda x: x[0] <= x[1]),
       fails=st.lists(st.booleans(), max_size=40))
def test_would_quarantine_predicts_judge(cfg, fails):
    """Brute force: replay the rule (k failures among the last m tested messages; the record
    cleared at a quarantine) on a plain list, and check both methods against it at every step."""
    k, m = cfg
    guard = NeighbourGuard(["x"], GuardConfig(failures=k, window=m))
    dof = 3
    bad, good = 1e6, 0.0
    history: list[bool] = []
    for failed in fails:
        stat = bad if failed else good
        if guard.is_quarantined("x"):
            history = []
            guard.links["x"].quarantined = False   # (released: judge is called again)
        expect = sum((history + [failed])[-m:]) >= k
        tests = guard.links["x"].tests
        assert guard.would_quarantine("x", stat, dof) == expect
        assert guard.links["x"].tests == tests   # nothing recorded
        assert guard.judge("x", stat, dof) == expect
        history.append(failed)
    assert not guard.would_quarantine("x", np.inf, 0)   # nothing tested: no verdict


# ----------------------------------------------------------------------------- the one-block computations
def _random_blocks(rng, count: int):
    """Blocks of every kind the guard meets: ranks 1 to 4, negligible, removals, zero, y out of range."""
    out = []
    for _ in range(count):
        kind = int(rng.integers(6))
        A = rng.normal(size=(int(rng.integers(1, 5)), 4))
        L = A.T @ A * (1e-12 if kind == 0 else 1.0)
        if kind == 1:
            L = -L
        if kind == 2:
            L = np.zeros((4, 4))
        y = L @ rng.normal(size=4) + (rng.normal(size=4) * 1e-2 if kind == 3 else 0.0)
        B = rng.normal(size=(4, 4))
        P = B @ B.T + 0.1 * np.eye(4)
        m0 = rng.normal(size=4)
        out.append(((0.0, L, y), m0, P, m0 + 0.1 * rng.normal(size=4)))
    return out


def test_one_block_computations_equal_the_stacked_ones():
    """A steady-state message has one block: split_blocks and information_statistic take a path on
    4 x 4 matrices and Python floats for it. Against the stacked computation of the same block
    (split_blocks on two copies of it, _statistic_stacked): the same split, degrees of freedom and
    statistic (to rounding)."""
    rng = np.random.default_rng(8)
    kinds = set()
    for e, m0, P, m1 in _random_blocks(rng, 600):
        eigen = block_eigen(e[1])
        add, other = split_blocks([e], eigen)
        add2, other2 = split_blocks([e, e])
        assert (len(add), len(other)) == (len(add2) // 2, len(other2) // 2)
        assert (add, other) == split_blocks([e])
        if not add:
            continue
        ref, ref_dof = _statistic_stacked([e], [m0], [P], [m1])
        for stat, dof in (information_statistic([e], [m0], [P], [m1], eigen),
                          information_statistic([e], [m0], [P], [m1])):
            kinds.add((dof, np.isinf(stat)))
            assert dof == ref_dof
            assert stat == ref or abs(stat - ref) <= 1e-12 * max(1.0, abs(ref))
    assert {(0, False), (1, False), (4, False)} <= kinds and any(inf for _, inf in kinds)


def test_moments_of_one_block_at_the_newest_state_equal_the_smoothing_passes():
    """add_information_moments of one block at the newest state reads the filtered moments
    instead of running the smoothing passes: bit for bit what the passes give (the same block
    with a zero block at the same time takes them), and the statistic equals the dense joint
    innovation test (independent reference, tests/fusion/test_guard.py)."""
    for seed in range(5):
        rng = np.random.default_rng(seed)

        def filt(seed=seed):
            f = DelayedStateEIF(ConstantVelocity(2, q=0.2), window=30)
            r = np.random.default_rng(seed)
            f.initialize(0.0, r.normal(size=4), np.diag([2.0, 2.0, 0.5, 0.5]))
            for k in range(1, 12):
                f.predict(0.1 * k)
                if k % 3:
                    f.update(0.1 * k, r.normal(size=2) + [0.1 * k, 0.0], PositionSensor(2, 0.5))
            return f

        A = rng.normal(size=(2, 4))
        L = A.T @ A
        block = (1.1, L, L @ rng.normal(size=4))
        one, two, ref = filt(), filt(), filt()
        fast = one.add_information_moments([block])
        passes = two.add_information_moments([block, (1.1, np.zeros((4, 4)), np.zeros(4))])
        for x, y in zip(fast, passes):
            assert x[0].tobytes() == y[0].tobytes()
        assert one.checkpoint()[1] == two.checkpoint()[1]
        for x, y in zip(one.estimate(), two.estimate()):
            assert x.tobytes() == y.tobytes()
        stat, dof = information_statistic([block], *fast)
        dense, dense_dof = _dense_statistic(ref, [block])
        assert dof == dense_dof == 2
        assert stat == pytest.approx(dense, rel=1e-7)
