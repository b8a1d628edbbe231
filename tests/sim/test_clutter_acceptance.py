"""Acceptance under clutter (issue 13): with 0.3 false detections per frame at every camera (and at
least 30 % of each camera's detections false), every node's RMSE stays within 1.25 x its RMSE on the
same scenario and seed without clutter, and its ANEES <= 8; without the protections
(``protection.enabled = false``) the same runs fail.

Scenarios: the URUS demo and the three camera scenarios of ``topologies/``. Seeds are not chosen by
their results: the first three seeds (from 0) in which every camera sees the target at least 10 %
of the time (and, for the URUS square, the person stays in the WSN's 30 m x 20 m square):
``tests/helpers/clutter.py``, shared with ``benchmarks/clutter.py``.
"""
from __future__ import annotations

from functools import lru_cache

import pytest

from tests.helpers.clutter import RATE, SCENARIOS, run, seeds_for, verdict

SEEDS = 3


@lru_cache(maxsize=None)
def seeds_of(name: str) -> tuple[int, ...]:
    return tuple(seeds_for(name, SEEDS))


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_node_keeps_its_accuracy_and_consistency_under_30_percent_clutter(name):
    for seed in seeds_of(name):
        res = run(name, seed, RATE, True)
        for node, spec in res.scenario.nodes.items():
            if spec.sensor_kind == "camera":
                own = [m for m in res.world.measurements if m.node == node]
                assert sum(m.clutter for m in own) >= 0.3 * len(own), (name, seed, node)
        assert all(v["health"] != "lost" or v["track_losses"] for v in res.metrics["nodes"].values())
        ok, ratio, anees = verdict(name, seed, True)
        assert ok, (name, seed, ratio, anees)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_without_the_protections_the_same_runs_fail(name):
    """At least one of the same runs fails without the protections (the seeds in order, up to the
    first failure; benchmarks/clutter.py reports them all)."""
    assert any(not verdict(name, seed, False)[0] for seed in seeds_of(name)), name
