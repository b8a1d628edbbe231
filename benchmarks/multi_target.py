"""Multi-target tracking on the plaza: dfusion's centralized tracker (JPDA, GNN) beside Stone Soup's.

On identical detections (``dfusion.sim.plaza``: 40 x 30 m, people crossing, births and
deaths at the edges, 10 Hz, std 0.3 m, P_D 0.9, 3 false detections per frame per plaza
area), for each seed and camera layout (one view of the whole plaza; three cameras with
overlapping views, fed one scan per camera in turn):

* dfusion ``MultiTargetTracker`` with JPDA (EHM) and with GNN, M-of-N two-point initiation,
  miss / staleness deletion;
* Stone Soup 1.9.1 ``JPDAwithEHM`` with ``MultiTargetMixtureTracker`` and
  ``GNNWith2DAssignment`` with ``MultiTargetTracker`` (its tutorials' components:
  ``PDAHypothesiser`` / ``DistanceHypothesiser``, ``MultiMeasurementInitiator``,
  ``CovarianceBasedDeleter``), with the same motion model, noise, P_D, clutter density and gate.

Metrics per frame after every scan of the frame: GOSPA (c = 2 m, p = 1, alpha = 2) and its
parts, CLEAR MOT / IDF1 (match within 1 m), CPU time (``time.process_time``) of the
tracker per frame. A second table: dfusion's CPU per frame against the number of people.

Stone Soup is not a dependency of dfusion: this script installs it into the running
interpreter's environment with pip (``stonesoup==1.9.1``) when it is missing.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import gc
import importlib
import os
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dfusion.fusion.tracking_node import TrackingNode
from dfusion.metrics import gospa, identity_metrics
from dfusion.models import ConstantVelocity
from dfusion.sim.plaza import CameraView, PlazaConfig, PlazaWorld, plaza_cameras, simulate_plaza
from dfusion.sim.tracking_network import TrackingNetworkRun, run_tracking_network
from dfusion.tracking import (GNN, JPDA, AnyDeleter, CovarianceDeleter, MissDeleter, MofNInitiator, MultiTargetTracker, ObserverDeleter,
                              RegionDeleter, StaleDeleter, TrackHistory)
from dfusion.tracking.track_to_track import TrackToTrackAssociator
from dfusion.viz import plot_identity_timeline, plot_tracks_topdown, record_tracks_mcap

#: One setting for the family (chosen once on seed 0 of the one-view layout, never per seed).
Q = 0.05                # acceleration noise spectral density of every tracker's motion model (m^2/s^3)
GATE = 0.99
VELOCITY_STD = 1.5      # prior std of a person's velocity per axis (m/s), for both libraries' initiators
C, P_ORDER, MATCH = 2.0, 1.0, 1.0
STONESOUP = "stonesoup==1.9.1"
NODE = "central"        # the one (centralized) node of every tracker's history
#: The decentralized network's settings (chosen once, for every seed, layout and link delay).
DELAYS = (0.0, 0.2)     # link delays (s) of the decentralized runs and of Stone Soup's network
NET_MAX_AGE = 0.45      # s since the fused track's newest information, judged by the nodes that saw it lately
NET_OBSERVER = 1.0      # s: a node whose own scans hit a track within this judges its staleness
NET_FALLBACK_AGE = 1.5  # s: every node ends a track whose newest information is this old (no observer left)
NET_REGION_GRACE = 0.6  # s: every node ends a track out of the plaza with no information for this (> the latency)
NET_MAX_TRACE = 1.0     # m^2: every node ends a track whose fused position covariance has a larger trace
NET_WINDOW = 12         # delayed states per track (1.2 s at 10 Hz: a message of two hops at 0.2 s fits)
NET_CONFIRM = 2         # consecutive close checks before two tracks are declared one person
NET_MERGE_DISTANCE = 1.5
FUSION = "fusion"       # the fusion node of Stone Soup's network


def ensure_stonesoup() -> None:
    try:
        importlib.import_module("stonesoup")
    except ImportError:
        print(f"installing {STONESOUP} (benchmark only, not a dfusion dependency) ...", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", STONESOUP], check=True)
        importlib.invalidate_caches()


# --- trackers: each maps a world to its tracks over time (a TrackHistory) and CPU seconds per frame ------------


def run_dfusion(world: PlazaWorld, association: str) -> tuple[TrackHistory, np.ndarray]:
    motion = ConstantVelocity(2, Q)
    c = world.config
    whole = CameraView("plaza", 0.0, c.width, 0.0, c.height)

    def plaza(x: np.ndarray) -> bool:
        return whole.contains(x)

    tracker = MultiTargetTracker(motion, JPDA() if association == "jpda" else GNN(),
                                 MofNInitiator(motion, m=3, n=5, gate=GATE, velocity_std=VELOCITY_STD),
                                 AnyDeleter(MissDeleter(5), StaleDeleter(0.45), RegionDeleter(plaza)), origin="central")
    history, cpu = TrackHistory(), np.zeros(len(world.times))
    for k in range(len(world.times)):
        scans = world.scans(k)
        t0 = time.process_time()
        for scan in scans:
            tracker.step(scan)
        cpu[k] = time.process_time() - t0
        history.record(NODE, float(world.times[k]), tracker.estimates())
    return history, cpu


def _stonesoup_parts(world: PlazaWorld):
    """Stone Soup's models and the time stamps of the frames."""
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.updater.kalman import KalmanUpdater

    c = world.config
    transition = CombinedLinearGaussianTransitionModel([SSConstantVelocity(Q), SSConstantVelocity(Q)])
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2) * c.std**2)
    epoch = _dt.datetime(2026, 1, 1)
    stamps = [epoch + _dt.timedelta(seconds=float(t)) for t in world.times]
    return transition, measurement, KalmanPredictor(transition), KalmanUpdater(measurement), stamps


