#!/usr/bin/env python
r"""Map-based localization on real CARMEN laser logs: MCL and scan matching + odometry EKF.

Usage::

    python examples/carmen_localization.py LOG.gz [--json OUT] [--plot DIR] [--max-scans N] [--seed S] [-v]
    python examples/carmen_localization.py --bag BAG ...   (scans and poses from a ROS bag)
    python examples/carmen_localization.py --all DIR [--seeds 0,1,2] [--jobs N] [--json OUT] [-v]
    python examples/carmen_localization.py ... --only scan_matching   (or mcl: one localizer alone)

``LOG`` is a CARMEN log with corrected poses, e.g. ``DATA/carmen/intel-corrected.log.gz``
(where to get it: ``tests/data/carmen/README.md``; the slice
``tests/data/carmen/intel-160scans.log.gz`` runs as is) (read with
:func:`dfusion.datasets.carmen.read_carmen`, which handles the log's pitfalls: repeated
``ODOM`` copies after each scan, 81.83 m "no return" readings). ``--all DIR`` runs every
``*.log`` / ``*.log.gz`` in ``DIR`` (for each seed of ``--seeds``) with the same settings
and prints one table (RMSE, median, 95 %, largest error after the first ``SKIP_SCANS``
localized scans, heading RMSE, recoveries, gated, ms/scan for each localizer) and pooled
figures over all scans of all runs; ``--json`` writes them; ``--jobs N`` runs N logs at
once in worker processes (the results do not depend on it). ``-v`` logs every recovery.

With ``--bag BAG`` the scans (``--scan-topic``, default ``/scan``, ``sensor_msgs/LaserScan``),
their corrected poses (``--pose-topic``, default ``/scan_pose``: ``PoseStamped``,
``PoseWithCovarianceStamped`` or ``Odometry``, the one nearest each scan's stamp within
``--pose-tolerance`` seconds, else refused) and the odometry stream (``--odom-topic``,
default ``/odom``) come from a ROS 1 or ROS 2 bag (:func:`dfusion.bags.carmen_from_bag`,
``docs/ros.md``), in the bag's time order. A laser mounted off the robot's centre is
folded in from the bag's ``/tf_static`` (``--tf-topic``, ``--base-frame``). ``--pose-topic
none`` takes the odometry poses as the scans' poses (they drift: no ground truth).
``--msg FILE.msg`` gives a message definition a Humble sqlite3 bag does not store.

**Settings** are the module-level constants below (``MCL_SETTINGS``, ``ICP_SETTINGS``,
...): one set for every CARMEN log, never per log.

Protocol (scans in file order, the first ``--max-scans`` of them if given; the time stamps
are not used -- they are all equal, all zero or wrap around in three of the logs, and
sorting by them reorders the MIT log -- the scan index is the time):

1. **Map**: the even-numbered scans (0, 2, 4, ...) at their corrected poses build an
   occupancy grid (:func:`dfusion.maps.mapping.grid_from_scans`, 5 cm cells, readings
   below ``--map-range`` = 30 m are hits, longer ones clear the cells up to 30 m).
2. **Localization**: the odd-numbered scans, none of them in the map, are localized
   against it. The ground truth is their corrected pose.
3. **Odometry**: derived from the corrected pose sequence of *all* scans (the ODOM
   stream of the Intel log is not consistent with the scan poses: 5 cm / 2.6 deg median
   disagreement at the scan times). Each increment between consecutive scan poses is
   taken in the frame of the earlier pose, ``(dx, dy, dtheta)``, and perturbed like
   wheel odometry::

       (dx, dy) <- (1 + e_s) (dx, dy),          e_s ~ N(0, 0.05^2)
       dtheta   <- dtheta + e_r,                e_r ~ N(0, (0.05 dtheta)^2 + (0.02 rad/m * |d|)^2)

   (5 % scale error per step, 5 % of each rotation, 0.02 rad per metre travelled;
   ``--odom-noise`` scales all three). The noisy increments are chained into an odometry
   trajectory that drifts (its error, relative to the true initial pose, is reported as
   ``odometry.rmse``). Seeded by ``--seed``. (A ``(rot1, trans, rot2)`` decomposition is
   not used to *simulate* the noise: the robot often turns in place here, with 3-7 cm
   of laser displacement, and ``rot1`` is then an arbitrary angle whose noise would
   dominate.)
4. **MCL** (:class:`~dfusion.localization.MonteCarloLocalization`, likelihood field,
   KLD 500-5,000 particles, 60 beams evenly spread over the beams with a reading below
   ``--laser-range`` (``beam_selection="valid"``; ``docs/localization.md`` has why and
   the numbers), odometry motion model with
   ``alpha = ((2 * 0.05)^2, (2 * 0.02)^2, (2 * 0.05)^2, 0.01)``, i.e. about twice the
   simulated noise; beams that end in free space short of the map's surface at the
   cloud's mean pose -- an object the map does not hold -- are left out of every
   particle's product: ``LikelihoodFieldModel(short_skip=True)``) is started from the
   first localization scan's true pose with 0.1 m / 0.05 rad uncertainty (pose
   tracking) and updated with every odometry pose and every localization scan; its
   estimate after each scan is compared with the truth.
   Its lock-out monitor (one-sided test of each scan's predictive likelihood against its
   usual level, window and run tests at ``MONITOR_ALPHA``) counts rejected scans
   ("gated") and alarms. Relocalization on alarms is *off* here
   (``MCL_RECOVERY_SAMPLER = "none"``): on these logs the alarms come from places where
   the map misses what the laser sees (the likelihood is low at the true pose too), and
   relocalizing there follows the map's errors -- measured with seeds 0 and 1: Freiburg
   RMSE 0.17 m without, 78-90 m with the local expanding search, 0.20-0.23 m with a
   non-expanding one; Intel 0.07 m without, 0.12-0.14 m with (``docs/localization.md``).
5. **Scan matching + EKF**: :class:`~dfusion.localization.ScanMatchingEKF` --
   :class:`~dfusion.localization.OdometryEKF` (survey eq. 5-8) predicting with the
   odometry increments split into a turn and a move (noise 1.5 times the simulated one:
   ``k_d = 0.075``, ``k_theta = 0.075``, ``k_dtheta = 0.03``, floors 1 cm and 5 mrad); at each
   localization scan a correlative scan matcher
   (:class:`~dfusion.localization.correlative.CorrelativeScanMatcher`, Olson 2009;
   ``CORRELATIVE_SETTINGS``: likelihood field with ``sigma_hit`` = 0.1 m, 120 of the scan's
   points) scores every pose of a lattice (5 cm cells, headings in steps of one cell at
   the farthest point) over the box around the 99 % region of the prediction, capped at
   +-1 m / +-0.3 rad, and point-to-line ICP
   (:meth:`~dfusion.localization.ScanMatcher.from_grid`, 0.5 m correspondence gate, Cauchy
   M-estimator with the scale ``1.4826 MAD`` of the residuals) starts from its best pose;
   the match, with the Newey-West (HAC) covariance of its residuals plus
   ``MATCH_COV_FLOOR_SD`` = (5 cm, 5 cm, 0.02 rad) for what the residuals of one scan cannot
   show (ICP from the true pose ends 4-7 cm / 0.3-0.7 deg RMS from it on these logs, while
   residual-based covariances say a few mm), enlarged in every direction to the spread of
   the scan's likelihood over the lattice about the match (large along a corridor),
   updates the EKF unless ICP fails or the chi-square gate (3 dof, 99.9 %) rejects it. Lock-outs are
   detected from the NIS window and the run of rejected matches and recovered from by a
   widened search confirmed by two scans (``ScanMatchingEKF``).

Runtime: the full Intel log (910 scans: 455 in the map, 455 localized) takes 3-10 s
depending on the machine's load (map 1-2 s); the Freiburg campus log (2,008 scans, a
5,355 x 4,823 map) about 2 minutes, most of it building the map. Output: a table and, with
``--json``, ``mcl`` and ``scan_matching`` with ``rmse``, ``heading_rmse``, ``median``,
``p95``, ``max``, ``max_after``, ``recoveries``, ``gated``, ``alarms``, ``ms_per_scan``,
the recovery ``events`` (scan index, status) and more (``docs/robots.md`` has the results).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from dfusion.datasets import read_carmen
from dfusion.errors import DfusionError, ValidationError
from dfusion.estimation.innovation import LockoutDetector
from dfusion.geometry import se2_between, se2_compose, wrap_angle
from dfusion.localization import MonteCarloLocalization, OdometryEKF, ScanMatcher, ScanMatchingEKF, scan_to_points
from dfusion.localization.correlative import CorrelativeScanMatcher
from dfusion.localization.odometry_ekf import predict_odometry_step
from dfusion.maps.mapping import grid_from_scans
from dfusion.models import LaserConfig, LikelihoodFieldModel, OdometryMotionModel

logger = logging.getLogger("carmen_localization")

#: Simulated odometry noise: translation scale error (fraction), heading error per radian
#: turned (fraction) and per metre travelled (rad/m); see the module docstring.
ODOM_NOISE = (0.05, 0.05, 0.02)


def noisy_odometry(poses: np.ndarray, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """Odometry poses from a pose sequence: noisy robot-frame increments, chained."""
    k_s, k_r, k_rd = (scale * a for a in ODOM_NOISE)
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k in range(1, poses.shape[0]):
        d = se2_between(poses[k - 1], poses[k])
        dist = math.hypot(d[0], d[1])
        s = 1.0 + rng.normal(0.0, k_s)
        dth = d[2] + rng.normal(0.0, math.sqrt((k_r * d[2]) ** 2 + (k_rd * dist) ** 2))
        out[k] = se2_compose(out[k - 1], np.array([s * d[0], s * d[1], float(wrap_angle(dth))]))
    return out


def pose_errors(est: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1]), np.abs(wrap_angle(est[:, 2] - truth[:, 2]))


# ------------------------------------------------------------------------------------------
# Settings: one set for every CARMEN log (module-level defaults; see the module docstring)
# ------------------------------------------------------------------------------------------
#: localized scans at the start that the "max after" column leaves out (convergence)
SKIP_SCANS = 10
#: initial uncertainty of both localizers (m, m, rad), around the true first pose
P0_SD = (0.1, 0.1, 0.05)
#: occupancy-grid mapping options (grid_from_scans)
MAP_SETTINGS: dict = {}
#: MCL: particles, beams, Augmented-MCL rates (injection share on divergence alarms)
MCL_SETTINGS = {"min_particles": 500, "max_particles": 5000, "max_beams": 60, "beam_selection": "valid",
                "alpha_slow": 0.001, "alpha_fast": 0.1}
#: divergence monitors (both localizers): NIS window, false-alarm rate of each test
MONITOR_WINDOW = 10
MONITOR_ALPHA = 1e-4
#: MCL relocalization on an alarm ("local", "uniform" or "none": detection and counting only;
#: see the module docstring for why the CARMEN logs use "none")
MCL_RECOVERY_SAMPLER = "none"
#: likelihood-field sensor model of MCL: beams short against the map at the cloud's mean
#: (an object the map does not hold in front of the mapped surface) leave the product
LIKELIHOOD_SETTINGS: dict = {"short_skip": True}
#: MCL's odometry motion noise: this factor times the simulated one (standard deviations)
MCL_NOISE_FACTOR = 2.0
#: ICP: point-to-line against the map's surface points
ICP_SETTINGS = {"max_correspondence_distance": 0.5, "trim_fraction": 0.0, "tolerance": 1e-4, "max_iterations": 40,
                "robust": "cauchy", "covariance": "hac"}
#: EKF odometry noise: this factor times the simulated one
EKF_NOISE_FACTOR = 1.5
#: chi-square gate of the EKF (3 dof, P_G = 0.999)
EKF_GATE_PROBABILITY = 0.999
#: give MCL's estimate to the scan matcher's recovery as an extra start (couples the two)
SM_SEEDS_FROM_MCL = False
#: added to every match covariance (m, m, rad): error the residuals of one scan cannot show
MATCH_COV_FLOOR_SD = (0.05, 0.05, 0.02)
#: correlative scan matcher (Olson 2009) before ICP: options of CorrelativeScanMatcher (None: off)
CORRELATIVE_SETTINGS: dict | None = {"sigma_hit": 0.1, "max_points": 120}
#: its search window: the box of this probability region of the prediction, capped (m, m, rad)
CORRELATIVE_PROBABILITY = 0.99
CORRELATIVE_CAP = (1.0, 1.0, 0.3)


def settings() -> dict:
    """The settings of this family, as written to the JSON."""
    return {"skip_scans": SKIP_SCANS, "p0_sd": P0_SD, "map": MAP_SETTINGS, "mcl": MCL_SETTINGS,
            "likelihood": LIKELIHOOD_SETTINGS, "mcl_noise_factor": MCL_NOISE_FACTOR, "mcl_recovery_sampler": MCL_RECOVERY_SAMPLER,
            "monitor_window": MONITOR_WINDOW, "monitor_alpha": MONITOR_ALPHA, "icp": ICP_SETTINGS,
            "ekf_noise_factor": EKF_NOISE_FACTOR, "ekf_gate_probability": EKF_GATE_PROBABILITY,
            "match_cov_floor_sd": MATCH_COV_FLOOR_SD, "sm_seeds_from_mcl": SM_SEEDS_FROM_MCL,
            "correlative": CORRELATIVE_SETTINGS, "correlative_probability": CORRELATIVE_PROBABILITY,
            "correlative_cap": CORRELATIVE_CAP}


def load_log(args: argparse.Namespace):
    """The CARMEN log ``args.log`` (scans in file order), or the bag ``args.bag``."""
    if getattr(args, "bag", None):
        from dfusion.bags import carmen_from_bag  # noqa: PLC0415

        from dfusion.bags import msgdefs_from_files  # noqa: PLC0415

        pose = None if args.pose_topic.lower() in ("", "none") else args.pose_topic
        odom = None if args.odom_topic.lower() in ("", "none") else args.odom_topic
        return carmen_from_bag(args.bag, scan_topic=args.scan_topic, odom_topic=odom, scan_pose_topic=pose,
                               pose_tolerance=args.pose_tolerance, tf_topic=args.tf_topic, base_frame=args.base_frame,
                               msgdefs=msgdefs_from_files(args.msg))
    if args.log is None:
        raise ValidationError("give a CARMEN log or --bag")
    return read_carmen(args.log, sort=False)


def log_scans(log, max_scans: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corrected poses ``(S, 3)``, ranges ``(S, B)`` and beam angles of a log's scans, in its order.

    The time stamps are not used: three of the six logs have unusable ones (all equal, all
    zero, or wrapping around), and sorting by them reorders the scans of the MIT log.
    """
    scans = log.scans[:max_scans] if max_scans else log.scans
    if len(scans) < 6:
        raise ValidationError(f"need at least 6 scans, got {len(scans)}")
    n = scans[0].ranges.size
    if any(s.ranges.size != n for s in scans):
        raise ValidationError("scans with different numbers of beams")
    return np.array([s.laser_pose for s in scans]), np.array([s.ranges for s in scans]), scans[0].angles


