"""The protocol's guarantees (issue 15) over random schedules on small trees (hypothesis).

Whatever the links do (lose, duplicate, reorder and cross messages; lose every message
in one direction for a while, so that the acknowledgements of the other direction are
lost; a node restarts as a fresh incarnation that replays its own measurements):

* never over-confident, at every step: for every node ``P_node - P_central`` is positive
  semi-definite (to rounding), ``P_central`` from filterpy's KalmanFilter given every
  measurement made so far (delivered or not);
* exact at the end: after :func:`dfusion.topology.settling_rounds` lossless rounds every
  node equals filterpy's centralized Kalman filter to 1e-9;
* the only rejected messages are those of an incarnation that was replaced (in flight
  when their sender restarted).

The schedule is :func:`tests.helpers.fusion_harness.run_network`.
"""
from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.fusion_harness import Schedule, Trace, central_kalman, random_tree, run_network

RTOL = 1e-9


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


class NeverOverConfident:
    """``on_step`` check: every node's covariance is at least the centralized one."""

    def __init__(self) -> None:
        self.steps = 0
        self.behind = 0.0      # largest eigenvalue of P_node - P_central seen (relative)

    def __call__(self, nodes, measurements, t) -> None:
        _, cov = central_kalman(measurements, t)
        scale = np.abs(cov).max()
        for node in nodes.values():
            _, P = node.estimate()
            eig = np.linalg.eigvalsh(P - cov)
            assert eig[0] >= -RTOL * scale, (node.name, t, eig[0])
            self.behind = max(self.behind, eig[-1] / scale)
        self.steps += 1


@st.composite
def schedules(draw) -> tuple:
    n = draw(st.integers(2, 7))
    seed = draw(st.integers(0, 2**31 - 1))
    steps = 24
    graph = random_tree(n, seed)
    names = sorted(graph.nodes)
    restarts = tuple(sorted(draw(st.lists(st.tuples(st.integers(2, steps), st.sampled_from(names)), max_size=2))))
    s = Schedule(
        seed=seed, steps=steps,
        drop=draw(st.floats(0.0, 0.5)),
        max_consecutive_drops=draw(st.integers(1, 4)),
        duplicate=draw(st.floats(0.0, 0.3)),
        max_latency=draw(st.sampled_from([0.0, 0.1, 0.3, 0.6])),   # 0.6 s: six steps of reordering
        send_every=draw(st.integers(1, 3)),
        irregular=draw(st.booleans()),
        outage=draw(st.sampled_from([0.0, 0.05, 0.15])),
        outage_steps=draw(st.integers(2, 8)),
        restarts=restarts,
    )
    return graph, s


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=schedules())
def test_never_over_confident_and_exact_after_settling(case):
    graph, s = case
    check = NeverOverConfident()
    s.on_step = check
    trace = Trace()
    nodes, meas, t_end = run_network(graph, s, trace=trace)
    assert check.steps == s.steps
    assert set(trace.rejections) <= {"previous-incarnation"}, trace.rejections
    if not s.restarts:
        assert not trace.rejections
    mean, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        m, P = node.estimate()
        assert rel_err(P, cov) < RTOL, (node.name, rel_err(P, cov))
        assert rel_err(m, mean) < RTOL, (node.name, rel_err(m, mean))


def test_one_way_outages_and_restarts_are_exercised():
    """The schedule is not vacuous: one-way outages and restarts happen, messages of a
    replaced incarnation arrive after its successor's and are rejected, and nodes lack
    information during the run (seed 21 is one where old messages arrive late)."""
    graph = random_tree(5, 21)
    s = Schedule(seed=21, steps=30, drop=0.2, duplicate=0.2, max_latency=0.6, outage=0.15, outage_steps=6,
                 restarts=((10, "n1"), (18, "n3")))
    check = NeverOverConfident()
    s.on_step = check
    trace = Trace()
    nodes, meas, t_end = run_network(graph, s, trace=trace)
    assert trace.outages > 5 and trace.restarted == [(10, "n1"), (18, "n3")]
    assert trace.rejections == {"previous-incarnation": 2}
    assert check.steps == 30 and check.behind > 0.01
    restarted = {"n1", "n3"}
    assert {name: node.epoch for name, node in nodes.items()} == {
        f"n{i}": 1000 * (i + 1) + (f"n{i}" in restarted) for i in range(5)}
    mean, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        assert rel_err(node.estimate()[1], cov) < RTOL
        assert rel_err(node.estimate()[0], mean) < RTOL