def _stonesoup_tracker(world: PlazaWorld, association: str, cameras: list[int]):
    """Stone Soup's tracker (JPDA with EHM, or GNN; its tutorials' components) fed the scans of
    ``cameras`` (indices into the layout), one scan per camera in turn."""
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.dataassociator.probability import JPDAwithEHM
    from stonesoup.deleter.error import CovarianceBasedDeleter
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.tracker.simple import MultiTargetMixtureTracker, MultiTargetTracker as SSMultiTargetTracker
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState

    c = world.config
    _, measurement, predictor, updater, stamps = _stonesoup_parts(world)

    def scans():
        for k, frames in enumerate(world.frames):
            for i in cameras:
                yield stamps[k], {Detection(z.reshape(2, 1), timestamp=stamps[k], measurement_model=measurement)
                                  for z in frames[i].z}

    deleter = CovarianceBasedDeleter(covar_trace_thresh=1.0, mapping=[0, 2])
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([0.0, VELOCITY_STD**2, 0.0, VELOCITY_STD**2])),
        measurement_model=measurement, deleter=UpdateTimeStepsDeleter(3 * len(cameras)),
        data_associator=GNNWith2DAssignment(DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=3)),
        updater=updater, min_points=3)
    if association == "jpda":
        hyp = PDAHypothesiser(predictor, updater, c.clutter_density, prob_detect=c.detection, prob_gate=GATE)
        return MultiTargetMixtureTracker(initiator=initiator, deleter=deleter, detector=scans(),
                                         data_associator=JPDAwithEHM(hyp), updater=updater)
    hyp = DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=3)
    return SSMultiTargetTracker(initiator=initiator, deleter=deleter, detector=scans(),
                                data_associator=GNNWith2DAssignment(hyp), updater=updater)


_SS_ORDER = [0, 2, 1, 3]      # Stone Soup's [x, vx, y, vy] -> [x, y, vx, vy]