def pose_summary(pos: np.ndarray, head: np.ndarray, skip: int = SKIP_SCANS) -> dict:
    after = pos[skip:] if pos.size > skip else pos
    return {
        "rmse": float(np.sqrt(np.mean(pos**2))),
        "heading_rmse": float(np.sqrt(np.mean(head**2))),
        "median": float(np.median(pos)),
        "p95": float(np.percentile(pos, 95)),
        "max": float(np.max(pos)),
        "max_after": float(np.max(after)),
    }


def make_monitor(dof: int) -> LockoutDetector:
    return LockoutDetector(dof, window=MONITOR_WINDOW, alpha=MONITOR_ALPHA, gate_probability=EKF_GATE_PROBABILITY)


def run_mcl(grid, laser, odom, ranges, times, loc_idx, x0, P0, seed, odom_noise) -> tuple[np.ndarray, np.ndarray, dict]:
    """MCL over the localization scans; estimates ``(L, 3)``, covariances ``(L, 3, 3)`` and counters."""
    k_s, k_r, k_rd = (odom_noise * a for a in ODOM_NOISE)
    # MCL's (rot1, trans, rot2) model, MCL_NOISE_FACTOR times the simulated noise: a1 rot^2 ->
    # rotation noise from rotation, a2 trans^2 -> from translation, a3 trans^2 -> translation scale
    f = MCL_NOISE_FACTOR
    a1, a2, a3, a4 = (f * k_r) ** 2, (f * k_rd) ** 2, (f * k_s) ** 2, 0.01
    mcl = MonteCarloLocalization(grid, laser, sensor=LikelihoodFieldModel(**LIKELIHOOD_SETTINGS),
                                 motion=OdometryMotionModel(a1, a2, a3, a4), rng=seed, monitor=make_monitor(1),
                                 recovery_sampler=MCL_RECOVERY_SAMPLER, **MCL_SETTINGS)
    k0 = int(loc_idx[0])
    mcl.predict(times[k0], odom[k0])
    mcl.initialize_gaussian(x0, P0, t=times[k0])
    est, cov, events = [], [], []
    for k in range(k0, len(times)):
        mcl.predict(times[k], odom[k])
        if k % 2 == 1:
            before = (mcl.stats["alarms"], mcl.stats["recoveries"])
            mcl.update(times[k], ranges[k])
            if mcl.stats["alarms"] > before[0]:
                events.append({"scan": len(est), "status": "recovered" if mcl.stats["recoveries"] > before[1]
                               else "recovery_failed"})
            e = mcl.estimate()
            est.append(e.mean)
            cov.append(e.cov)
    st = mcl.stats
    stats = {"recoveries": int(st["recoveries"]), "recovery_failures": int(st["recovery_failures"]),
             "injected": int(st["injected"]), "gated": int(st["gated"]), "alarms": int(st["alarms"]), "events": events}
    return np.array(est), np.array(cov), stats


