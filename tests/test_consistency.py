"""Monte Carlo consistency (NEES), rumour propagation without channel filters,
and recovery after an outage: decentralized nodes against the centralized EKF."""
from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from scipy.stats import chi2

from dfusion.sim.metrics import nees
from dfusion.sim.runner import run_scenario
from dfusion.sim.scenario import load_scenario

DATA = Path(__file__).parent / "data"
RUNS = 12


def monte_carlo_anees(fusion: str, runs: int = RUNS) -> dict[str, float]:
    """Average NEES per node over ``runs`` seeds and all time steps after the first."""
    per: dict[str, list[np.ndarray]] = {}
    for r in range(runs):
        res = run_scenario(load_scenario(DATA / "mc4.scenario.toml", seed=1000 + r, fusion=fusion))
        for name in res.node_mean:
            per.setdefault(name, []).append(nees(res.node_mean[name], res.node_cov[name], res.truth)[1:])
    return {name: float(np.mean(v)) for name, v in per.items()}


def interval(runs: int = RUNS, dof: int = 4) -> tuple[float, float]:
    # scipy's chi-square quantiles, not dfusion's helper: an independent reference
    return chi2.ppf(0.025, dof * runs) / runs, chi2.ppf(0.975, dof * runs) / runs


def test_channel_filter_nodes_are_consistent_with_30_percent_drops():
    lo, hi = interval()
    anees = monte_carlo_anees("channel")
    assert set(anees) == {"a", "b", "c", "d"}
    for name, v in anees.items():
        assert lo <= v <= hi, (name, v, (lo, hi))


def test_naive_fusion_fails_the_same_test():
    lo, hi = interval(runs=6)
    anees = monte_carlo_anees("naive", runs=6)
    for name, v in anees.items():
        assert v > hi, (name, v, hi)   # over-confident: information counted again and again


OUTAGE = {
    "duration": 50.0, "dt": 0.1, "seed": 5, "window": 400,
    "target": {"motion": "constant_velocity", "q": 0.05, "initial_mean": [0.0, 0.0, 1.0, 0.0],
               "initial_cov_diag": [1.0, 1.0, 1.0, 1.0]},
    # every sensor measures until the outage ends (35 s), then nothing new happens
    "nodes": [
        {"name": "r", "sensor": "position", "std": 1.0, "rate": 2.0, "send_period": 0.5, "active": [[0.0, 35.0]]},
        {"name": "a", "sensor": "none", "send_period": 0.5},
        {"name": "b", "sensor": "position", "std": 0.7, "rate": 5.0, "send_period": 0.5, "active": [[0.0, 35.0]]},
        {"name": "c", "sensor": "position", "std": 0.5, "rate": 5.0, "send_period": 0.5, "active": [[0.0, 35.0]]},
        {"name": "d", "sensor": "position", "std": 0.8, "rate": 5.0, "send_period": 0.5, "active": [[0.0, 35.0]]},
        {"name": "e", "sensor": "position", "std": 0.6, "rate": 5.0, "send_period": 0.5, "active": [[0.0, 35.0]]},
    ],
    "links": [
        {"between": ["r", "a"], "latency": 0.05, "outages": [[15.0, 35.0]]},
        {"between": ["r", "b"], "latency": 0.05},
        {"between": ["a", "c"], "latency": 0.05},
        {"between": ["a", "d"], "latency": 0.05},
        {"between": ["b", "e"], "latency": 0.05},
    ],
}


def test_outage_recovery_within_diameter_plus_one_send_periods():
    sc = load_scenario(OUTAGE)
    res = run_scenario(sc)
    diameter = nx.diameter(sc.graph)
    assert diameter == 4
    t = res.times
    gap = np.max([np.abs(res.node_mean[n] - res.central_mean).max(axis=1) for n in res.node_mean], axis=0)
    # during the outage the two sides disagree with the centralized estimate
    during = (t > 20.0) & (t < 35.0)
    assert gap[during].min() > 1e-3
    # both sides kept measuring: the covariance of a node beyond the cut exceeds the centralized one
    k = int(np.searchsorted(t, 34.9))
    assert np.trace(res.node_cov["c"][k]) > np.trace(res.central_cov[k]) * 1.05
    # within (diameter + 1) send periods after the link returns, every node equals it
    deadline = 35.0 + (diameter + 1) * 0.5
    after = t >= deadline
    assert after.any()
    assert gap[after].max() < 1e-6, gap[after].max()
    # and not (much) earlier: information needs the hops
    assert gap[(t > 35.0) & (t < 35.3)].max() > 1e-6
    for v in res.metrics["nodes"].values():
        assert v["final_gap"] < 1e-9
