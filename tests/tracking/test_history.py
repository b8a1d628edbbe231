"""TrackHistory and TruthPaths: records in time order (one per time, the last wins), Track
objects or (identity, mean, cov) tuples, a clear error for bad input; the plaza's truth
paths are its per-frame truth."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.errors import ShapeError, TimeError, ValidationError
from dfusion.models import ConstantVelocity
from dfusion.sim.plaza import PlazaConfig, simulate_plaza
from dfusion.tracking import MultiTargetTracker, TrackHistory, TrackId, TruthPaths
from dfusion.tracking.association import GNN
from dfusion.tracking.deletion import MissDeleter
from dfusion.tracking.initiation import MofNInitiator


def test_record_order_replace_and_bad_input():
    h = TrackHistory()
    a, b = TrackId("n1", 0), TrackId("n1", 1)
    h.record("n1", 0.1, [(a, [1.0, 2.0, 0, 0], np.eye(4))])
    h.record("n1", 0.1, [(a, [1.5, 2.0, 0, 0], np.eye(4)), (b, [5.0, 5.0, 0, 0], np.eye(4))])   # same time: replaces
    h.record("n2", 0.2, [])
    assert list(h.times("n1")) == [0.1] and list(h.times()) == [0.1, 0.2]
    ids, pos = h.positions("n1", 0.1)
    assert ids == [a, b] and pos.tolist() == [[1.5, 2.0], [5.0, 5.0]]
    assert h.at("n1", 0.2) == [] and h.at("n2", 0.1) == []
    with pytest.raises(TimeError, match="older"):
        h.record("n1", 0.05, [])
    with pytest.raises(ValidationError, match="twice"):
        h.record("n1", 0.3, [(a, [0.0, 0.0], np.eye(2)), (a, [1.0, 1.0], np.eye(2))])
    with pytest.raises(ShapeError):
        h.record("n1", 0.3, [(a, [0.0, 0.0, 0.0, 0.0], np.eye(2))])
    assert list(h.times("n1")) == [0.1]                    # a refused record leaves the history as it was
    # a tracker's Track objects are recorded as their estimates
    motion = ConstantVelocity(2, 0.05)
    tr = MultiTargetTracker(motion, GNN(), MofNInitiator(motion), MissDeleter(5), origin="n3")
    track = tr.add_track(np.array([1.0, 2.0, 0.5, 0.0]), np.eye(4), 0.0)
    h.record("n3", 0.0, tr.tracks)
    (tid, m, P), = h.at("n3", 0.0)
    assert tid == track.id and np.allclose(m, [1.0, 2.0, 0.5, 0.0]) and np.allclose(P, np.eye(4))


def test_truth_paths_and_the_plaza():
    truth = TruthPaths({"A": (np.array([0.0, 1.0, 2.0]), np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])),
                        "B": (np.array([1.5]), np.array([[9.0, 9.0]]))})
    names, pos = truth.at(1.5)
    assert names == ["A", "B"] and pos.tolist() == [[2.0, 0.0], [9.0, 9.0]]
    assert truth.at(2.5)[0] == [] and truth.at(0.0)[0] == ["A"]
    with pytest.raises(TimeError):
        TruthPaths({"A": (np.array([1.0, 1.0]), np.zeros((2, 2)))})
    world = simulate_plaza(PlazaConfig(n_people=4, duration=3.0, seed=1))
    paths = world.truth_paths()
    for k, t in enumerate(world.times):
        ids, xy = world.truth_positions(k)
        names, pos = paths.at(float(t))
        assert names == [f"person {i}" for i in ids]
        np.testing.assert_array_equal(pos, xy)
