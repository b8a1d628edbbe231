"""A small decentralized plaza run (dfusion.sim.tracking_network): three camera nodes on a chain,
each fed only its own camera, three people, 10 s, with and without link delay. Every node tracks
every person, and its GOSPA is below a bound computed without dfusion: the GOSPA (scipy's
assignment, written out here) of an oracle that knows which detection is whose and reports,
each frame, the mean of a person's detections of that frame (absent when no camera saw them)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from dfusion.errors import ValidationError
from dfusion.fusion.tracking_node import TrackingNode
from dfusion.models import ConstantVelocity
from dfusion.sim.plaza import CameraView, PlazaConfig, plaza_cameras, simulate_plaza
from dfusion.sim.tracking_network import run_tracking_network
from dfusion.tracking import GNN, AnyDeleter, CovarianceDeleter, MofNInitiator, ObserverDeleter, RegionDeleter, StaleDeleter
from dfusion.tracking.track_to_track import TrackToTrackAssociator

C = 2.0
SETTLED = 1.0     # s: the first second (initiation) is left out of both


def gospa_p1(X: np.ndarray, Y: np.ndarray, c: float = C) -> float:
    """GOSPA (p = 1, alpha = 2): optimal assignment of min(d, c), plus c/2 per unpaired point."""
    if len(X) == 0 or len(Y) == 0:
        return c / 2 * (len(X) + len(Y))
    D = np.minimum(np.linalg.norm(X[:, None] - Y[None], axis=2), c)
    r, k = linear_sum_assignment(D)
    return float(D[r, k].sum()) + c / 2 * abs(len(X) - len(Y))


def oracle_bound(world) -> float:
    got = []
    for k, t in enumerate(world.times):
        if t < SETTLED:
            continue
        truth = np.array([x[:2] for _, x in sorted(world.truth[k].items())]).reshape(-1, 2)
        est = []
        for pid in sorted(world.truth[k]):
            zs = [f.z[f.person == pid] for f in world.frames[k]]
            zs = np.vstack([z for z in zs if len(z)]) if any(len(z) for z in zs) else np.zeros((0, 2))
            if len(zs):
                est.append(zs.mean(axis=0))
        got.append(gospa_p1(truth, np.array(est).reshape(-1, 2)))
    return float(np.mean(got))


def network(world):
    motion = ConstantVelocity(2, 0.05)
    names = [v.name for v in world.config.cameras]
    nbrs = {"cam1": ["cam2"], "cam2": ["cam1", "cam3"], "cam3": ["cam2"]}
    plaza = CameraView("plaza", 0.0, world.config.width, 0.0, world.config.height)
    return [TrackingNode(n, nbrs[n], motion, associator=GNN(), initiator=MofNInitiator(motion, velocity_std=1.5),
                         deleter=AnyDeleter(ObserverDeleter(AnyDeleter(StaleDeleter(0.45), RegionDeleter(plaza.contains))),
                                            StaleDeleter(1.5), RegionDeleter(plaza.contains, grace=0.6),
                                            CovarianceDeleter(1.0)),
                         merger=TrackToTrackAssociator(confirm=2), window=12, epoch=i + 1)
            for i, n in enumerate(names)]


@pytest.mark.parametrize("delay", [0.0, 0.2])
def test_every_node_tracks_every_person_below_an_oracle_bound(delay):
    world = simulate_plaza(PlazaConfig(n_people=3, duration=10.0, seed=5, cameras=plaza_cameras(3)))
    bound = oracle_bound(world)
    run = run_tracking_network(world, network(world), delay)
    truth = world.truth_paths()
    times = [t for t in world.times if t >= SETTLED]
    for node in ("cam1", "cam2", "cam3"):
        per_frame = []
        for t in times:
            names, X = truth.at(float(t))
            _, Y = run.history.positions(node, float(t))
            per_frame.append(gospa_p1(X, Y))
        assert np.mean(per_frame) < bound, (node, np.mean(per_frame), bound)
        assert sum(bool(run.history.at(node, float(t))) for t in times) == len(times)
    _, agreement = run.history.label_agreement(truth)
    assert agreement.agreement >= 0.98 and agreement.compared > 0.8 * 3 * len(times)
    assert run.node_cpu.shape == (len(world.times), 3) and run.bytes_sent > 0


def test_one_node_per_camera_and_links_inside_the_network():
    world = simulate_plaza(PlazaConfig(n_people=1, duration=0.3, seed=0, cameras=plaza_cameras(3)))
    nodes = network(world)
    with pytest.raises(ValidationError, match="one node per camera"):
        run_tracking_network(world, nodes[:2])
    with pytest.raises(ValidationError, match="delay"):
        run_tracking_network(world, nodes, -0.1)
    with pytest.raises(ValidationError, match="not in the network"):
        run_tracking_network(world, [nodes[0], nodes[1], TrackingNode("cam9", ["cam2"], ConstantVelocity(2, 0.05))])
