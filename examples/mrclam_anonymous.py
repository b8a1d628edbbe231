#!/usr/bin/env python
r"""MRCLAM as a multi-target problem: every robot tracks every other robot from its own ANONYMOUS sightings.

Usage::

    python examples/mrclam_anonymous.py DATASET_DIR [--duration S] [--associator gnn|jpda] [--json OUT]
    python examples/mrclam_anonymous.py DATASET_DIR --network [--no-recovery] [--no-exclude-self] ...

``DATASET_DIR`` is an MRCLAM dataset directory (``MRCLAM_Dataset6``; where to get it:
``tests/data/mrclam/README.md``; the 180 s slice ``tests/data/mrclam`` runs as is).

Each of the five robots (the observer):

1. **localizes itself** exactly as in ``examples/mrclam_tracking.py``: a
   :class:`~dfusion.localization.LandmarkEKF` on its velocity odometry and its
   range-bearing sightings of the 15 landmarks (landmarks keep their barcodes: they are
   the map), robust updates ``POSE_MONITOR``, started at its true pose with 5 cm / 0.05 rad;
2. **tracks the four other robots** with a :class:`~dfusion.tracking.MultiTargetTracker`
   from its sightings of robots **with the barcode removed**: each camera frame's robot
   sightings become one scan of world-frame position detections
   (:func:`dfusion.tracking.sightings_scan`: ``p = s_xy + r (cos, sin)(theta_s + b)`` with
   the covariance ``G R G^T + J P_s J^T`` of the sighting noise and of the observer's pose
   covariance ``P_s``, by linearization), which the tracker associates with its tracks
   (GNN by default, or JPDA) within a 0.999 chi-square gate. The team is known: four
   tracks start at time 0 from the other robots' true start positions with 0.3 m per
   axis and zero velocity with 0.1 m/s (the prior of the single-target run), are never
   deleted, and no track is started from the sightings
   (:class:`~dfusion.tracking.NoInitiator`, :class:`~dfusion.tracking.NoDeleter`). The
   start positions are the only identity information: after time 0 nothing says which
   sighting is which robot. Constant-velocity tracks, ``q = 1e-4 m^2/s^3`` (the
   single-target cv model's), detection probability 0.4 for a robot in the camera's view
   (bearing within 0.6 rad, range 0.9-8.7 m; the view probability integrates the track's
   position uncertainty), 1e-3 false sightings per m^2 per frame.

**The team** (rows ``team``): one tracker of all five robots given every robot's sightings
in time order (each converted from its own robot's estimated pose; a robot's own track is not
in its camera's view, being closer than the minimum range): the centralized reference that a
network of robots fusing their tracks would approach, and the like-for-like comparison with
the single-target result of ``examples/mrclam_tracking.py``, which fuses four observers.

**The network** (``--network``, rows ``network``): every robot a
:class:`~dfusion.fusion.TrackingNode` of the chain 1 - 2 - 3 - 4 - 5, fed only its own
robot's sighting scans (with its own pose covariance), every node adding the same five start
tracks (:meth:`TrackingNode.add_track`: the start position, 0.3 m, zero velocity with
``sigma``), bundles exchanged every 0.5 s in process (no delay), no initiator, no deleter,
no merges (the team is known). A node associates its scans with its **fused** tracks, so
every node tracks all five robots, also those it never sees, under identities the nodes
share. Its own track takes no part in the association of its own sightings (a robot's
camera never sees the robot itself; ``--no-exclude-self``). Lock-out recovery
(``--no-recovery`` turns it off): anonymous, :class:`~dfusion.frontends.TeamSightingsFrontEnd`
(k = 5 agreeing detections outside every gate re-acquire the likeliest track that no sighting
backed since, ``--reacquire``); identities known, each sighting of robot ``j`` goes through a
:class:`~dfusion.frontends.TargetTrackingFrontEnd` on track ``j`` with the single-target
run's robust settings (``mrclam_tracking.TARGET_MONITOR``: gate 0.999, Huber, lock-out
recovery); without recovery, the plain 0.999 gate. Anonymous tracks are mapped to robots
once for the whole network (the nodes share the identities).

The **identities-known** run is the same tracker with the identity given: one tracker per
(observer, tracked robot) with that robot's track only, fed only the sightings of that
robot (the same gate, ``P_D``, clutter density, motion model and prior).

Evaluation every 0.5 s while the tracked robot's ground truth exists. Identities known:
the track of robot ``j`` is the one started for it. Anonymous: the start positions are the
only identity information and the first sighting of a robot may come minutes later, by
when it may be anywhere, so the track that takes it need not be the one started at its
position; each observer's tracks are therefore mapped to the robots once for the whole run
(:func:`track_mapping`: the one-to-one assignment maximizing the number of each robot's
sightings its track took, by the sightings' true identities, which only the evaluation
sees), and the track of robot ``j`` is the one mapped to it (the JSON also gives
``rmse_start_label``, the RMSE of the track started at ``j``'s position):

* **RMSE** of that track against robot ``j``'s true position (a track that swapped onto
  another robot for a while is measured against ``j``: swaps cost accuracy);
* **identity switches** (CLEAR MOT, :func:`dfusion.metrics.identity_metrics`, 1 m
  threshold, per observer and tracked robot);
* **label agreement** of each robot over the four observers that track it
  (:func:`dfusion.metrics.label_agreement`, 1 m): each track carries its start label, the
  name the whole team gives it from the common prior; of the times at which every observer
  has a track within 1 m of the robot, the share at which all these tracks carry the same
  label;
* **on target**: the share of the time the track of ``j`` is within 1 m of ``j``;
* **associated right**: of the frames in which the observer saw ``j`` alone (89 % of the
  frames with a robot sighting in dataset 6), the share whose sighting the tracker gave to
  the track of ``j`` (the rest went to another track or to clutter; JSON:
  ``associated_right``, ``associated_wrong`` of ``lone_sightings``).

Results on dataset 6 and how to reproduce them: ``docs/multi-target.md``, section "MRCLAM
with anonymous sightings"; ``benchmarks/mrclam_anonymous.py`` runs both modes, prints the
table and checks the goals of issue 24.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mrclam_tracking as single  # noqa: E402  (the single-target example: its self-localization settings)

from dfusion.datasets import read_mrclam  # noqa: E402
from dfusion.errors import DfusionError  # noqa: E402
from dfusion.estimation.innovation import InnovationMonitor, MonitorSettings  # noqa: E402
from dfusion.frontends import TargetTrackingFrontEnd, TeamSightingsFrontEnd  # noqa: E402
from dfusion.fusion import TrackingNode  # noqa: E402
from dfusion.localization import LandmarkEKF  # noqa: E402
from dfusion.metrics import TrackingFrame, identity_metrics, label_agreement  # noqa: E402
from dfusion.models import (ConstantVelocity, LandmarkRangeBearing, MeanRevertingVelocity,  # noqa: E402
                            TargetRangeBearing, Unicycle, VelocityOdometry)
from dfusion.tracking import (GNN, JPDA, CameraView, GaussianHypothesiser, MultiTargetTracker, NoDeleter,  # noqa: E402
                              NoInitiator, TrackId, sightings_scan)


@dataclass(frozen=True)
class Settings:
    """One set of settings for the MRCLAM family (module docstring)."""

    motion: str = "ou"              # "ou": MeanRevertingVelocity(sigma, tau); "cv": ConstantVelocity(q)
    sigma: float = 0.045            # m/s, stationary velocity std per axis (dataset 6 ground truth: 0.030-0.055)
    tau: float = 30.0               # s, velocity correlation time (ground-truth autocorrelation 0.44-0.61 at 20 s)
    q: float = 1e-4                 # m^2/s^3, "cv" only (the single-target cv model's)
    prior_std: float = 0.3          # m, start position per axis
    prior_velocity_std: float = 0.045  # m/s (sigma)
    range_std: float = 0.15         # m   (dataset README residual level; single-target run)
    bearing_std: float = 0.02       # rad
    gate: float = 0.999             # chi-square gate probability (13.8 for 2 dof)
    detection_probability: float = 0.4
    clutter_density: float = 2e-5   # false robot sightings per m^2 per frame (measured: 7 of 3906, 10580 frames, ~45 m^2 view)
    half_angle: float = 0.6         # rad  (bearings -0.592..0.572 in dataset 6)
    min_range: float = 0.9          # m    (ranges 0.94..8.63)
    max_range: float = 8.7
    eval_dt: float = 0.5            # s
    match_threshold: float = 1.0    # m, CLEAR MOT / label agreement / on-target
    associator: str = "gnn"
    exchange_period: float = 0.5    # s, network: every node sends its bundles to its tree neighbours
    track_horizon: float = 20.0     # s, network: each track's delayed-state window (FusionNode horizon)
    tree: tuple = ((1, 2), (2, 3), (3, 4), (4, 5))   # network: the chain 1 - 2 - 3 - 4 - 5
    recovery: bool = True           # network: lock-out recovery (known: the single-target robust front end;
                                    # anonymous: TeamSightingsFrontEnd), with the single-target TARGET_MONITOR
    exclude_self: bool = True       # network, anonymous: a node's own track takes no part in its association
    reacquire: str = "stale"        # network, anonymous: TeamSightingsFrontEnd's candidates ("stale", "likeliest")


def _motion(s: Settings):
    return ConstantVelocity(2, s.q) if s.motion == "cv" else MeanRevertingVelocity(2, s.sigma, s.tau)


def _tracker(s: Settings, origin: str) -> MultiTargetTracker:
    assoc = JPDA() if s.associator == "jpda" else GNN()
    return MultiTargetTracker(_motion(s), assoc, NoInitiator(), NoDeleter(), origin=origin,
                              hypothesiser=GaussianHypothesiser(s.gate, detections_in_view=True))


def _localizers(ds, observers) -> tuple[dict, dict]:
    """The landmark map and each observer's self-localization (``examples/mrclam_tracking.py``'s)."""
    lm = {int(i): xy for i, xy in zip(*ds.landmark_array())}
    ekfs = {}
    for o in observers:
        log = ds.robots[o]
        odo = VelocityOdometry(log.odom_t, log.odom, Unicycle(single.DEFAULTS["std_v"], single.DEFAULTS["std_w"]))
        ekfs[o] = LandmarkEKF(odo, 0.0, log.truth_at(0.0), np.diag([0.05**2] * 3),
                              monitor=InnovationMonitor(f"robot{o}/pose", 2, single.POSE_MONITOR))
    return lm, ekfs


def _camera_frames(ds, observers) -> list[tuple[float, int, int, int]]:
    """Every camera frame of the observers in time order: ``(time, observer, first row, end row)``."""
    frames = []
    for o in observers:
        log = ds.robots[o]
        frame_t, first = np.unique(log.meas_t, return_index=True)
        frames += [(float(t), o, int(a), int(b)) for t, a, b in zip(frame_t, first, list(first[1:]) + [log.meas_t.size])]
    frames.sort()
    return frames


def _localize(ekf, log, lm: dict, s: Settings, t: float, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """The observer's pose EKF at frame time ``t`` after the frame's landmark sightings (rows ``a:b``);
    returns the frame's rows and their subjects."""
    ekf.predict(t)
    rows = np.arange(a, b)
    subj = log.meas_subject[rows]
    for i in rows[subj > 5]:   # landmarks: the robot's own localization
        sensor = LandmarkRangeBearing(lm[int(log.meas_subject[i])], s.range_std, s.bearing_std)
        ekf.update(t, np.array([log.meas_range[i], log.meas_bearing[i]]), sensor)
    return rows, subj


