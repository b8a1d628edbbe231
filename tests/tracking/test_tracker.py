"""The multi-target tracker (dfusion.tracking.tracker): a single target is a tracker with one track and
equals filterpy's Kalman filter; identities are deterministic; deletion; many people on the plaza."""
from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter

from dfusion.errors import ShapeError, TimeError, ValidationError
from dfusion.metrics import TrackingFrame, gospa, identity_metrics
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.sim.plaza import PlazaConfig, simulate_plaza
from dfusion.tracking import (GNN, JPDA, AnyDeleter, CovarianceDeleter, MissDeleter, MofNInitiator, MultiTargetTracker,
                              RegionDeleter, Scan, StaleDeleter, TrackId)


def tracker(assoc, origin="n", motion=None, deleter=None):
    motion = motion or ConstantVelocity(2, 0.05)
    return MultiTargetTracker(motion, assoc, MofNInitiator(motion), deleter or AnyDeleter(MissDeleter(5)), origin=origin)


@pytest.mark.parametrize("assoc", [GNN(), JPDA()], ids=["gnn", "jpda"])
def test_one_target_without_clutter_is_filterpys_kalman_filter(assoc):
    """One track, one detection per scan, (almost) no clutter: the update is the Kalman update, to 1e-9."""
    rng = np.random.default_rng(3)
    q, dt = 0.05, 0.1
    trk = tracker(assoc, motion=ConstantVelocity(2, q))
    x0, P0 = np.array([1.0, 2.0, 0.5, -0.2]), np.diag([0.5, 0.5, 1.0, 1.0])
    trk.add_track(x0, P0, 0.0)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.R = x0.copy(), P0.copy(), np.eye(2) * 0.09
    kf.F = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    Qa = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q)     # [p, v] per axis
    kf.Q = np.zeros((4, 4))
    for a in range(2):
        kf.Q[np.ix_([a, a + 2], [a, a + 2])] = Qa
    truth = x0.copy()
    for k in range(1, 41):
        truth = kf.F @ truth
        z = truth[:2] + rng.normal(0, 0.3, 2)
        kf.predict()
        kf.update(z)
        tracks = trk.step(Scan(k * dt, z[None, :], PositionSensor(2, 0.3), 0.0, 1.0))
        assert len(tracks) == 1 and tracks[0].id == TrackId("n", 0)
        mean, cov = tracks[0].estimate()
        np.testing.assert_allclose(mean, kf.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(cov, kf.P, rtol=1e-9, atol=1e-12)


def test_two_crossing_targets_keep_their_identities_with_jpda():
    rng = np.random.default_rng(0)
    trk = tracker(JPDA())
    dt = 0.1
    for k in range(1, 81):
        t = k * dt
        a, b = np.array([t, 4.0]), np.array([4.0, t])                   # cross at (4, 4) at t = 4 s
        Z = np.array([a, b]) + rng.normal(0, 0.3, (2, 2))
        tracks = trk.step(Scan(t, Z, PositionSensor(2, 0.3), 1e-3, 0.9))
    assert [tr.id.serial for tr in tracks] == [0, 1]
    ends = {tr.id.serial: tr.estimate()[0][:2] for tr in tracks}
    near_a = min(ends, key=lambda s: np.linalg.norm(ends[s] - np.array([8.0, 4.0])))
    near_b = min(ends, key=lambda s: np.linalg.norm(ends[s] - np.array([4.0, 8.0])))
    assert near_a != near_b
    assert np.linalg.norm(ends[near_a] - [8.0, 4.0]) < 0.6 and np.linalg.norm(ends[near_b] - [4.0, 8.0]) < 0.6


def test_identities_are_deterministic_and_carry_the_origin():
    world = simulate_plaza(PlazaConfig(n_people=3, duration=4.0, seed=5))
    runs = []
    for _ in range(2):
        trk = tracker(JPDA(), origin="cam7")
        ids = []
        for k in range(len(world.times)):
            for scan in world.scans(k):
                ids.append([str(tr.id) for tr in trk.step(scan)])
        runs.append(ids)
    assert runs[0] == runs[1]
    assert runs[0][-1] and all(s.startswith("cam7#") for s in runs[0][-1])


def test_deleters():
    motion = ConstantVelocity(2, 0.05)
    trk = MultiTargetTracker(motion, GNN(), MofNInitiator(motion), AnyDeleter(MissDeleter(3)), origin="n")
    trk.add_track([0, 0, 0, 0], np.eye(4) * 0.1, 0.0)
    sensor = PositionSensor(2, 0.3)
    for k in range(1, 3):
        assert len(trk.step(Scan(0.1 * k, np.zeros((0, 2)), sensor, 1e-3, 0.9))) == 1
    assert trk.step(Scan(0.3, np.zeros((0, 2)), sensor, 1e-3, 0.9)) == []          # third miss in view
    assert trk.deleted == 1
    # out of view: never missed, so only staleness (or the covariance) ends it
    trk = MultiTargetTracker(motion, GNN(), MofNInitiator(motion), AnyDeleter(MissDeleter(3), StaleDeleter(0.5)))
    trk.add_track([0, 0, 0, 0], np.eye(4) * 0.1, 0.0)
    blind = dict(sensor=sensor, clutter_density=1e-3, detection_probability=0.9, in_view=lambda x: False)
    assert len(trk.step(Scan(0.5, np.zeros((0, 2)), **blind))) == 1
    assert trk.step(Scan(0.6, np.zeros((0, 2)), **blind)) == []
    trk = MultiTargetTracker(motion, GNN(), MofNInitiator(motion), CovarianceDeleter(max_trace=1.0))
    trk.add_track([0, 0, 0, 0], np.eye(4) * 0.1, 0.0)
    assert trk.step(Scan(3.0, np.zeros((0, 2)), **blind)) == []                     # P_pos grew past 1 m^2
    trk = MultiTargetTracker(motion, GNN(), MofNInitiator(motion), RegionDeleter(lambda x: x[0] < 1.0, grace=0.15))
    trk.add_track([0.5, 0, 1.0, 0], np.eye(4) * 0.01, 0.0)
    assert len(trk.step(Scan(0.4, [[0.9, 0.0]], sensor, 1e-3, 0.9))) == 1
    assert len(trk.step(Scan(0.6, [[1.1, 0.0]], sensor, 1e-3, 0.9))) == 1          # outside, but detected
    assert len(trk.step(Scan(0.7, np.zeros((0, 2)), sensor, 1e-3, 0.9))) == 1       # outside, one miss: grace
    assert trk.step(Scan(0.8, np.zeros((0, 2)), sensor, 1e-3, 0.9)) == []           # outside, 0.2 s without a hit
    with pytest.raises(ValidationError):
        MissDeleter(0)


def test_a_track_near_the_edge_of_a_view_is_not_missed_by_that_camera():
    """Visibility: P_D is scaled by the probability of being in view; a camera that probably does not see the
    track neither updates it much nor counts a miss."""
    motion = ConstantVelocity(2, 0.05)
    trk = MultiTargetTracker(motion, JPDA(), MofNInitiator(motion), MissDeleter(2))
    trk.add_track([10.5, 0, 0, 0], np.diag([0.04, 0.04, 0.01, 0.01]), 0.0)
    edge = lambda mean, cov: 0.5 * (1 - math.erf((mean[0] - 10.0) / np.sqrt(2 * cov[0, 0])))   # view x <= 10
    sensor = PositionSensor(2, 0.3)
    for k in range(1, 6):
        tracks = trk.step(Scan(0.1 * k, np.zeros((0, 2)), sensor, 1e-3, 0.9, view_probability=edge))
        assert len(tracks) == 1 and tracks[0].misses == 0
    hyp_vis = edge(*tracks[0].estimate())
    assert 0 < hyp_vis < 0.5
    tracks = trk.step(Scan(0.6, np.zeros((0, 2)), sensor, 1e-3, 0.9))                # a camera that sees it: a miss
    assert tracks[0].misses == 1


def test_bad_scans_are_refused_without_changing_the_tracker():
    trk = tracker(GNN())
    trk.add_track([0, 0, 0, 0], np.eye(4), 0.0)
    sensor = PositionSensor(2, 0.3)
    trk.step(Scan(1.0, [[0.0, 0.0]], sensor, 1e-3, 0.9))
    before = trk.tracks[0].estimate()
    with pytest.raises(TimeError, match="older"):
        trk.step(Scan(0.5, [[0.0, 0.0]], sensor, 1e-3, 0.9))
    with pytest.raises(ShapeError):
        Scan(1.1, [[0.0, 0.0, 0.0]], sensor, 1e-3, 0.9)
    with pytest.raises(ValidationError, match="finite"):
        Scan(1.1, [[np.nan, 0.0]], sensor, 1e-3, 0.9)
    with pytest.raises(ValidationError, match="detection probability"):
        Scan(1.1, [[0.0, 0.0]], sensor, 1e-3, 1.5)
    after = trk.tracks[0].estimate()
    np.testing.assert_array_equal(before[0], after[0])


def test_the_plaza_is_tracked_better_than_by_its_raw_detections():
    """Eight people, clutter, P_D 0.9, 15 s: the tracker's GOSPA is below that of taking every detection of
    a frame as an estimate, and each person keeps mostly one identity."""
    world = simulate_plaza(PlazaConfig(n_people=8, duration=15.0, seed=11))
    trk = tracker(JPDA(), deleter=AnyDeleter(MissDeleter(5), StaleDeleter(0.45)))
    g_trk, g_raw, frames = [], [], []
    for k in range(len(world.times)):
        for scan in world.scans(k):
            trk.step(scan)
        ids, X = world.truth_positions(k)
        est = trk.estimates()
        Y = np.array([m[:2] for _, m, _ in est]).reshape(-1, 2)
        g_trk.append(gospa(X, Y).distance)
        g_raw.append(gospa(X, world.frames[k][0].z).distance)
        frames.append(TrackingFrame(ids, X, [i for i, _, _ in est], Y))
    assert np.mean(g_trk[20:]) < 0.6 * np.mean(g_raw[20:])
    assert identity_metrics(frames, 1.0).idf1 > 0.9
