"""Decentralized fusion on trees equals the centralized Kalman filter (filterpy)."""
from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.fusion_harness import Schedule, central_kalman, random_tree, run_network


def rel_err(a, b):
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


def window_from_rule(graph, s: Schedule) -> int:
    """The window rule (docs/background.md sec. 2) in states, with drops counted as extra send periods.

    window >= diameter * (max latency + send period) + max measurement delay;
    a link drops at most ``max_consecutive_drops`` messages in a row, so a hop
    takes at most latency + (drops + 1) send periods. Irregular measurement
    times insert up to one extra state per node per step: count them.
    """
    hop = s.max_latency + (s.max_consecutive_drops + 1) * s.send_every * s.dt
    seconds = nx.diameter(graph) * hop + s.max_meas_delay + 2 * s.dt
    per_step = 1 + (graph.number_of_nodes() if s.irregular else 0)
    return int(np.ceil(seconds / s.dt)) * per_step + 2


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(2, 30),
    seed=st.integers(0, 2**31 - 1),
    drop=st.floats(0.0, 0.5),
    duplicate=st.floats(0.0, 0.3),
    irregular=st.booleans(),
    long_window=st.booleans(),
)
def test_property_every_node_equals_central_kalman(n, seed, drop, duplicate, irregular, long_window):
    graph = random_tree(n, seed)
    s = Schedule(seed=seed, steps=16, drop=drop, duplicate=duplicate, irregular=irregular)
    s.window = 10_000 if long_window else window_from_rule(graph, s)
    nodes, meas, t_end = run_network(graph, s)
    mean, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        m, P = node.estimate()
        assert rel_err(m, mean) < 1e-8, (node.name, rel_err(m, mean))
        assert rel_err(P, cov) < 1e-8, (node.name, rel_err(P, cov))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_marginalizing_windows_still_exact_under_the_rule(seed):
    """A 12-node tree over 150 steps: windows far shorter than the run."""
    graph = random_tree(12, seed)
    s = Schedule(seed=seed, steps=150, drop=0.3, duplicate=0.1, irregular=False)
    s.window = window_from_rule(graph, s)
    assert s.window < 100
    nodes, meas, t_end = run_network(graph, s)
    mean, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        assert node.filter.marginalized > 0
        m, P = node.estimate()
        assert rel_err(m, mean) < 1e-8
        assert rel_err(P, cov) < 1e-8


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(2, 15), seed=st.integers(0, 2**31 - 1), window=st.integers(2, 8))
def test_property_short_windows_are_never_over_confident(n, seed, window):
    graph = random_tree(n, seed)
    s = Schedule(seed=seed, steps=30, drop=0.4, max_consecutive_drops=4, max_latency=0.5, window=window)
    nodes, meas, t_end = run_network(graph, s)
    _, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        _, P = node.estimate()
        eig = np.linalg.eigvalsh(P - cov)
        assert eig[0] >= -1e-9 * np.max(np.abs(cov)), (node.name, eig[0])


def test_naive_fusion_double_counts():
    """Without channel filters the echo makes every node over-confident."""
    graph = random_tree(5, 4)
    s = Schedule(seed=4, steps=30, drop=0.0, duplicate=0.0, fusion="naive")
    nodes, meas, t_end = run_network(graph, s)
    _, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        _, P = node.estimate()
        assert np.linalg.eigvalsh(cov - P)[-1] > 0.1 * np.trace(cov) / 4  # much tighter than truth