def run_observer(ds, observer: int, s: Settings, known: bool, duration: float) -> dict:
    """One robot tracking the four others from its own sightings (:func:`run_tracker`)."""
    return run_tracker(ds, [observer], [r for r in sorted(ds.robots) if r != observer], s, known, duration,
                       f"robot{observer}")


def run_tracker(ds, observers: list[int], tracked: list[int], s: Settings, known: bool, duration: float,
                name: str) -> dict:
    """A tracker of the robots ``tracked`` fed the sightings of the robots ``observers`` (each localizing
    itself), frame by frame in time order; the tracks at the evaluation times.

    One observer: the per-robot run. All five observing and tracked (``--team``): one tracker given
    every robot's sightings (a robot's own track is not in its camera's view: closer than
    ``min_range``). Returns ``{"t": (E,), "tracks": {label: (E, 2) positions}, "frames", "sightings",
    "taken": [(robot sighted, track label or None) per lone sighting], "observers"}``.
    """
    lm, ekfs = _localizers(ds, observers)
    P0 = np.diag([s.prior_std**2] * 2 + [s.prior_velocity_std**2] * 2)
    starts = {j: np.r_[ds.robots[j].truth_at(0.0)[:2], 0.0, 0.0] for j in tracked}
    if known:
        trackers = {j: _tracker(s, f"{name}-{j}") for j in tracked}
        for j in tracked:
            trackers[j].add_track(starts[j], P0, 0.0, TrackId("start", j))
    else:
        trackers = {0: _tracker(s, name)}
        for j in tracked:
            trackers[0].add_track(starts[j], P0, 0.0, TrackId("start", j))
    view = CameraView(s.half_angle, s.min_range, s.max_range)
    eval_t = np.round(s.eval_dt * np.arange(1, int(math.floor(duration / s.eval_dt + 1e-9)) + 1), 9)
    out = {j: np.empty((eval_t.size, 2)) for j in tracked}
    frames = _camera_frames(ds, observers)
    ie = 0
    n_frames = n_sightings = 0
    taken: list[tuple[int, int | None]] = []

    def record(upto: float) -> None:
        nonlocal ie
        while ie < eval_t.size and eval_t[ie] <= upto + 1e-9:
            for trk in trackers.values():
                for track in trk.tracks:
                    track.predict(float(eval_t[ie]))
                    out[track.id.serial][ie] = track.estimate()[0][:2]
            ie += 1

    for t, o, a, b in frames:
        if t > duration:
            break
        record(t - 1e-6)          # evaluation times before this frame
        log, ekf = ds.robots[o], ekfs[o]
        rows, subj = _localize(ekf, log, lm, s, t, a, b)
        seen = rows[np.isin(subj, tracked)]
        if not seen.size:
            continue
        n_frames += 1
        n_sightings += seen.size
        groups = {j: seen[log.meas_subject[seen] == j] for j in tracked} if known else {0: seen}
        for key, idx in groups.items():
            if not idx.size:
                continue
            hits = {tr.id: tr.hits for tr in trackers[key].tracks}
            scan = sightings_scan(t, log.meas_range[idx], log.meas_bearing[idx], ekf.x, ekf.P, s.range_std,
                                  s.bearing_std, view=view, detection_probability=s.detection_probability,
                                  clutter_density=s.clutter_density, source=f"robot{o}")
            trackers[key].step(scan)
            if idx.size == 1:     # which track took a lone sighting (None: none), and whose sighting it was
                took = [tr.id.serial for tr in trackers[key].tracks if tr.hits > hits[tr.id]]
                taken.append((int(log.meas_subject[idx[0]]), took[0] if took else None))
    record(math.inf)
    return {"t": eval_t, "tracks": out, "frames": n_frames, "sightings": n_sightings, "taken": taken,
            "observers": list(observers)}