def run_scan_matching(grid, angles, odom, ranges, times, loc_idx, x0, P0, odom_noise, laser_range,
                      seeds: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """ICP + odometry EKF with lock-out recovery; estimates ``(L, 3)``, covariances and counters.

    ``seeds`` (``(L, 3)``, optional): another localizer's estimate at each localization
    scan, an extra start of the widened search of a recovery (``SM_SEEDS_FROM_MCL``).
    """
    k_s, k_r, k_rd = (odom_noise * a for a in ODOM_NOISE)
    matcher = ScanMatcher.from_grid(grid, "point_to_line", **ICP_SETTINGS)
    f = EKF_NOISE_FACTOR
    ekf = OdometryEKF(x0, P0, k_d=f * k_s, k_theta=f * k_r, k_dtheta=f * k_rd, s_d=0.01, s_theta=0.005,
                      gate=float(chi2.ppf(EKF_GATE_PROBABILITY, 3)))
    corr = None if CORRELATIVE_SETTINGS is None else CorrelativeScanMatcher(grid, max_range=laser_range,
                                                                            **CORRELATIVE_SETTINGS)
    loc = ScanMatchingEKF(matcher, ekf, cov_floor=np.diag(MATCH_COV_FLOOR_SD) ** 2, monitor=make_monitor(3),
                          correlative=corr, correlative_probability=CORRELATIVE_PROBABILITY,
                          correlative_cap=CORRELATIVE_CAP)
    k0 = int(loc_idx[0])
    est, cov, events = [], [], []
    for k in range(k0, len(times)):
        if k > k0:
            loc.predict(times[k], (odom[k - 1], odom[k]))
        if k % 2 == 0:
            continue
        extra = () if seeds is None else (seeds[len(est)],)
        out = loc.correct(times[k], scan_to_points(ranges[k], angles, laser_range), extra)
        if out.alarm is not None:
            events.append({"scan": len(est), "status": out.status, "reason": out.alarm})
        est.append(ekf.x)
        cov.append(ekf.P)
    st = loc.stats
    stats = {"recoveries": st["recoveries"], "recovery_failures": st["recovery_failures"], "alarms": st["alarms"],
             "gated": st["gated"], "icp_failures": st["failed"], "gated_out": st["gated"], "events": events}
    return np.array(est), np.array(cov), stats


def build_map(poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, resolution: float = 0.05,
              map_range: float = 30.0):
    """The occupancy grid of the even-numbered scans (step 1 of the protocol) and its build time (s)."""
    t0 = time.perf_counter()
    map_idx = np.arange(0, len(poses), 2)
    grid = grid_from_scans(poses[map_idx], ranges[map_idx], angles, resolution=resolution, max_range=map_range,
                           **MAP_SETTINGS)
    return grid, time.perf_counter() - t0


def run_log(log_path: Path | str | None, seed: int = 0, *, log=None, max_scans: int | None = None,
            resolution: float = 0.05, map_range: float = 30.0, laser_range: float = 30.0, odom_noise: float = 1.0,
            keep_errors: bool = False, series: bool = True, keep_grid: bool = False, grid=None,
            only: str | None = None) -> dict:
    """The protocol of the module docstring on one log (``log``: already read; default:
    :func:`dfusion.datasets.read_carmen` of ``log_path`` in file order); the result dictionary.
    ``grid``: the map from :func:`build_map` for these scans (it does not depend on the seed).
    ``only``: ``"mcl"`` or ``"scan_matching"`` runs that localizer alone (the other's key is
    then missing from the result)."""
    if only not in (None, *KEYS):
        raise ValidationError(f"only must be one of {KEYS}, got {only!r}")
    t_wall = time.perf_counter()
    if log is None:
        log = read_carmen(log_path, sort=False)
    poses, ranges, angles = log_scans(log, max_scans)
    times = np.arange(poses.shape[0], dtype=float)  # scan index as time stamp
    map_idx = np.arange(0, len(poses), 2)
    loc_idx = np.arange(1, len(poses), 2)
    if grid is None:
        grid, t_map = build_map(poses, ranges, angles, resolution, map_range)
    else:
        t_map = 0.0

    rng = np.random.default_rng(seed)
    odom = noisy_odometry(poses, rng, odom_noise)
    # the odometry frame starts at the true first pose: its drift is its error
    odo_pos, odo_head = pose_errors(odom[loc_idx], poses[loc_idx])
    laser = LaserConfig(angles, max_range=laser_range)
    k0 = int(loc_idx[0])
    P0 = np.diag(P0_SD) ** 2
    truth = poses[loc_idx]

    n = loc_idx.size
    runs: dict[str, tuple] = {}  # key -> (estimates, covariances, counters, seconds)
    mcl_est = None
    if only in (None, "mcl") or SM_SEEDS_FROM_MCL:
        t0 = time.perf_counter()
        mcl_est, mcl_cov, mcl_stats = run_mcl(grid, laser, odom, ranges, times, loc_idx, poses[k0], P0, seed,
                                              odom_noise)
        if only in (None, "mcl"):
            runs["mcl"] = (mcl_est, mcl_cov, mcl_stats, time.perf_counter() - t0)
    if only in (None, "scan_matching"):
        t0 = time.perf_counter()
        sm_est, sm_cov, sm_stats = run_scan_matching(grid, angles, odom, ranges, times, loc_idx, poses[k0], P0,
                                                     odom_noise, laser_range, mcl_est if SM_SEEDS_FROM_MCL else None)
        runs["scan_matching"] = (sm_est, sm_cov, sm_stats, time.perf_counter() - t0)
    errs = {key: pose_errors(r[0], truth) for key, r in runs.items()}
    out = {
        "log": str(log_path),
        "scans": int(poses.shape[0]),
        "map_scans": int(map_idx.size),
        "localized_scans": int(n),
        "map": {"resolution": grid.resolution, "width": grid.width, "height": grid.height,
                "occupied_cells": int(grid.occupied.sum()), "seconds": t_map},
        "odometry": {**pose_summary(odo_pos, odo_head), "noise": [odom_noise * a for a in ODOM_NOISE]},
        **{key: {**pose_summary(*errs[key]), **r[2], "seconds": r[3], "ms_per_scan": 1e3 * r[3] / n}
           for key, r in runs.items()},
        "seed": int(seed),
    }
    if series:
        # per localized scan: time (scan index), truth and each localizer's pose (x m, y m,
        # theta rad) with its 3x3 covariance
        out["series"] = {"t": times[loc_idx].tolist(), "truth": truth.tolist(), "odometry": odom[loc_idx].tolist(),
                         **{key: {"mean": r[0].tolist(), "cov": r[1].tolist()} for key, r in runs.items()}}
    if keep_errors:
        out["errors"] = {key: e[0].tolist() for key, e in errs.items()}
    out["runtime_s"] = time.perf_counter() - t_wall
    if keep_grid:
        out["_plot"] = {"grid": grid, "map_poses": poses[map_idx]}   # for the figures; not written to JSON
    return out


def run(args: argparse.Namespace, log=None) -> dict:
    """One log (``args.log`` or ``args.bag``, or ``log`` already read) with the options of the command line."""
    log = load_log(args) if log is None else log
    name = args.bag if getattr(args, "bag", None) else args.log
    return run_log(name, args.seed, log=log, max_scans=args.max_scans, resolution=args.resolution,
                   map_range=args.map_range, laser_range=args.laser_range, odom_noise=args.odom_noise,
                   keep_grid=True, only=getattr(args, "only", None))


LOCALIZERS = (("mcl", "MCL (likelihood field)"), ("scan_matching", "ICP + odometry EKF"))
KEYS = tuple(k for k, _ in LOCALIZERS)


def present(results: dict | list[dict]) -> tuple:
    """The ``LOCALIZERS`` that ran (all of them unless ``--only``)."""
    r = results[0] if isinstance(results, list) else results
    return tuple((k, lab) for k, lab in LOCALIZERS if k in r)


def figures(res: dict, grid, out: Path) -> list[Path]:
    """``out/carmen_topdown.png`` (the map built from the even scans, the true path of the
    localized scans, each localizer's estimate with 3-sigma ellipses, the drifting
    odometry) and ``out/carmen_errors.png`` (X and Y errors of both localizers with their
    own ±3σ)."""
    from dfusion.viz.plots import plot_track_errors  # noqa: PLC0415
    from dfusion.viz.topdown import Scene, Track, draw_scene  # noqa: PLC0415

    ser = res["series"]
    t = np.asarray(ser["t"])
    truth = np.asarray(ser["truth"])[:, :2]
    mcl = Track("MCL (likelihood field)", t, np.asarray(ser["mcl"]["mean"])[:, :2],
                np.asarray(ser["mcl"]["cov"])[:, :2, :2], "tab:blue")
    sm = Track("ICP + odometry EKF", t, np.asarray(ser["scan_matching"]["mean"])[:, :2],
               np.asarray(ser["scan_matching"]["cov"])[:, :2, :2], "tab:orange")
    odo = Track("odometry (dead reckoning)", t, np.asarray(ser["odometry"])[:, :2], None, "0.45", style=":")
    scene = Scene(title=f"CARMEN {Path(res['log']).name}: {res['localized_scans']} scans localized in a map of "
                        f"{res['map_scans']} others",
                  truth={"robot (corrected poses)": (t, truth)}, tracks=[mcl, sm, odo], grid=grid,
                  note=f"RMSE: MCL {res['mcl']['rmse']:.3f} m, ICP + EKF {res['scan_matching']['rmse']:.3f} m, "
                       f"odometry {res['odometry']['rmse']:.2f} m",
                  time_format="scan {:.0f}")
    out.mkdir(parents=True, exist_ok=True)
    a = draw_scene(scene, out / "carmen_topdown.png")
    b = plot_track_errors(t, truth, [mcl, sm], out / "carmen_errors.png",
                          title=f"CARMEN {Path(res['log']).name}: position error of each localizer with its own ±3σ",
                          xlabel="scan index (the logs' stamps are unusable)")
    return [a, b]


def print_table(res: dict) -> None:
    m = res["map"]
    print(f"CARMEN {res['log']}: {res['scans']} scans, map from {res['map_scans']} "
          f"({m['width']}x{m['height']} cells of {m['resolution']} m, built in {m['seconds']:.1f} s), "
          f"{res['localized_scans']} scans localized")
    print(f"{'localizer':<26}{'RMSE m':>9}{'median':>9}{'95 %':>8}{'max':>8}{'max>10':>8}{'heading RMSE rad':>18}"
          f"{'recoveries':>11}{'alarms':>7}{'gated':>7}{'ms/scan':>9}")
    for key, label in (("odometry", "odometry (dead reckoning)"),) + present(res):
        v = res[key]
        ms = f"{v['ms_per_scan']:.1f}" if "ms_per_scan" in v else "-"
        rec = str(v["recoveries"]) if "recoveries" in v else "-"
        alarms = str(v["alarms"]) if "alarms" in v else "-"
        gated = str(v["gated"]) if "gated" in v else "-"
        print(f"{label:<26}{v['rmse']:>9.3f}{v['median']:>9.3f}{v['p95']:>8.3f}{v['max']:>8.3f}{v['max_after']:>8.3f}"
              f"{v['heading_rmse']:>18.4f}{rec:>11}{alarms:>7}{gated:>7}{ms:>9}")
    if "scan_matching" in res:
        sm = res["scan_matching"]
        print(f"ICP failures {sm['icp_failures']}, gated out {sm['gated_out']}", end="; ")
    print(f"run time {res['runtime_s']:.1f} s")


def pooled(results: list[dict]) -> dict:
    """Figures over all scans of all runs (needs ``keep_errors``)."""
    out = {}
    for key, _ in present(results):
        e = np.concatenate([np.asarray(r["errors"][key]) for r in results])
        after = np.concatenate([np.asarray(r["errors"][key])[SKIP_SCANS:] for r in results])
        n = np.array([r["localized_scans"] for r in results])
        out[key] = {
            "rmse": float(np.sqrt(np.mean(e**2))),
            "median": float(np.median(e)),
            "p95": float(np.percentile(e, 95)),
            "max_after": float(np.max(after)),
            "worst_rmse": float(max(r[key]["rmse"] for r in results)),
            "heading_rmse": float(np.sqrt(np.sum([r[key]["heading_rmse"] ** 2 * k for r, k in zip(results, n)]) / n.sum())),
            "recoveries": int(sum(r[key]["recoveries"] for r in results)),
            "alarms": int(sum(r[key]["alarms"] for r in results)),
            "gated": int(sum(r[key]["gated"] for r in results)),
            "ms_per_scan": float(np.sum([r[key]["seconds"] for r in results]) * 1e3 / n.sum()),
        }
    return out


def per_log(results: list[dict]) -> list[dict]:
    """Mean and worst RMSE and the worst error after the first ``SKIP_SCANS`` scans over the
    seeds of each log, per localizer."""
    out = []
    for name in dict.fromkeys(r["log"] for r in results):
        runs = [r for r in results if r["log"] == name]
        row = {"log": name, "seeds": [r["seed"] for r in runs]}
        for key, _ in present(runs):
            rm = [r[key]["rmse"] for r in runs]
            row[key] = {"rmse_mean": float(np.mean(rm)), "rmse_worst": float(np.max(rm)),
                        "max_after_worst": float(max(r[key]["max_after"] for r in runs)),
                        "recoveries": int(sum(r[key]["recoveries"] for r in runs)),
                        "alarms": int(sum(r[key]["alarms"] for r in runs))}
        out.append(row)
    return out


SUB = f"{'RMSE':>7}{'median':>7}{'max>10':>7}{'head':>7}{'recov':>6}{'alarm':>6}{'gated':>6}{'ms/scan':>8}"


def _cells(v: dict) -> str:
    return (f"{v['rmse']:>7.3f}{v['median']:>7.3f}{v['max_after']:>7.3f}{v['heading_rmse']:>7.4f}"
            f"{v['recoveries']:>6}{v['alarms']:>6}{v['gated']:>6}{v['ms_per_scan']:>8.1f}")


def short_name(log: str) -> str:
    return Path(log).name.replace("-corrected", "").split(".")[0]


def print_all_table(results: list[dict], pool: dict, logs: list[dict] | None = None) -> None:
    w = len(SUB)
    locs = present(results)
    print(f"{'log':<20}{'seed':>5}{'scans':>6} | " + " | ".join(f"{lab:<{w}}" for _, lab in locs))
    print(f"{'':<31} | " + " | ".join(f"{SUB:<{w}}" for _ in locs))
    for r in results:
        print(f"{short_name(r['log']):<20}{r['seed']:>5}{r['localized_scans']:>6} | "
              + " | ".join(_cells(r[key]) for key, _ in locs))
    n = sum(r["localized_scans"] for r in results)
    print(f"{'pooled':<25}{n:>6} | " + " | ".join(_cells(pool[key]) for key, _ in locs))
    if logs:
        print(f"\nover the seeds: {'log':<20} | " + " | ".join(
            f"{lab + ': RMSE mean / worst, max>10 worst':<44}" for _, lab in locs))
        for row in logs:
            print(f"{'':<16}{short_name(row['log']):<20} | " + " | ".join(
                f"{row[k]['rmse_mean']:>8.3f} / {row[k]['rmse_worst']:.3f}, {row[k]['max_after_worst']:>6.3f}{'':<21}"
                for k, _ in locs))
    print("worst RMSE per localizer: " + ", ".join(f"{lab} {pool[k]['worst_rmse']:.3f} m" for k, lab in locs))


def _run_seeds(job: tuple) -> list[dict]:
    """One log for every seed, the map built once."""
    path, seeds, kw = job
    log = read_carmen(path, sort=False)
    poses, ranges, angles = log_scans(log, kw.get("max_scans"))
    grid, t_map = build_map(poses, ranges, angles, kw.get("resolution", 0.05), kw.get("map_range", 30.0))
    out = []
    for seed in seeds:
        logger.info("localizing %s, seed %d", Path(path).name, seed)
        r = run_log(path, seed, log=log, keep_errors=True, series=False, grid=grid, **kw)
        r["map"]["seconds"] = t_map
        out.append(r)
    return out


def run_all(folder: Path, seeds: list[int], jobs: int = 1, **kw) -> dict:
    """Every ``*.log`` / ``*.log.gz`` in ``folder`` for every seed, in ``jobs`` processes."""
    logs = sorted(p for p in Path(folder).iterdir()
                  if p.is_file() and (p.name.endswith(".log") or p.name.endswith(".log.gz")))
    if not logs:
        raise ValidationError(f"no CARMEN logs (*.log, *.log.gz) in {folder}")
    # the largest logs first, so that the workers finish together
    work = [(p, seeds, kw) for p in sorted(logs, key=lambda p: -p.stat().st_size)]
    t0 = time.perf_counter()
    if jobs > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            done = dict(zip([w[0] for w in work], pool.map(_run_seeds, work)))
    else:
        done = {w[0]: _run_seeds(w) for w in work}
    results = [r for p in logs for r in done[p]]
    pool_ = pooled(results)
    for r in results:
        r.pop("errors")
    return {"runs": results, "pooled": pool_, "per_log": per_log(results), "seeds": seeds,
            "settings": settings(), "runtime_s": time.perf_counter() - t0, "jobs": jobs}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, nargs="?", default=None, help="CARMEN log (plain or .gz) with corrected poses")
    ap.add_argument("--bag", type=Path, default=None, help="read scans, scan poses and odometry from this ROS bag")
    ap.add_argument("--scan-topic", default="/scan", help="with --bag: the sensor_msgs/LaserScan topic")
    ap.add_argument("--pose-topic", default="/scan_pose",
                    help="with --bag: the scans' corrected poses (PoseStamped, PoseWithCovarianceStamped, Odometry); "
                         "'none': odometry poses (no ground truth)")
    ap.add_argument("--odom-topic", default="/odom", help="with --bag: the nav_msgs/Odometry stream ('none': not read)")
    ap.add_argument("--pose-tolerance", type=float, default=0.01, metavar="S",
                    help="with --bag: seconds a scan's pose may be stamped from the scan (default 0.01)")
    ap.add_argument("--tf-topic", default="/tf_static", help="with --bag: static transforms (the laser's mount)")
    ap.add_argument("--base-frame", default=None,
                    help="with --bag: the robot's frame (default: the odometry's child_frame_id, else base_link)")
    ap.add_argument("--msg", action="append", default=[], metavar="FILE.msg",
                    help="with --bag: a message definition (.../PKG/msg/TYPE.msg or PKG/msg/TYPE=FILE) for bags that "
                         "store none (Humble sqlite3); repeatable")
    ap.add_argument("--all", type=Path, default=None, metavar="DIR", help="evaluate every *.log(.gz) in DIR")
    ap.add_argument("--json", type=Path, default=None, help="write the results (and per-scan series for one log)")
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR",
                    help="one log: write the top-down figure and the error plot (PNG) into DIR")
    ap.add_argument("--max-scans", type=int, default=None, help="use only the first N scans")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=str, default=None, help="with --all: comma-separated seeds (default: --seed)")
    ap.add_argument("--jobs", type=int, default=1, help="with --all: logs run at once in worker processes")
    ap.add_argument("--resolution", type=float, default=0.05, help="map cell size (m)")
    ap.add_argument("--map-range", type=float, default=30.0, help="readings below this are hits when mapping (m)")
    ap.add_argument("--laser-range", type=float, default=30.0, help="readings at or above this are ignored (m)")
    ap.add_argument("--odom-noise", type=float, default=1.0, help="scale of the simulated odometry noise")
    ap.add_argument("--only", choices=KEYS, default=None,
                    help="run one localizer alone (e.g. scan_matching while tuning it); the other is not run")
    ap.add_argument("-v", "--verbose", action="store_true", help="log recoveries (INFO)")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    if sum(x is not None for x in (args.log, args.bag, args.all)) != 1:
        ap.error("give one of LOG, --bag BAG or --all DIR")
    if args.only and args.plot:
        ap.error("--plot needs both localizers (no --only)")
    kw = {"max_scans": args.max_scans, "resolution": args.resolution, "map_range": args.map_range,
          "laser_range": args.laser_range, "odom_noise": args.odom_noise, "only": args.only}
    try:
        if args.all is not None:
            seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else [args.seed]
            res = run_all(args.all, seeds, jobs=max(1, args.jobs), **kw)
            print_all_table(res["runs"], res["pooled"], res["per_log"])
            print(f"run time {res['runtime_s']:.0f} s with --jobs {res['jobs']}")
        else:
            res = run(args)
            print_table(res)
    except (DfusionError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    plot = res.pop("_plot", None)
    if args.plot and plot is not None:
        print("wrote " + ", ".join(str(p) for p in figures(res, plot["grid"], args.plot)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