def _stonesoup_estimates(tracks) -> list:
    return [(x.id, np.asarray(x.state_vector, float).ravel()[_SS_ORDER],
             np.asarray(x.covar, float)[np.ix_(_SS_ORDER, _SS_ORDER)]) for x in sorted(tracks, key=lambda x: x.id)]


def run_stonesoup(world: PlazaWorld, association: str) -> tuple[TrackHistory, np.ndarray]:
    per_frame = len(world.config.cameras)
    it = iter(_stonesoup_tracker(world, association, list(range(per_frame))))
    history, cpu = TrackHistory(), np.zeros(len(world.times))
    for k in range(len(world.times)):
        t0 = time.process_time()
        for _ in range(per_frame):
            _, tracks = next(it)
        cpu[k] = time.process_time() - t0
        history.record(NODE, float(world.times[k]), _stonesoup_estimates(tracks))
    return history, cpu


def run_stonesoup_network(world: PlazaWorld, delay: float) -> tuple[TrackHistory, np.ndarray]:
    """Stone Soup's network architecture: one sensor node per camera (a JPDA tracker, as above,
    fed that camera's scans alone) and one fusion node, as in Stone Soup's architecture tutorials
    (``stonesoup.architecture``: a fusion node's ``MultiTargetTracker`` with GNN on Mahalanobis
    distance, ``Tracks2GaussianDetectionFeeder`` turning the sensor nodes' tracks into
    ``GaussianDetection``s, ``DetectionAndTrackSwitchingUpdater`` with ``ChernoffUpdater``
    (covariance intersection) for tracks, ``MultiMeasurementInitiator``, ``UpdateTimeStepsDeleter``).
    Every frame each sensor node sends its tracks; the fusion node takes them ``delay`` seconds
    later, one sensor at a time, and its tracks (at the time of the tracks it fused: not brought
    forward) are the network's picture. Driven frame by frame in one thread (the architecture
    classes run each fusion node's tracker in a thread and take their detections from their own
    sensor models; here every tracker is fed the benchmark's identical detections)."""
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.feeder.track import Tracks2GaussianDetectionFeeder
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.tracker.simple import MultiTargetTracker as SSMultiTargetTracker
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track as SSTrack
    from stonesoup.updater.chernoff import ChernoffUpdater
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.wrapper import DetectionAndTrackSwitchingUpdater

    n = len(world.config.cameras)
    _, _, predictor, _, stamps = _stonesoup_parts(world)
    sensors = [iter(_stonesoup_tracker(world, "jpda", [i])) for i in range(n)]
    inbox: deque = deque()

    def received():
        while inbox:
            yield inbox.popleft()

    updater = DetectionAndTrackSwitchingUpdater(None, KalmanUpdater(None), ChernoffUpdater(None))
    associator = GNNWith2DAssignment(DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=3))
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([0.0, VELOCITY_STD**2, 0.0, VELOCITY_STD**2])),
        measurement_model=None, deleter=UpdateTimeStepsDeleter(n), data_associator=associator, updater=updater,
        min_points=2)
    fusion = SSMultiTargetTracker(initiator=initiator, deleter=UpdateTimeStepsDeleter(3 * n),
                                  detector=Tracks2GaussianDetectionFeeder(received()), data_associator=associator,
                                  updater=updater)
    fused = iter(fusion)
    in_flight: list = []
    tracks: set = set()
    history, cpu = TrackHistory(), np.zeros(len(world.times))
    for k in range(len(world.times)):
        t = float(world.times[k])
        t0 = time.process_time()
        for i, it in enumerate(sensors):
            stamp, local = next(it)
            # the message: a snapshot of the sensor node's tracks (their states now)
            in_flight.append((t + delay, k, i, stamp, {SSTrack([x.state], id=x.id) for x in local}))
        arrived = [m for m in in_flight if m[0] <= t + 1e-9]
        in_flight = [m for m in in_flight if m[0] > t + 1e-9]
        for _, _, _, stamp, snapshot in sorted(arrived, key=lambda m: (m[1], m[2])):
            inbox.append((stamp, snapshot))
            _, tracks = next(fused)
        cpu[k] = time.process_time() - t0
        history.record(FUSION, t, _stonesoup_estimates(tracks))
    return history, cpu