def run_network(ds, s: Settings, known: bool, duration: float) -> dict[int, dict]:
    """Every robot a :class:`~dfusion.fusion.TrackingNode` of a tree (``s.tree``), tracking all five
    robots (the same five start tracks at every node, :meth:`TrackingNode.add_track`) from its own
    sightings only and exchanging track bundles with its tree neighbours every ``s.exchange_period``
    seconds (in process, no delay).

    Anonymous: each camera frame's robot sightings are one scan (:func:`sightings_scan`, the robot's
    own pose covariance) that the node associates with its **fused** tracks
    (:meth:`TrackingNode.process`). Identities known: each sighting of robot ``j`` is a position fix
    of track ``j`` (its per-detection covariance as the sensor's noise), through a
    :class:`~dfusion.frontends.TargetTrackingFrontEnd` on that track's fusion: the same 0.999 gate
    against the fused estimate (``s.recovery``: the single-target run's robust updates and
    lock-out recovery, ``mrclam_tracking.TARGET_MONITOR``).

    Returns per node the dict of :func:`run_tracker` (every node tracks all five robots).
    """
    robots = sorted(ds.robots)
    names = {o: f"robot{o}" for o in robots}
    nbrs: dict[int, list[str]] = {o: [] for o in robots}
    for a, b in s.tree:
        nbrs[a].append(names[b])
        nbrs[b].append(names[a])
    lm, ekfs = _localizers(ds, robots)
    P0 = np.diag([s.prior_std**2] * 2 + [s.prior_velocity_std**2] * 2)
    tids = {j: TrackId("start", j) for j in robots}
    motion = _motion(s)
    nodes = {}
    for o in robots:
        nodes[o] = TrackingNode(names[o], nbrs[o], motion, associator=JPDA() if s.associator == "jpda" else GNN(),
                                hypothesiser=GaussianHypothesiser(s.gate, detections_in_view=True),
                                initiator=NoInitiator(), deleter=False, merger=False, window=None,
                                horizon=s.track_horizon, epoch=o)
        for j in robots:
            nodes[o].add_track(tids[j], 0.0, np.r_[ds.robots[j].truth_at(0.0)[:2], 0.0, 0.0], P0)
    monitor = single.TARGET_MONITOR if s.recovery else MonitorSettings(
        gate_probability=s.gate, huber_probability=None, drift_test=False, recover=False)
    fronts = {(o, j): TargetTrackingFrontEnd(InnovationMonitor(f"robot{o}/robot{j}", 2, monitor))
              for o in robots for j in robots if j != o} if known else {}
    teams = {o: TeamSightingsFrontEnd(nodes[o], single.TARGET_MONITOR, velocity_std=s.sigma, window=s.track_horizon,
                                      candidates=s.reacquire)
             for o in robots} if s.recovery and not known else {}
    view = CameraView(s.half_angle, s.min_range, s.max_range)
    eval_t = np.round(s.eval_dt * np.arange(1, int(math.floor(duration / s.eval_dt + 1e-9)) + 1), 9)
    send_t = np.round(s.exchange_period * np.arange(1, int(math.floor(duration / s.exchange_period + 1e-9)) + 1), 9)
    out = {o: {j: np.empty((eval_t.size, 2)) for j in robots} for o in robots}
    frames = _camera_frames(ds, robots)
    ticks = sorted([(float(t), 0) for t in send_t] + [(float(t), 1) for t in eval_t])
    counts = {o: {"frames": 0, "sightings": 0} for o in robots}
    taken: dict[int, list[tuple[int, int | None]]] = {o: [] for o in robots}
    ik = ie = 0

    def tick(upto: float) -> None:
        nonlocal ik, ie
        while ik < len(ticks) and ticks[ik][0] <= upto + 1e-9:
            t, kind = ticks[ik]
            ik += 1
            if kind == 0:                       # every node sends, then every bundle is delivered
                bundles = []
                for o in robots:
                    nodes[o].predict(t)
                    bundles += nodes[o].outgoing(t)
                for dst, data in bundles:
                    nodes[int(dst[5:])].receive(data)
            else:
                for o in robots:
                    nodes[o].predict(t)
                    for j in robots:
                        out[o][j][ie] = nodes[o].tracks[tids[j]].estimate()[0][:2]
                ie += 1

    for t, o, a, b in frames:
        if t > duration:
            break
        tick(t - 1e-6)
        log, ekf = ds.robots[o], ekfs[o]
        rows, subj = _localize(ekf, log, lm, s, t, a, b)
        seen = rows[np.isin(subj, robots) & (subj != o)]
        if not seen.size:
            continue
        node = nodes[o]
        node.predict(t)
        counts[o]["frames"] += 1
        counts[o]["sightings"] += seen.size
        if known:
            for i in seen:
                j = int(log.meas_subject[i])
                fix = TargetRangeBearing(ekf.x, ekf.P, (log.meas_range[i], log.meas_bearing[i]), s.range_std,
                                         s.bearing_std).position_fix()
                fronts[(o, j)].assess(node.tracks[tids[j]], t, fix)
            if seen.size == 1:
                taken[o].append((int(log.meas_subject[seen[0]]), int(log.meas_subject[seen[0]])))
            continue
        scan = sightings_scan(t, log.meas_range[seen], log.meas_bearing[seen], ekf.x, ekf.P, s.range_std,
                              s.bearing_std, view=view, detection_probability=s.detection_probability,
                              clutter_density=s.clutter_density, source=names[o])
        before = {j: np.trace(node.tracks[tids[j]].estimate(t)[1][:2, :2]) for j in robots}
        own = (tids[o],) if s.exclude_self else ()     # a robot's camera never sees the robot itself
        if o in teams:
            n_events = len(teams[o].stats.events)
            teams[o].process(scan, exclude=own)
        else:
            node.process(scan, exclude=own)
        if seen.size == 1:     # which track took the lone sighting: the one whose covariance at t shrank
            took = [j for j in robots if np.trace(node.tracks[tids[j]].estimate(t)[1][:2, :2]) < 0.999 * before[j]]
            if o in teams and len(teams[o].stats.events) > n_events:    # re-acquired by a widened track
                took = [teams[o].stats.events[-1][1].serial]
            taken[o].append((int(log.meas_subject[seen[0]]), took[0] if took else None))
    tick(math.inf)
    return {o: {"t": eval_t, "tracks": out[o], "frames": counts[o]["frames"], "sightings": counts[o]["sightings"],
                "taken": taken[o], "observers": [o], "node": nodes[o],
                "recovery": ({**{k: v for k, v in vars(teams[o].stats).items() if k != "events"},
                              "events": [(round(te, 3), tid.serial, round(jump, 2))
                                         for te, tid, jump in teams[o].stats.events]} if o in teams else
                             {str(j): fronts[(o, j)].health() for j in robots if j != o} if known else {})}
            for o in robots}


def track_mapping(res: dict) -> dict[int, int]:
    """Each track (by its start label) -> the robot it followed: the one-to-one assignment of
    tracks to robots maximizing the number of lone sightings of a robot that the track took
    (the sightings' true identities, known to the evaluation only), plus 1/2 for the robot
    whose start position the track was given (a track that took no sighting keeps its start)."""
    labels = sorted(res["tracks"])
    pos = {lab: i for i, lab in enumerate(labels)}
    C = 0.5 * np.eye(len(labels))
    for subj, lab in res["taken"]:
        if lab is not None:
            C[pos[lab], pos[subj]] += 1.0
    r, c = linear_sum_assignment(C, maximize=True)
    return {labels[a]: labels[b] for a, b in zip(r, c)}


def evaluate(ds, runs: dict[int, dict], s: Settings, known: bool, shared_mapping: bool = False) -> dict:
    """RMSE, on-target share and identity switches per (observer, tracked robot); label agreement per robot.

    Identities known: the track of robot ``j`` is the one started for it. Anonymous: each
    observer's tracks are mapped to the robots once for the whole run (:func:`track_mapping`);
    the track of robot ``j`` is the one mapped to it (``shared_mapping``: one mapping for all
    observers, from the lone sightings of all of them: the network, whose nodes share the
    tracks' identities). The label agreement compares the tracks' start labels (the names the
    team shares from the common prior).
    """
    if shared_mapping and not known:
        first = next(iter(runs.values()))
        pooled = track_mapping({"tracks": first["tracks"], "taken": [x for r in runs.values() for x in r["taken"]]})
    pairs: dict[str, dict] = {}
    by_robot: dict[int, dict[int, np.ndarray]] = {}
    mappings = {}
    t_all = next(iter(runs.values()))["t"]
    truth = {j: ds.robots[j].truth_at(t_all)[:, :2] for j in ds.robots}
    for o, res in runs.items():
        t = res["t"]
        mapping = {j: j for j in res["tracks"]} if known else pooled if shared_mapping else track_mapping(res)
        mappings[str(o)] = {str(k): v for k, v in mapping.items()}
        tracks = {mapping[lab]: est for lab, est in res["tracks"].items()}
        by_robot[o] = tracks
        frames = []
        for k in range(t.size):
            gids = [j for j in tracks if t[k] <= ds.robots[j].gt_t[-1]]
            X = np.array([truth[j][k] for j in gids]).reshape(-1, 2)
            hids = list(tracks)
            Y = np.array([tracks[j][k] for j in hids]).reshape(-1, 2)
            frames.append(TrackingFrame(gids, X, hids, Y))
        im = identity_metrics(frames, s.match_threshold)
        for j, est in tracks.items():
            ok = t <= ds.robots[j].gt_t[-1]
            err = np.linalg.norm(est[ok] - truth[j][ok], axis=1)
            start = res["tracks"][j][ok]       # the track started at robot j's start position
            err_start = np.linalg.norm(start - truth[j][ok], axis=1)
            lone = [lab for subj, lab in res["taken"] if subj == j]
            pairs[f"{o}-{j}"] = {
                "observer": o, "target": j, "rmse": float(np.sqrt(np.mean(err**2))),
                "lone_sightings": len(lone),
                "associated_right": int(sum(lab is not None and mapping[lab] == j for lab in lone)),
                "associated_wrong": int(sum(lab is not None and mapping[lab] != j for lab in lone)),
                "rmse_start_label": float(np.sqrt(np.mean(err_start**2))),
                "on_target": float(np.mean(err <= s.match_threshold)),
                "switches": int(im.switches_by_truth.get(j, 0)),
                "sightings": int(sum(np.count_nonzero(ds.robots[r].meas_subject == j) for r in res["observers"])),
            }
    agreement = {}
    for j in sorted(ds.robots):
        obs = [o for o in runs if j in by_robot[o] and o != "team"]
        if not obs:
            continue
        t = runs[obs[0]]["t"]
        ok = t <= ds.robots[j].gt_t[-1]
        X = truth[j][ok]
        nodes = []
        for o in obs:
            ids = list(runs[o]["tracks"])          # the network-wide names: the start labels
            Y = np.stack([runs[o]["tracks"][r][ok] for r in ids], axis=1)
            nodes.append([(ids, Y[k]) for k in range(Y.shape[0])])
        la = label_agreement([[j]] * X.shape[0], [X[k:k + 1] for k in range(X.shape[0])], nodes, s.match_threshold)
        agreement[str(j)] = {"agreement": la.agreement, "agreeing": la.agreeing, "compared": la.compared,
                             "seen": la.seen, "frames": int(X.shape[0])}
    return {"pairs": pairs, "label_agreement": agreement, "mapping": mappings}