def camera_tree(names: list[str]) -> list[tuple[str, str]]:
    """The decentralized network's tree: a star around a middle camera (with three cameras, the
    chain cam1 - cam2 - cam3; with six, cam2, the middle of the row y in [0, 17] m, linked to
    every other camera)."""
    hub = names[(len(names) - 1) // 2] if len(names) <= 3 else names[1]
    return [(hub, x) for x in names if x != hub]


def run_decentralized(world: PlazaWorld, delay: float, association: str = "jpda") -> tuple[TrackHistory, np.ndarray,
                                                                                           TrackingNetworkRun]:
    """One :class:`~dfusion.fusion.tracking_node.TrackingNode` per camera, each fed only its own
    camera's scans, on :func:`camera_tree`; every frame every node sends each neighbour a bundle,
    delivered ``delay`` seconds later (:func:`dfusion.sim.tracking_network.run_tracking_network`:
    in-process, lossless, in order). Deletion by rules on the fused track, the same at every
    node: no information from any node for ``NET_MAX_AGE`` s, or out of the plaza with no
    information for 0.15 s (``StaleDeleter``, ``RegionDeleter``), judged by the nodes whose own
    scans hit the track within ``NET_OBSERVER`` s (``ObserverDeleter``: a node far from the
    track hears its information late by the tree's latency, and would end a track whose
    estimate strays over the border while its person walks along it); any node ends a track
    with no information for ``NET_FALLBACK_AGE`` s. The initiator, the associator and the gate
    are the centralized tracker's. Every node also ends a track out of the plaza with no
    information for ``NET_REGION_GRACE`` s (above the latency) and a track whose fused position
    covariance has a trace above ``NET_MAX_TRACE``: a track's newest information counts the
    PDA factors of scans that probably missed it, so a track lost outside every view, fed
    by clutter in its growing gate, never looks stale; its covariance shows it."""
    c = world.config
    motion = ConstantVelocity(2, Q)
    names = [v.name for v in c.cameras]
    edges = camera_tree(names)
    nbrs = {n: sorted({a if b == n else b for a, b in edges if n in (a, b)}) for n in names}
    whole = CameraView("plaza", 0.0, c.width, 0.0, c.height)
    nodes = [TrackingNode(n, nbrs[n], motion, associator=JPDA() if association == "jpda" else GNN(),
                          initiator=MofNInitiator(motion, m=3, n=5, gate=GATE, velocity_std=VELOCITY_STD),
                          deleter=AnyDeleter(ObserverDeleter(AnyDeleter(StaleDeleter(NET_MAX_AGE),
                                                                        RegionDeleter(whole.contains)), NET_OBSERVER),
                                             StaleDeleter(NET_FALLBACK_AGE),
                                             RegionDeleter(whole.contains, grace=NET_REGION_GRACE),
                                             CovarianceDeleter(NET_MAX_TRACE)),
                          merger=TrackToTrackAssociator(gate=GATE, confirm=NET_CONFIRM, max_distance=NET_MERGE_DISTANCE),
                          window=NET_WINDOW, epoch=i + 1)
             for i, n in enumerate(names)]
    run = run_tracking_network(world, nodes, delay)
    return run.history, run.network_cpu, run


def trackers(cameras: int, stonesoup: bool, gnn: bool = True) -> dict:
    """The trackers of a layout: name -> function(world) -> (TrackHistory, CPU s per frame, TrackingNetworkRun or None).
    The networks (dfusion decentralized, Stone Soup's sensor nodes + fusion node) need several cameras;
    ``gnn=False`` leaves out the centralized GNN trackers."""
    out = {"dfusion JPDA": lambda w: (*run_dfusion(w, "jpda"), None)}
    if gnn:
        out["dfusion GNN"] = lambda w: (*run_dfusion(w, "gnn"), None)
    if stonesoup:
        out["Stone Soup JPDA (EHM)"] = lambda w: (*run_stonesoup(w, "jpda"), None)
        if gnn:
            out["Stone Soup GNN"] = lambda w: (*run_stonesoup(w, "gnn"), None)
    if cameras > 1:
        for d in DELAYS:
            out[decentralized_name(d)] = lambda w, d=d: run_decentralized(w, d)
            if stonesoup:
                out[stonesoup_network_name(cameras, d)] = lambda w, d=d: (*run_stonesoup_network(w, d), None)
    return out


def decentralized_name(delay: float) -> str:
    return f"dfusion decentralized JPDA, delay {delay:g} s"


def stonesoup_network_name(cameras: int, delay: float) -> str:
    return f"Stone Soup network {cameras}+1, delay {delay:g} s"


@dataclass
class Row:
    layout: str
    seed: int
    tracker: str
    node: str
    gospa: float
    loc: float
    missed: float
    false: float
    idf1: float
    mota: float
    switches: int
    cpu_ms: float               # the whole tracker's (network's) CPU per frame
    targets: float
    agreement: float | None = None      # network label agreement (several nodes)
    node_cpu_ms: float | None = None    # this node's CPU per frame (decentralized)


def evaluate(layout: str, seed: int, name: str, run, world: PlazaWorld) -> tuple[list[Row], TrackHistory]:
    """One Row per node of the tracker's history (the metrics of each node's tracks against the truth)."""
    gc.collect()
    history, cpu, net = run(world)
    truth = world.truth_paths()
    agreement = None
    if len(history.nodes) > 1:
        agreement = history.label_agreement(truth, MATCH)[1].agreement
    rows = []
    for i, node in enumerate(history.nodes):
        frames = history.frames(node, truth, world.times)
        parts = np.array([[g.distance, g.localization, g.missed, g.false] for g in
                          (gospa(f.truth, f.tracks, C, P_ORDER) for f in frames)])
        ids = identity_metrics(frames, MATCH)
        mean = parts.mean(axis=0)
        rows.append(Row(layout, seed, name, node, *mean, ids.idf1, ids.mota, ids.switches, 1e3 * float(np.mean(cpu)),
                        float(np.mean([len(t) for t in world.truth])), agreement,
                        None if net is None else 1e3 * float(np.mean(net.node_cpu[:, i]))))
    return rows, history


def save_figures(directory: Path, layout: str, name: str, world: PlazaWorld, history: TrackHistory) -> None:
    """The top-down view, the identity timeline and the MCAP recording of one run (``--figures``)."""
    c = world.config
    stem = f"{name.split(' (')[0].replace(' ', '-').lower()}_{layout.replace(' ', '-')}_seed{c.seed}"
    truth = world.truth_paths()
    what = f"{name}, {layout}, seed {c.seed}, {c.duration:.0f} s"
    views = c.cameras if len(c.cameras) > 1 else ()          # one view is the whole plaza: its outline
    paths = [plot_tracks_topdown(history, truth, directory / f"topdown_{stem}.png", views=views,
                                 region=(0.0, c.width, 0.0, c.height), title=f"{what}: tracks and truth, top-down"),
             plot_identity_timeline(history, truth, directory / f"timeline_{stem}.png", threshold=MATCH,
                                    title=f"{what}: identity timeline (a track is on a person within {MATCH:g} m)")[0],
             record_tracks_mcap(history, directory / f"tracks_{stem}.mcap", truth, views=views)]
    print("wrote " + ", ".join(str(p) for p in paths))


def accuracy_table(rows: list[Row]) -> None:
    print("| layout | seed | tracker | node | GOSPA (m) | localization | missed | false | IDF1 | MOTA | switches | "
          "label agreement | CPU/frame (ms) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        agree = "-" if r.agreement is None else f"{r.agreement:.4f}"
        print(f"| {r.layout} | {r.seed} | {r.tracker} | {r.node} | {r.gospa:.3f} | {r.loc:.3f} | {r.missed:.3f} | "
              f"{r.false:.3f} | {r.idf1:.3f} | {r.mota:.3f} | {r.switches} | {agree} | {r.cpu_ms:.2f} |")


def summary(rows: list[Row], strict: bool) -> bool:
    ok = True
    goals = []
    print("\n| layout | tracker | mean GOSPA (m) | GOSPA / Stone Soup JPDA (per seed) | IDF1 (min) | switches (total) | CPU/frame (ms) | CPU / Stone Soup JPDA |")
    print("|---|---|---|---|---|---|---|---|")
    for layout in dict.fromkeys(r.layout for r in rows):
        ref = {r.seed: r for r in rows if r.layout == layout and r.tracker == "Stone Soup JPDA (EHM)"}
        for name in dict.fromkeys(r.tracker for r in rows if r.node == NODE):
            rs = [r for r in rows if r.layout == layout and r.tracker == name]
            if not rs:
                continue
            ratios = [r.gospa / ref[r.seed].gospa for r in rs if r.seed in ref]
            cpu_ratio = (f"{np.median([r.cpu_ms / ref[r.seed].cpu_ms for r in rs if r.seed in ref]):.2f}" if ref
                         else "- (no Stone Soup run)")
            print(f"| {layout} | {name} | {np.mean([r.gospa for r in rs]):.3f} | "
                  f"{' / '.join(f'{x:.2f}' for x in ratios) or '-'} | {min(r.idf1 for r in rs):.3f} | "
                  f"{sum(r.switches for r in rs)} | {np.mean([r.cpu_ms for r in rs]):.2f} | {cpu_ratio} |")
            if name == "dfusion JPDA" and ref:
                good_gospa = max(ratios) <= 0.95
                good_switches = all(r.switches <= ref[r.seed].switches for r in rs if r.seed in ref)
                ok &= good_gospa and good_switches
                goals.append(f"goal ({layout}): dfusion JPDA GOSPA <= 0.95 x Stone Soup JPDA on every seed: "
                      f"{'PASS' if good_gospa else 'FAIL'}; identity switches <= Stone Soup JPDA's on every seed "
                      f"({' / '.join(f'{r.switches} vs {ref[r.seed].switches}' for r in rs if r.seed in ref)}): "
                      f"{'PASS' if good_switches else 'FAIL'}")
    print("\n".join(["", *goals]))
    return ok


def network_summary(rows: list[Row]) -> bool:
    """The networks per layout and link delay: every node of dfusion's decentralized network, the
    fusion node of Stone Soup's, against Stone Soup's centralized JPDA on the same detections;
    the goals of issue 24."""
    ok = True
    goals = []
    print("\n| layout | network | node | mean GOSPA (m) | GOSPA / Stone Soup JPDA (per seed) | IDF1 (per seed) | "
          "switches (per seed; Stone Soup JPDA's) | label agreement (per seed) | node CPU/frame (ms) | "
          "network CPU/frame (ms) | network CPU / Stone Soup network |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for layout in dict.fromkeys(r.layout for r in rows):
        ref = {r.seed: r for r in rows if r.layout == layout and r.tracker == "Stone Soup JPDA (EHM)"}
        ncam = int(layout.split()[0])
        for d in DELAYS:
            dec = [r for r in rows if r.layout == layout and r.tracker == decentralized_name(d)]
            ssn = [r for r in rows if r.layout == layout and r.tracker == stonesoup_network_name(ncam, d)]
            ss_cpu = {r.seed: r.cpu_ms for r in ssn}
            for name, rs in ((decentralized_name(d), dec), (stonesoup_network_name(ncam, d), ssn)):
                for node in dict.fromkeys(r.node for r in rs):
                    nr = [r for r in rs if r.node == node]
                    ratios = [r.gospa / ref[r.seed].gospa for r in nr if r.seed in ref]
                    cpu_ratio = [r.cpu_ms / ss_cpu[r.seed] for r in nr if r.seed in ss_cpu]
                    agree = " / ".join("-" if r.agreement is None else f"{r.agreement:.4f}" for r in nr)
                    node_cpu = "-" if nr[0].node_cpu_ms is None else f"{np.mean([r.node_cpu_ms for r in nr]):.2f}"
                    print(f"| {layout} | {name} | {node} | {np.mean([r.gospa for r in nr]):.3f} | "
                          f"{' / '.join(f'{x:.2f}' for x in ratios) or '-'} | "
                          f"{' / '.join(f'{r.idf1:.3f}' for r in nr)} | "
                          f"{' / '.join(f'{r.switches} ({ref[r.seed].switches})' if r.seed in ref else str(r.switches) for r in nr)} | "
                          f"{agree} | {node_cpu} | {np.mean([r.cpu_ms for r in nr]):.2f} | "
                          f"{' / '.join(f'{x:.2f}' for x in cpu_ratio) or '-'} |")
            if not dec:
                continue
            what = f"({layout}, delay {d:g} s)"
            checks = []
            if ref:
                worst = max(r.gospa / ref[r.seed].gospa for r in dec if r.seed in ref)
                checks.append((f"every node's GOSPA <= 0.95 x Stone Soup JPDA's on every seed (worst {worst:.2f})",
                               worst <= 0.95))
                extra = [f"{r.node} seed {r.seed}: {r.switches} vs {ref[r.seed].switches}" for r in dec
                         if r.seed in ref and r.switches > ref[r.seed].switches]
                checks.append(("every node's identity switches <= Stone Soup JPDA's on every seed"
                               + (f" (over: {', '.join(extra)})" if extra else ""), not extra))
            low = min(r.idf1 for r in dec)
            checks.append((f"every node's IDF1 >= 0.97 (lowest {low:.3f})", low >= 0.97))
            agree = min(r.agreement for r in dec)
            checks.append((f"label agreement >= 0.99 on every seed (lowest {agree:.4f})", agree >= 0.99))
            if ss_cpu:
                ratio = max(r.cpu_ms / ss_cpu[r.seed] for r in dec if r.seed in ss_cpu)
                checks.append((f"network CPU <= 0.5 x Stone Soup's {ncam}+1 network on every seed (worst {ratio:.2f})",
                               ratio <= 0.5))
            for text, good in checks:
                ok &= good
                goals.append(f"goal {what}: {text}: {'PASS' if good else 'FAIL'}")
    print("\n".join(["", *goals]))
    return ok


def scaling_table(people: list[int], duration: float, seed: int) -> bool:
    """CPU per frame against the number of people: the centralized trackers (one view) and a node
    of the decentralized network (three camera nodes, no link delay; the mean over the nodes and the
    busiest node, the hub)."""
    print("\n| people (set) | targets present (mean) | tracker | CPU/frame (ms) | CPU per target (ms) |")
    print("|---|---|---|---|---|")
    per_target = {}
    for n in people:
        world = simulate_plaza(PlazaConfig(n_people=n, duration=duration, seed=seed))
        present = float(np.mean([len(t) for t in world.truth]))
        measured = {}
        for name, association in (("dfusion JPDA", "jpda"), ("dfusion GNN", "gnn")):
            gc.collect()
            measured[name] = 1e3 * float(np.mean(run_dfusion(world, association)[1]))
        world3 = simulate_plaza(PlazaConfig(n_people=n, duration=duration, seed=seed, cameras=plaza_cameras(3)))
        present3 = float(np.mean([len(t) for t in world3.truth]))
        gc.collect()
        net = run_decentralized(world3, 0.0)[2]
        node_ms = 1e3 * net.node_cpu.mean(axis=0)
        measured["decentralized JPDA, a node of 3 (mean)"] = float(node_ms.mean())
        measured["decentralized JPDA, a node of 3 (hub)"] = float(node_ms.max())
        for name, ms in measured.items():
            k = present3 if name.startswith("decentralized") else present
            per_target.setdefault(name, []).append(ms / max(k, 1.0))
            print(f"| {n} | {k:.1f} | {name} | {ms:.2f} | {ms / max(k, 1.0):.3f} |")
    ok = True
    for name, v in per_target.items():
        growth = v[-1] / min(v)
        good = growth <= 1.5
        ok &= good
        print(f"goal: {name} CPU per target at {people[-1]} people <= 1.5 x its smallest (at most linear): "
              f"{growth:.2f} {'PASS' if good else 'FAIL'}")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, 10 s, small scaling table")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--people", type=int, default=8)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--cameras", type=int, nargs="+", default=[1, 3, 6],
                    help="camera layouts (1, 3 or 6 views; the networks run on layouts of several cameras)")
    ap.add_argument("--no-stonesoup", action="store_true", help="dfusion only")
    ap.add_argument("--no-scaling", action="store_true", help="skip the table of CPU against the number of people")
    ap.add_argument("--no-gnn", action="store_true",
                    help="leave out the centralized GNN trackers (the networks are compared with the JPDA ones)")
    ap.add_argument("--strict", action="store_true", help="exit status 1 when a goal is not met")
    ap.add_argument("--figures", type=Path, metavar="DIR",
                    help="save the top-down view, the identity timeline (PNG) and the tracks (MCAP) of every "
                         "dfusion tracker on seed 0 of each layout to DIR")
    args = ap.parse_args()
    seeds = 1 if args.quick else args.seeds
    duration = 10.0 if args.quick else args.duration
    print(f"load average at start: {os.getloadavg()[0]:.2f}; python {sys.version.split()[0]}, numpy {np.__version__}")
    if not args.no_stonesoup:
        ensure_stonesoup()
        import stonesoup
        print(f"stonesoup {stonesoup.__version__}")
    rows = []
    for ncam in args.cameras:
        layout = "1 view" if ncam == 1 else f"{ncam} cameras"
        runs = trackers(ncam, not args.no_stonesoup, not args.no_gnn)
        for seed in range(seeds):
            world = simulate_plaza(PlazaConfig(n_people=args.people, duration=duration, seed=seed,
                                               cameras=plaza_cameras(ncam)))
            for name, run in runs.items():
                got, history = evaluate(layout, seed, name, run, world)
                rows.extend(got)
                print(f"  {layout}, seed {seed}, {name}: mean GOSPA {np.mean([r.gospa for r in got]):.3f} m, "
                      f"{got[0].cpu_ms:.1f} ms/frame", flush=True)
                if args.figures is not None and seed == 0 and name.startswith("dfusion"):
                    save_figures(args.figures, layout, name, world, history)
    print(f"\n{args.people} people set, {duration:.0f} s, 10 Hz, std 0.3 m, P_D 0.9, 3 false per frame per plaza area; "
          f"mean targets present {np.mean([r.targets for r in rows]):.1f}; GOSPA c = {C} m, p = {P_ORDER:g}, "
          f"alpha = 2; match within {MATCH} m; networks on a star around the middle camera (3 cameras: the chain "
          f"cam1 - cam2 - cam3), messages every frame, link delays {', '.join(f'{d:g}' for d in DELAYS)} s\n")
    accuracy_table(rows)
    ok = summary(rows, args.strict)
    ok &= network_summary(rows)
    if not args.no_scaling:
        ok &= scaling_table([2, 5, 10] if args.quick else [1, 5, 10, 20, 30], 5.0 if args.quick else 20.0, 0)
    return 1 if (args.strict and not ok) else 0


if __name__ == "__main__":
    sys.exit(main())