def run(dataset: Path, s: Settings, *, known: bool, duration: float | None = None, progress=None) -> dict:
    """Every robot as an observer (anonymous sightings, or identities known); the evaluation."""
    t_wall = time.perf_counter()
    ds = read_mrclam(dataset, duration=duration)
    end = ds.duration if duration is None else min(duration, ds.duration)
    runs = {}
    for o in sorted(ds.robots):
        t0 = time.perf_counter()
        runs[o] = run_observer(ds, o, s, known, end)
        if progress:
            progress(f"{'known' if known else 'anonymous'}: observer robot {o}: {runs[o]['frames']} frames with "
                     f"{runs[o]['sightings']} robot sightings, {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    robots = sorted(ds.robots)
    runs["team"] = run_tracker(ds, robots, robots, s, known, end, "team")
    if progress:
        progress(f"{'known' if known else 'anonymous'}: the team (one tracker, every robot's sightings): "
                 f"{runs['team']['frames']} frames, {time.perf_counter() - t0:.1f} s")
    res = evaluate(ds, runs, s, known)
    res.update({"mode": "identities known" if known else "anonymous", "duration": end,
                "runtime_s": time.perf_counter() - t_wall})
    return res


def run_net(dataset: Path, s: Settings, *, known: bool, duration: float | None = None, progress=None) -> dict:
    """The network (:func:`run_network`), anonymous or identities known; the evaluation (one mapping
    of tracks to robots for the whole network: the nodes share the identities)."""
    t_wall = time.perf_counter()
    ds = read_mrclam(dataset, duration=duration)
    end = ds.duration if duration is None else min(duration, ds.duration)
    runs = run_network(ds, s, known, end)
    stats = {}
    for o, r in runs.items():
        node = r.pop("node")
        stats[str(o)] = {"bundles_sent": node.stats.bundles_sent, "bytes_sent": node.stats.bytes_sent,
                         "bundles_rejected": node.stats.bundles_rejected,
                         "track_messages_rejected": node.stats.track_messages_rejected,
                         "recovery": r.pop("recovery")}
    if progress:
        progress(f"{'known' if known else 'anonymous'}: the network ({len(runs)} TrackingNodes, tree "
                 f"{'-'.join(f'{a}{b}' for a, b in s.tree)}): {time.perf_counter() - t_wall:.1f} s")
    res = evaluate(ds, runs, s, known, shared_mapping=True)
    res.update({"mode": "identities known" if known else "anonymous", "duration": end, "network": stats,
                "runtime_s": time.perf_counter() - t_wall})
    return res


def combine(anon: dict, known: dict, group: str | None = None) -> list[dict]:
    """One row per (observer, tracked robot): both runs side by side. ``group``: ``"robots"`` (each robot
    alone) and ``"team"`` by default, or the name of every row (``"network"``)."""
    rows = []
    for key, a in sorted(anon["pairs"].items(), key=lambda kv: (str(kv[1]["observer"]), kv[1]["target"])):
        k = known["pairs"][key]
        team = a["observer"] == "team"
        none = {"agreement": None, "compared": None}
        la = none if team else anon["label_agreement"][str(a["target"])]
        lk = none if team else known["label_agreement"][str(a["target"])]
        rows.append({"group": group or ("team" if team else "robots"),
                     "observer": a["observer"], "target": a["target"], "sightings": a["sightings"],
                     "rmse_known": k["rmse"], "rmse_anonymous": a["rmse"], "ratio": a["rmse"] / k["rmse"],
                     "rmse_anonymous_start_label": a["rmse_start_label"],
                     "on_target_known": k["on_target"], "on_target_anonymous": a["on_target"],
                     "switches_known": k["switches"], "switches_anonymous": a["switches"],
                     "associated_right": a["associated_right"] / a["lone_sightings"] if a["lone_sightings"] else None,
                     "lone_sightings": a["lone_sightings"],
                     "agreement_known": lk["agreement"], "agreement_anonymous": la["agreement"],
                     "compared_known": lk["compared"], "compared_anonymous": la["compared"]})
    return rows


def print_table(rows: list[dict], anon: dict, known: dict) -> None:
    print(f"\nMRCLAM, anonymous robot sightings against identities known ({anon['duration']:.1f} s; every robot "
          f"tracks the four others from its own sightings; evaluation every 0.5 s)")
    print(f"{'group':>8}{'obs':>5}{'target':>7}{'sightings':>10}{'RMSE known':>12}{'RMSE anon':>11}{'ratio':>7}{'(start label)':>14}"
          f"{'on target k/a':>15}{'switches k/a':>14}{'assoc. right':>13}{'label agreement k/a (compared)':>33}")
    for r in rows:
        print(f"{r['group']:>8}{r['observer']:>5}{r['target']:>7}{r['sightings']:>10}{r['rmse_known']:>12.3f}{r['rmse_anonymous']:>11.3f}"
              f"{r['ratio']:>7.3f}{r['rmse_anonymous_start_label']:>14.3f}"
              f"{r['on_target_known']:>8.2f}/{r['on_target_anonymous']:<6.2f}"
              f"{r['switches_known']:>8}/{r['switches_anonymous']:<5}"
              f"{'-' if r['associated_right'] is None else format(r['associated_right'], '.2f'):>13}"
              + ("" if r["agreement_known"] is None else
                 f"{r['agreement_known']:>12.3f}/{r['agreement_anonymous']:.3f} ({r['compared_known']}/{r['compared_anonymous']})"))
    print(f"run time {known['runtime_s']:.1f} s (known) + {anon['runtime_s']:.1f} s (anonymous)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="MRCLAM dataset directory")
    ap.add_argument("--duration", type=float, default=None, help="use the first S seconds")
    ap.add_argument("--associator", choices=("gnn", "jpda"), default="gnn")
    ap.add_argument("--motion", choices=("ou", "cv"), default="ou",
                    help="ou (default): Ornstein-Uhlenbeck velocity; cv: constant velocity q = 1e-4")
    ap.add_argument("--network", action="store_true",
                    help="the network instead: every robot a TrackingNode of the chain 1-2-3-4-5 exchanging track "
                         "bundles (rows 'network')")
    ap.add_argument("--no-recovery", action="store_true",
                    help="network: the plain 0.999 gate, no lock-out recovery (known) or re-acquisition (anonymous)")
    ap.add_argument("--reacquire", choices=("stale", "likeliest"), default="stale",
                    help="network, anonymous: a lock-out re-acquires the likeliest stale track (default), or the "
                         "likeliest track if it is stale")
    ap.add_argument("--no-exclude-self", action="store_true",
                    help="network, anonymous: a node's own track takes part in the association of its sightings")
    ap.add_argument("--json", type=Path, default=None, help="write both runs and the table as JSON")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    s = Settings(associator=args.associator, motion=args.motion, recovery=not args.no_recovery,
                 exclude_self=not args.no_exclude_self, reacquire=args.reacquire)

    def progress(msg: str) -> None:
        print(msg, flush=True)

    go = run_net if args.network else run
    try:
        known = go(args.dataset, s, known=True, duration=args.duration, progress=progress)
        anon = go(args.dataset, s, known=False, duration=args.duration, progress=progress)
    except (DfusionError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    rows = combine(anon, known, "network" if args.network else None)
    print_table(rows, anon, known)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"dataset": str(args.dataset), "settings": asdict(s), "rows": rows,
                                         "anonymous": anon, "known": known}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
