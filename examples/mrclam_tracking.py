#!/usr/bin/env python
r"""Decentralized tracking of robot 1 by robots 2-5 on the UTIAS MRCLAM dataset.

Usage::

    python examples/mrclam_tracking.py DATASET_DIR [--duration S] [--json OUT] [--plot DIR]
        [--perturb {none,outliers,gap,odometry-scale,combined,all} ...] [--no-robust] [--jobs N]
    python examples/mrclam_tracking.py DATASET_DIR --bag BAG ...    (the robots' data from a ROS bag)

``DATASET_DIR`` is an MRCLAM dataset directory (e.g. ``DATA/mrclam/dataset6``, the
folder ``MRCLAM_Dataset6``, see ``tests/data/mrclam/README.md`` for where to get it; or
the slice ``tests/data/mrclam``). Robots 2, 3, 4 and 5 are fusion nodes of a tree
(chain 2 - 3 - 4 - 5 by default); robot 1 is the target.

Each observer robot ``k``:

1. **localizes itself** with a pose EKF (:class:`dfusion.localization.LandmarkEKF`):
   its velocity odometry integrated with the :class:`~dfusion.models.Unicycle` model
   (noise densities ``--std-v`` m/sqrt(s), ``--std-w`` rad/sqrt(s)) and its range-bearing
   measurements of the 15 landmarks at their surveyed positions (``--range-std``,
   ``--bearing-std``, the residual levels stated in the dataset README). Its landmark
   updates are robust (:data:`POSE_MONITOR`, :mod:`dfusion.estimation.innovation`):
   chi-square gate 13.8 (0.999), Huber weights beyond 5.99 (0.95), and lock-out
   recovery after 10 looks (scans) of rejected landmarks that agree on one pose jump. It
   starts from its ground-truth pose at time 0 with 5 cm / 0.05 rad uncertainty, as is
   usual with this dataset.
2. **tracks robot 1** in a :class:`~dfusion.fusion.FusionNode`. Target models
   (``--target-model``):

   * ``odometry`` (default): robot 1 shares its odometry (it is still not a node); the
     target state is its pose ``(x, y, theta)``, a :class:`~dfusion.models.Unicycle`
     driven by robot 1's velocities averaged over the 0.1 s filter grid, so the track is
     robot 1's dead reckoning corrected by the observers' fixes: the baseline of the issue
     (dead reckoning, 0.81 m over the first 300 s of dataset 6) plus the observations.
   * ``cv``: a :class:`~dfusion.models.ConstantVelocity` state ``(x, y, vx, vy)``
     (``--q``), information from the observations only. Robot 1 is observed only about
     half of the time (gaps up to 38 s in the first 300 s), so this track cannot be far
     better than dead reckoning (0.50 m against 0.81 m, ``docs/robots.md``).

   Each of its range-bearing measurements ``(r, b)`` of robot 1 is fused as a position fix
   (:meth:`~dfusion.models.TargetRangeBearing.position_fix`),
   ``p = s_xy + r (cos(theta_s + b), sin(theta_s + b))`` from the robot's estimated
   pose ``s``, which carries the robot's own pose uncertainty ``P_pose`` into the noise:
   ``R_eff = G R G^T + J P_pose J^T`` (``G = dp/d(r, b)``, ``J = dp/ds``; the polar form
   ``R + J_s P_pose J_s^T`` converted to the position). The fix is linear in robot 1's
   state, so a track that drifted during a long gap is not linearized at a wrong point.
   The fixes go through a
   :class:`~dfusion.frontends.TargetTrackingFrontEnd`
   (:data:`TARGET_MONITOR`): gated (13.8) against the node's *fused* estimate,
   Huber-weighted, and when the fixes of 5 looks (filter steps) are rejected, agree on where robot 1 is
   and no neighbour's information backed the node's belief meanwhile, the node's
   belief of robot 1's position is re-initialized from them (process noise added at
   the node only: nothing is double counted, ``docs/robots.md``). ``--no-robust``: the
   plain gate of before (lock-outs are then still detected and counted).
3. **exchanges** robot 1's information with its tree neighbours every
   ``--send-period`` seconds over a :class:`~dfusion.sim.SimulatedNetwork`
   (``--latency``).

The common prior of the nodes is robot 1's ground-truth position at time 0 with
``--prior-std`` (0.3 m) per axis and its true heading with 0.05 rad (``odometry``) or
zero velocity with 0.1 m/s (``cv``): the same knowledge of
the start as the dead-reckoning baseline, which integrates robot 1's own odometry from
its true initial pose.

With ``--bag BAG`` the robots' odometry, sightings and ground truth come from a ROS 1 or
ROS 2 bag (topics ``--odom-topic``, ``--sightings-topic``, ``--truth-topic``, patterns with
``{n}`` for the robot's number, by default ``/robot{n}/odom``, ``/robot{n}/sightings``,
``/robot{n}/ground_truth``; :func:`dfusion.bags.mrclam_from_bag`, ``docs/ros.md``);
``DATASET_DIR`` then only gives the landmark map (``Landmark_Groundtruth.dat``). ``--msg
FILE.msg`` gives the sightings' definition to a Humble sqlite3 bag, which stores none.

References:

* ``centralized``: one EKF over the joint state (robot 1's state, pose or constant velocity, and
  the four observers' poses, 15 or 16 numbers) given every odometry row and every landmark and
  robot-1 measurement of the four observers (same models, same robust treatment: the same
  monitors, one for robot 1's fixes and one per observer's landmarks, recovering on robot
  1's position block or on that observer's pose block): the reference every
  decentralized result is compared against (``docs/centralized.md``). It knows the
  correlations between the observers' poses and their
  robot-1 measurements, which the nodes approximate with ``R_eff``.
* ``centralized_tracking``: a :class:`~dfusion.estimation.CentralizedEKF` on robot 1's
  state given the union of the measurements the nodes accepted, with their ``R_eff``
  (Huber weights included): what the fusion network should reproduce (exactly, up to
  linearization points) as long as no node recovers; it has no recovery of its own.
* ``dead_reckoning``: each robot's odometry integrated from its true initial pose.

Estimates are recorded every ``--eval-dt`` seconds (0.5) while robot 1's ground truth
exists, after the node has processed everything that reached it by then. JSON keys:
``nodes.<robot>.rmse`` (robot 1's position), ``centralized.rmse``,
``centralized_tracking.rmse``, ``localization.<robot>.rmse`` (each observer's own pose,
and ``centralized_localization``), ``dead_reckoning.<robot>.rmse``, the gaps between
nodes and references, message counts and the run time; per node and for the joint EKF
also ``anees`` (average NEES of robot 1's position per dimension, 1 when consistent),
``gated`` (robot-1 fixes rejected) of ``target`` (seen), ``lockouts`` / ``detected``,
``recoveries``, ``pose_recoveries`` and ``recovery_events``.

**Evaluation** (``--perturb``): perturbed copies of the dataset built by
:func:`dfusion.datasets.perturb_mrclam`: ``outliers`` (10 % of the sightings of
robot 1 replaced by a range and bearing uniform in the span of all the dataset's
measurements), ``gap`` (all sightings of robot 1 removed for the densest 60 s),
``odometry-scale`` (the velocities of the observer that sees robot 1 most, scaled by
1.05), ``combined`` (the three), ``all`` (none and the four). Several runs print one
table (per node and the references: RMSE, ratio to the joint EKF, ANEES, gated,
detected lock-outs, recoveries, pose-EKF recoveries) and write
``{"runs": {kind: <the single-run JSON>}, "summary": [...], "runtime_s"}``;
``--jobs`` processes. ``--outlier-fraction``, ``--gap-seconds``, ``--gap-start``,
``--odometry-robot``, ``--odometry-scale`` change the perturbations (stress tests, e.g.
``--perturb odometry-scale --odometry-robot 1 --odometry-scale 1.2`` scales robot 1's
own odometry). Results on dataset 6 are in ``docs/robots.md``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from dfusion.datasets import (  # noqa: E402
    PERTURBATIONS,
    integrate_odometry,
    mean_velocities,
    perturb_mrclam,
    read_landmarks,
    read_mrclam,
)
from dfusion.errors import DfusionError  # noqa: E402
from dfusion.estimation.innovation import InnovationMonitor, MonitorSettings, monitored_update  # noqa: E402
from dfusion.frontends import TargetTrackingFrontEnd  # noqa: E402
from dfusion.fusion import FusionNode  # noqa: E402
from dfusion.localization import LandmarkEKF
from dfusion.models import LandmarkRangeBearing, TargetRangeBearing, VelocityOdometry
from dfusion.models import ConstantVelocity, Unicycle  # noqa: E402
from dfusion.geometry import wrap_angle  # noqa: E402
from dfusion.transport import LinkSpec, SimulatedNetwork  # noqa: E402

DEFAULTS = {
    "q": 0.0001,
    "std_v": 0.01,
    "std_w": 0.05,
    "range_std": 0.15,
    "bearing_std": 0.02,
    "prior_std": 0.3,
    "send_period": 1.0,
    "latency": 0.05,
    "eval_dt": 0.5,
    "grid_dt": 0.1,
    "gate": 13.8,
}


class JointEKF:
    """The centralized EKF: robot 1 (constant velocity or its odometry) + the observers' poses
    (unicycle), with the nodes' robust treatment: one :class:`InnovationMonitor` for the
    robot-1 fixes (the nodes' gate, Huber weights, lock-out recovery on robot 1's position
    block) and one per observer for its landmarks (those of the pose EKFs, recovery on that
    observer's pose block). ``settings=None``: the plain gate ``gate`` only."""

    def __init__(self, target_motion, odo: dict[int, VelocityOdometry], prior_mean, prior_cov,
                 poses0: dict[int, np.ndarray], pose_cov: np.ndarray, gate: float,
                 target_odometry: VelocityOdometry | None = None,
                 settings: MonitorSettings | None = None, pose_settings: MonitorSettings | None = None) -> None:
        self.cv = target_motion
        self.target_odometry = target_odometry  # robot 1's own odometry (target_model "odometry")
        self.odo = odo
        self.robots = sorted(odo)
        m = len(prior_mean)
        self.m = m
        n = m + 3 * len(self.robots)
        self.x = np.zeros(n)
        self.P = np.zeros((n, n))
        self.x[:m] = prior_mean
        self.P[:m, :m] = prior_cov
        self.idx = {}
        for i, r in enumerate(self.robots):
            s = m + 3 * i
            self.idx[r] = s
            self.x[s:s + 3] = poses0[r]
            self.P[s:s + 3, s:s + 3] = pose_cov
        self.t = 0.0
        self.gate = gate
        self.rejected = 0
        self.target_seen = 0
        self.target_rejected = 0
        self.settings = settings
        self.monitors: dict[str, InnovationMonitor] = {}
        if settings is not None:
            self.monitors["target"] = InnovationMonitor("joint/target", 2, settings)
            for r in self.robots:
                self.monitors[f"robot{r}"] = InnovationMonitor(f"joint/robot{r}", 2, pose_settings or settings)

    def predict_to(self, t: float) -> None:
        if t <= self.t:
            return
        n = self.x.size
        F = np.eye(n)
        Q = np.zeros((n, n))
        dt = t - self.t
        m = self.m
        if self.target_odometry is None:
            F[:m, :m] = self.cv.F(dt)
            Q[:m, :m] = self.cv.Q(dt)
            self.x[:m] = F[:m, :m] @ self.x[:m]
        else:
            xt, F[:m, :m], Q[:m, :m] = self.target_odometry.propagate(self.x[:m], self.t, t)
            self.x[:m] = xt
        for r, s in self.idx.items():
            xr, Fr, Qr = self.odo[r].propagate(self.x[s:s + 3], self.t, t)
            self.x[s:s + 3] = xr
            F[s:s + 3, s:s + 3] = Fr
            Q[s:s + 3, s:s + 3] = Qr
        self.P = F @ self.P @ F.T + Q
        self.P = 0.5 * (self.P + self.P.T)
        self.t = t

    def _fuse(self, nu, H, R) -> None:
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T   # P H^T S^-1 (S and P symmetric)
        self.x = self.x + K @ nu
        for s in self.idx.values():
            self.x[s + 2] = wrap_angle(self.x[s + 2])
        if self.target_odometry is not None:
            self.x[2] = wrap_angle(self.x[2])
        IKH = np.eye(self.x.size) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ R @ K.T
        self.P = 0.5 * (self.P + self.P.T)

    def _update(self, measure, R, monitor: str, block: slice, source=None) -> bool:
        """``measure()`` gives ``(nu, H)`` at the current estimate. Plain gate without
        settings; otherwise :func:`monitored_update`, monitoring the state ``block`` (the
        one a recovery inflates)."""
        if self.settings is None:
            nu, H = measure()
            S = H @ self.P @ H.T + R
            if float(nu @ np.linalg.solve(S, nu)) > self.gate:
                self.rejected += 1
                return False
            self._fuse(nu, H, R)
            return True

        def innovation():
            nu, H = measure()
            S = H @ self.P @ H.T + R
            return nu, 0.5 * (S + S.T), H[:, block], self.P[block, block]

        def fuse(w: float) -> None:
            nu, H = measure()
            self._fuse(nu, H, R / w)

        def inflate(Q_b) -> None:
            self.P[block, block] += Q_b   # process noise on the block

        a = monitored_update(self.monitors[monitor], self.t, innovation, fuse, inflate, source)
        self.rejected += int(not a.accept)
        return a.accept

    def update_landmark(self, r: int, z, sensor: LandmarkRangeBearing) -> bool:
        s = self.idx[r]
        z = np.asarray(z, float)

        def measure():
            H = np.zeros((2, self.x.size))
            H[:, s:s + 3] = sensor.H(self.x[s:s + 3])
            return sensor.residual(z, sensor.h(self.x[s:s + 3])), H

        return self._update(measure, sensor.R, f"robot{r}", slice(s, s + 3),
                            source=tuple(np.round(sensor.landmark, 6).tolist()))

    def update_target(self, r: int, z, R) -> bool:
        """Robot ``r``'s range-bearing ``z`` of the target, as the position fix seen from
        the current estimate of its pose: ``p = s_xy + r (cos, sin)(theta_s + b)``,
        ``p - q = J_c (s_hat - s) + G v``, so ``H = [I (target), -J_c (pose)]`` and the
        noise is ``G R G^T`` (linear in the target: robust when the target estimate is far
        off after a long gap, where the polar form linearizes badly)."""
        s = self.idx[r]
        rr, b = float(z[0]), float(z[1])
        pose = self.x[s:s + 3]
        c, sn = math.cos(pose[2] + b), math.sin(pose[2] + b)
        G = np.array([[c, -rr * sn], [sn, rr * c]])

        def measure():
            pose = self.x[s:s + 3]
            c, sn = math.cos(pose[2] + b), math.sin(pose[2] + b)
            p = pose[:2] + rr * np.array([c, sn])
            H = np.zeros((2, self.x.size))
            H[:, 0:2] = np.eye(2)
            H[:, s:s + 3] = -np.array([[1.0, 0.0, -rr * sn], [0.0, 1.0, rr * c]])
            return p - self.x[:2], H

        ok = self._update(measure, G @ R @ G.T, "target", slice(0, 2))
        self.target_seen += 1
        self.target_rejected += int(not ok)
        return ok

    def recoveries(self, key: str) -> int:
        mon = self.monitors.get(key)
        return 0 if mon is None else mon.stats.recoveries


#: Robust settings of the robot-1 trackers (nodes and joint EKF): gate 0.999, Huber 0.95,
#: lock-out after k = 5 looks of rejected fixes (false alarm 1e-3 with up to 25 %
#: independent outliers), NIS window of 10 tracked, drift test off (docs/robots.md:
#: measured, it hurts here).
TARGET_MONITOR = MonitorSettings(drift_test=False)
#: The same for the landmark updates of the pose EKFs (and the joint EKF's pose blocks),
#: except k = 10 looks (up to 50 % outliers): MRCLAM's landmark range failures come in bursts
#: on neighbouring landmarks, which k = 5 mistakes for lock-outs (docs/robots.md).
POSE_MONITOR = MonitorSettings(drift_test=False, max_outlier_rate=0.5)


def monitor_settings(args: argparse.Namespace) -> tuple[MonitorSettings, MonitorSettings] | None:
    """The robust settings of the target trackers and of the pose EKFs
    (:class:`MonitorSettings` defaults: gate 0.999, Huber 0.95, false alarm 1e-3, run test
    up to 25 % outliers, drift test ``--target-drift-test`` / ``--pose-drift-test``), or ``None``
    with ``--no-robust`` (the plain gate ``--gate`` of the landmark EKFs, the nodes and the
    joint EKF, no Huber weights, no recovery)."""
    if getattr(args, "no_robust", False):
        return None
    return (replace(TARGET_MONITOR, drift_test=bool(getattr(args, "target_drift_test", False))),
            replace(POSE_MONITOR, drift_test=bool(getattr(args, "pose_drift_test", False))))


def plain_gate(args: argparse.Namespace) -> MonitorSettings:
    """``--no-robust`` for the nodes' fixes: the gate ``--gate`` only; lock-outs are still
    detected and counted (``lockouts``) but nothing is done about them."""
    return MonitorSettings(gate_probability=float(chi2.cdf(args.gate, 2)), huber_probability=None,
                           drift_test=False, recover=False)


def perturb_options(args: argparse.Namespace) -> dict:
    """Keyword arguments of :func:`perturb_mrclam` given on the command line (stress tests)."""
    keys = ("outlier_fraction", "gap_seconds", "gap_start", "odometry_robot", "odometry_scale")
    return {k: getattr(args, k) for k in keys if getattr(args, k, None) is not None}


def anees(err: np.ndarray, cov: np.ndarray) -> float:
    """Average NEES per dimension, ``mean_k e_k^T P_k^-1 e_k / d`` (1 for a consistent
    estimator; Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2)."""
    if not len(err):
        return float("nan")
    nees = np.einsum("ki,ki->k", err, np.linalg.solve(cov, err[..., None])[..., 0])
    return float(np.mean(nees) / err.shape[1])


def rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.atleast_2d(err) ** 2, axis=-1)))) if len(err) else float("nan")


def load_dataset(args: argparse.Namespace):
    """The dataset directory, or the bag ``args.bag`` with the directory's landmark map."""
    if getattr(args, "bag", None):
        from dfusion.bags import mrclam_from_bag

        from dfusion.bags import msgdefs_from_files

        topics = {"odometry": args.odom_topic, "sightings": args.sightings_topic, "ground_truth": args.truth_topic}
        return mrclam_from_bag(args.bag, read_landmarks(args.dataset)[1], duration=args.duration, topics=topics,
                               msgdefs=msgdefs_from_files(args.msg))
    return read_mrclam(args.dataset, duration=args.duration)


def run(args: argparse.Namespace, ds=None) -> dict:
    """Track the target on ``ds`` (default: :func:`load_dataset`); see the module docstring."""
    t_wall = time.perf_counter()
    ds = load_dataset(args) if ds is None else ds
    target = args.target
    observers = list(args.observers)
    perturb = getattr(args, "perturb", "none")
    if isinstance(perturb, (list, tuple)):   # as parsed: one kind runs here, several in evaluate()
        if len(perturb) != 1 or perturb[0] == "all":
            raise DfusionError(f"run() takes one perturbation, got {perturb}; evaluate() runs several")
        perturb = perturb[0]
    if perturb != "none":
        ds = perturb_mrclam(ds, perturb, target=target, observers=tuple(observers), seed=args.seed,
                            **perturb_options(args))
    if target in observers or target not in ds.robots or any(o not in ds.robots for o in observers):
        raise DfusionError("target and observers must be distinct robots of the dataset")
    odo_mode = args.target_model == "odometry"
    lm_ids, lm_xy = ds.landmark_array()
    landmarks = {int(i): xy for i, xy in zip(lm_ids, lm_xy)}
    tr = ds.robots[target]
    t_end = min(float(tr.gt_t[-1]), args.duration if args.duration else math.inf)
    for o in observers:
        t_end = min(t_end, float(ds.robots[o].gt_t[-1]))
    every = max(1, int(round(args.eval_dt / args.grid_dt)))
    grid = np.round(args.grid_dt * np.arange(1, int(math.floor(t_end / args.grid_dt + 1e-9)) + 1), 9)
    is_eval = (np.arange(1, grid.size + 1) % every) == 0
    eval_t = grid[is_eval]

    motion = Unicycle(args.std_v, args.std_w)
    odo = {o: VelocityOdometry(ds.robots[o].odom_t, ds.robots[o].odom, motion) for o in observers}
    P_pose0 = np.diag([0.05**2, 0.05**2, 0.05**2])
    pose0 = {o: ds.robots[o].truth_at(0.0) for o in observers}
    both = monitor_settings(args)
    settings, pose_settings = (None, None) if both is None else both
    if settings is None:
        ekfs = {o: LandmarkEKF(odo[o], 0.0, pose0[o], P_pose0, gate=args.gate) for o in observers}
    else:
        ekfs = {o: LandmarkEKF(odo[o], 0.0, pose0[o], P_pose0,
                               monitor=InnovationMonitor(f"robot{o}/pose", 2, pose_settings)) for o in observers}

    p1 = tr.truth_at(0.0)
    if odo_mode:
        # robot 1 shares its odometry: the target is its pose, driven by that odometry
        tmotion = Unicycle(args.std_v, args.std_w)
        prior_mean = p1.copy()
        prior_cov = np.diag([args.prior_std**2] * 2 + [0.05**2])
        u_grid = mean_velocities(tr.odom_t, tr.odom, np.concatenate([[0.0], grid]))
        target_odo = VelocityOdometry(tr.odom_t, tr.odom, tmotion)
    else:
        tmotion = ConstantVelocity(2, args.q)
        prior_mean = np.array([p1[0], p1[1], 0.0, 0.0])
        prior_cov = np.diag([args.prior_std**2] * 2 + [0.1**2] * 2)
        u_grid = None
        target_odo = None
    names = {o: f"robot{o}" for o in observers}
    links = [(names[a], names[b]) for a, b in zip(observers[:-1], observers[1:])]  # chain
    nbrs = {names[o]: [] for o in observers}
    for a, b in links:
        nbrs[a].append(b)
        nbrs[b].append(a)
    nodes = {o: FusionNode(names[o], nbrs[names[o]], tmotion, window=600, horizon=60.0,
                           prior=(0.0, prior_mean, prior_cov), epoch=o) for o in observers}
    spec = LinkSpec(latency=args.latency)
    net = SimulatedNetwork([(a, b, spec) for a, b in links], seed=args.seed)
    joint = JointEKF(tmotion, odo, prior_mean, prior_cov, pose0, P_pose0, args.gate, target_odo, settings,
                     pose_settings)
    fronts = {o: TargetTrackingFrontEnd(InnovationMonitor(f"{names[o]}/target", 2, settings or plain_gate(args)))
              for o in observers}
    # the union of the nodes' accepted measurements in one delayed-state EIF (no network)
    central_trk = FusionNode("central", [], tmotion, window=600, horizon=60.0, prior=(0.0, prior_mean, prior_cov))
    n_central = 0

    # events: (t, kind, robot, row); kind 0 = landmark, 1 = target observation
    events = []
    for o in observers:
        r = ds.robots[o]
        for i in range(r.meas_t.size):
            s = int(r.meas_subject[i])
            if r.meas_t[i] > grid[-1]:
                continue
            if s in landmarks:
                events.append((float(r.meas_t[i]), 0, o, i))
            elif s == target:
                events.append((float(r.meas_t[i]), 1, o, i))
    events.sort()
    R0 = np.diag([args.range_std**2, args.bearing_std**2])
    counts = {o: {"landmarks": 0, "landmarks_rejected": 0, "target": 0, "target_rejected": 0} for o in observers}
    rec_nodes = {o: np.empty((eval_t.size, 2)) for o in observers}
    rec_cov = {o: np.empty((eval_t.size, 2, 2)) for o in observers}
    rec_loc_cov = {o: np.empty((eval_t.size, 3, 3)) for o in observers}
    cov_joint = np.empty((eval_t.size, 2, 2))
    cov_ct = np.empty((eval_t.size, 2, 2))
    rec_loc = {o: np.empty((eval_t.size, 3)) for o in observers}
    rec_joint = np.empty((eval_t.size, 2))
    rec_ct = np.empty((eval_t.size, 2))
    rec_joint_pose = {o: np.empty((eval_t.size, 3)) for o in observers}
    next_send = args.send_period
    ie = 0
    ke = 0

    def advance(node: FusionNode, t: float, k: int) -> None:
        """Predict a node to ``t`` (CV: any time; odometry: grid step ``k`` with its control)."""
        if t > node.latest_time + 1e-9:
            node.predict(t, u_grid[k] if odo_mode else None)

    def network(t: float, k: int) -> None:
        nonlocal next_send
        for o in observers:
            for d in net.receive(names[o], t + 1e-9):
                nodes[o].receive(d.data)
        while next_send <= t + 1e-9:
            ts = next_send
            for o in observers:
                node = nodes[o]
                if not odo_mode:
                    advance(node, ts, k)
                for nb in node.neighbors:
                    net.send(node.name, nb, node.message_to(nb, sent_at=ts), ts)
            next_send += args.send_period

    for k, tg in enumerate(grid):
        tg = float(tg)
        if odo_mode:
            for o in observers:
                advance(nodes[o], tg, k)
        while ie < len(events) and events[ie][0] <= tg + 1e-9:
            t, kind, o, i = events[ie]
            ie += 1
            r = ds.robots[o]
            z = np.array([r.meas_range[i], r.meas_bearing[i]])
            ekf = ekfs[o]
            ekf.predict(t)
            joint.predict_to(t)
            if kind == 0:
                sensor = LandmarkRangeBearing(landmarks[int(r.meas_subject[i])], args.range_std, args.bearing_std)
                ok = ekf.update(t, z, sensor)
                counts[o]["landmarks"] += 1
                counts[o]["landmarks_rejected"] += int(not ok)
                joint.update_landmark(o, z, sensor)
                continue
            sensor = TargetRangeBearing(ekf.x, ekf.P, z, args.range_std, args.bearing_std).position_fix()
            node = nodes[o]
            if odo_mode:
                t_node = tg  # the state of the grid step the measurement falls in
            else:
                network(t, k)
                advance(node, t, k)
                t_node = t
            fe = fronts[o]
            n_fused = len(fe.fused)
            counts[o]["target"] += 1
            if not fe.assess(node, t_node, sensor).accept:
                counts[o]["target_rejected"] += 1
            for tf, fused in fe.fused[n_fused:]:   # the fix as fused (Huber weight included)
                advance(central_trk, tf, k)
                central_trk.update(tf, fused.z, fused)
                n_central += 1
            # the joint EKF uses the raw noise: it estimates the observer's pose jointly
            joint.update_target(o, z, R0)
        network(tg, k)
        if not is_eval[k]:
            continue
        for o in observers:
            node = nodes[o]
            advance(node, tg, k)
            m_, P_ = node.estimate(tg)
            rec_nodes[o][ke], rec_cov[o][ke] = m_[:2], P_[:2, :2]
            ekfs[o].predict(tg)
            rec_loc[o][ke] = ekfs[o].x
            rec_loc_cov[o][ke] = ekfs[o].P
        joint.predict_to(tg)
        rec_joint[ke] = joint.x[:2]
        cov_joint[ke] = joint.P[:2, :2]
        advance(central_trk, tg, k)
        mc, Pc = central_trk.estimate(tg)
        rec_ct[ke] = mc[:2]
        cov_ct[ke] = Pc[:2, :2]
        for o in observers:
            s = joint.idx[o]
            rec_joint_pose[o][ke] = joint.x[s:s + 3]
        ke += 1

    truth1 = tr.truth_at(eval_t)[:, :2]
    out: dict = {
        "dataset": str(args.dataset),
        "target": target,
        "target_model": args.target_model,
        "observers": observers,
        "tree": [list(l) for l in links],
        "span": [float(eval_t[0]) if eval_t.size else 0.0, float(t_end)],
        "eval_points": int(eval_t.size),
        "parameters": {k: getattr(args, k) for k in DEFAULTS},
        "robust": None if settings is None else {"target": asdict(settings), "pose": asdict(pose_settings)},
        "perturbation": perturb,
        "perturbation_options": perturb_options(args),
        "nodes": {},
        "localization": {},
        "centralized_localization": {},
        "dead_reckoning": {},
    }
    for o in observers:
        e = rec_nodes[o] - truth1
        out["nodes"][str(o)] = {
            "rmse": rmse(e),
            "gap_to_centralized": float(np.mean(np.hypot(*(rec_nodes[o] - rec_joint).T))),
            "gap_to_centralized_tracking": float(np.mean(np.hypot(*(rec_nodes[o] - rec_ct).T))),
            "anees": anees(e, rec_cov[o]),
            "messages": nodes[o].stats.messages_sent,
            "bytes": nodes[o].stats.bytes_sent,
            **counts[o],
            "gated": counts[o]["target_rejected"],
            "downweighted": fronts[o].monitor.stats.downweighted,
            "lockouts": fronts[o].monitor.stats.lockouts,
            "drifts": fronts[o].monitor.stats.drifts,
            "detected": fronts[o].monitor.stats.lockouts + fronts[o].monitor.stats.drifts,
            "nis_mean": fronts[o].monitor.stats.nis_sum / max(1, fronts[o].monitor.stats.tested),
            "window_nis_max": fronts[o].monitor.stats.window_nis_max,
            "recoveries": fronts[o].monitor.stats.recoveries,
            "pose_recoveries": ekfs[o].recoveries,
            "recovery_events": fronts[o].monitor.stats.events,
        }
        gt = ds.robots[o].truth_at(eval_t)
        out["localization"][str(o)] = {
            "rmse": rmse(rec_loc[o][:, :2] - gt[:, :2]),
            "heading_rmse": float(np.sqrt(np.mean(wrap_angle(rec_loc[o][:, 2] - gt[:, 2]) ** 2))),
        }
        out["centralized_localization"][str(o)] = {"rmse": rmse(rec_joint_pose[o][:, :2] - gt[:, :2])}
    jt = joint.monitors.get("target")
    out["centralized"] = {
        "rmse": rmse(rec_joint - truth1),
        "anees": anees(rec_joint - truth1, cov_joint),
        "rejected": joint.rejected,
        "gated": joint.target_rejected,
        "target": joint.target_seen,
        "downweighted": None if jt is None else jt.stats.downweighted,
        "lockouts": None if jt is None else jt.stats.lockouts,
        "drifts": None if jt is None else jt.stats.drifts,
        "detected": None if jt is None else jt.stats.lockouts + jt.stats.drifts,
        "nis_mean": None if jt is None else jt.stats.nis_sum / max(1, jt.stats.tested),
        "window_nis_max": None if jt is None else jt.stats.window_nis_max,
        "recoveries": joint.recoveries("target"),
        "pose_recoveries": sum(joint.recoveries(f"robot{o}") for o in observers),
        "recovery_events": [] if jt is None else jt.stats.events,
    }
    out["centralized_tracking"] = {"rmse": rmse(rec_ct - truth1), "anees": anees(rec_ct - truth1, cov_ct),
                                   "measurements": n_central}
    for r in [target, *observers]:
        rl = ds.robots[r]
        dr = integrate_odometry(rl.odom_t, rl.odom, rl.truth_at(0.0), 0.0, eval_t)
        out["dead_reckoning"][str(r)] = {"rmse": rmse(dr[:, :2] - rl.truth_at(eval_t)[:, :2])}
    out["runtime_s"] = time.perf_counter() - t_wall
    dr1 = integrate_odometry(tr.odom_t, tr.odom, tr.truth_at(0.0), 0.0, eval_t)
    # per evaluation point (lists, for --json): time (s); robot 1's true position, each node's
    # estimate (m) with its 2x2 covariance (m^2); each observer's own pose (x, y m, theta rad),
    # its landmark EKF estimate and covariance; the references
    out["series"] = {
        "t": eval_t.tolist(), "truth": truth1.tolist(),
        "nodes": {str(o): {"mean": rec_nodes[o].tolist(), "cov": rec_cov[o].tolist()} for o in observers},
        "observers": {str(o): {"truth": ds.robots[o].truth_at(eval_t).tolist(), "mean": rec_loc[o].tolist(),
                               "cov": rec_loc_cov[o].tolist()} for o in observers},
        "centralized": rec_joint.tolist(), "centralized_tracking": rec_ct.tolist(),
        "dead_reckoning": dr1[:, :2].tolist(),
    }
    out["landmarks"] = {str(k): [float(v) for v in xy] for k, xy in landmarks.items()}
    return out


def figures(res: dict, out: Path) -> list[Path]:
    """``out/mrclam_topdown.png`` (the robots, the landmarks, robot 1's path and every node's
    estimate of it with 3-sigma ellipses, the chain) and ``out/mrclam_errors.png`` (each
    node's X and Y error of robot 1 against the centralized joint EKF's)."""
    from dfusion.viz.plots import plot_track_errors
    from dfusion.viz.topdown import Scene, Track, draw_scene

    ser = res["series"]
    t = np.asarray(ser["t"])
    truth = np.asarray(ser["truth"])
    tgt = res["target"]
    colors = ["tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan"]
    names = {o: f"robot{o}" for o in ser["nodes"]}
    node_colors = {names[o]: colors[i % len(colors)] for i, o in enumerate(ser["nodes"])}
    node_colors[f"robot{tgt}"] = "tab:green"
    tracks = [Track(names[o], t, np.asarray(v["mean"]), np.asarray(v["cov"]), node_colors[names[o]])
              for o, v in ser["nodes"].items()]
    joint = Track("centralized (joint EKF)", t, np.asarray(ser["centralized"]), None, "k", style="--", width=0.8)
    dr = Track(f"robot {tgt} dead reckoning", t, np.asarray(ser["dead_reckoning"]), None, "0.45", style=":",
               width=1.0)
    lm = res["landmarks"]
    scene = Scene(
        title=f"MRCLAM {Path(res['dataset']).name}: robot {tgt} tracked by robots {res['observers']} "
              f"({res['span'][0]:.0f}-{res['span'][1]:.0f} s)",
        truth={f"robot {tgt} (target)": (t, truth),
               **{f"robot {o} (observer)": (t, np.asarray(v["truth"])[:, :2]) for o, v in ser["observers"].items()}},
        tracks=[*tracks, joint, dr],
        points={"landmarks (surveyed, numbered)": (np.array(list(lm.values())), "*", "gold")},
        labels=[(xy, k) for k, xy in lm.items()],
        tree=([f"robot{o}" for o in res["observers"]], [tuple(e) for e in res["tree"]]),
        node_colors=node_colors,
        truth_colors={f"robot {o} (observer)": node_colors[names[o]] for o in ser["observers"]},
        note="RMSE of robot 1's position: " + ", ".join(f"robot{o} {v['rmse']:.2f} m" for o, v in res["nodes"].items())
             + f"; joint EKF {res['centralized']['rmse']:.2f} m, dead reckoning "
             f"{res['dead_reckoning'][str(tgt)]['rmse']:.2f} m",
    )
    out.mkdir(parents=True, exist_ok=True)
    scene.note += "\n(the nodes' estimates nearly coincide: their rings overlap; dashed paths: the observers)"
    a = draw_scene(scene, out / "mrclam_topdown.png")
    b = plot_track_errors(t, truth, tracks, out / "mrclam_errors.png", reference=joint,
                          title=f"MRCLAM: each node's error of robot {tgt}'s position (coloured, with its ±3σ) "
                                f"against the centralized joint EKF's (black)")
    return [a, b]


def print_tables(res: dict) -> None:
    t0, t1 = res["span"]
    tgt = res["target"]
    print(f"MRCLAM {res['dataset']}: robot {tgt} ({res['target_model']} model) tracked by robots {res['observers']} "
          f"(tree {res['tree']}), {t0:.1f}-{t1:.1f} s, {res['eval_points']} evaluation points")
    print(f"\nrobot {tgt} position RMSE (m)")
    print(f"{'estimator':<28}{'RMSE':>8}{'gap to central':>16}{'obs used/seen':>15}")
    for o, v in res["nodes"].items():
        print(f"{'node robot' + o:<28}{v['rmse']:>8.3f}{v['gap_to_centralized']:>16.3f}"
              f"{(str(v['target'] - v['target_rejected']) + '/' + str(v['target'])):>15}")
    print(f"{'centralized (joint EKF)':<28}{res['centralized']['rmse']:>8.3f}")
    print(f"{'centralized tracking (R_eff)':<28}{res['centralized_tracking']['rmse']:>8.3f}")
    print(f"{'dead reckoning':<28}{res['dead_reckoning'][str(tgt)]['rmse']:>8.3f}")
    print("\nobserver self-localization RMSE (m)")
    print(f"{'robot':<8}{'landmark EKF':>14}{'heading (rad)':>15}{'joint EKF':>11}{'dead reckoning':>16}")
    for o, v in res["localization"].items():
        print(f"{o:<8}{v['rmse']:>14.3f}{v['heading_rmse']:>15.3f}{res['centralized_localization'][o]['rmse']:>11.3f}"
              f"{res['dead_reckoning'][o]['rmse']:>16.3f}")
    print(f"\nrun time {res['runtime_s']:.1f} s")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="MRCLAM dataset directory (with --bag: only its landmark map)")
    ap.add_argument("--bag", type=Path, default=None, help="read the robots' data from this ROS 1 / ROS 2 bag")
    ap.add_argument("--odom-topic", default="/robot{n}/odom", help="with --bag: robot {n}'s velocity odometry")
    ap.add_argument("--sightings-topic", default="/robot{n}/sightings", help="with --bag: robot {n}'s sightings")
    ap.add_argument("--truth-topic", default="/robot{n}/ground_truth",
                    help="with --bag: robot {n}'s ground truth (PoseStamped, PoseWithCovarianceStamped, Odometry)")
    ap.add_argument("--msg", action="append", default=[], metavar="FILE.msg",
                    help="with --bag: a message definition (.../PKG/msg/TYPE.msg or PKG/msg/TYPE=FILE) for bags that "
                         "store none (Humble sqlite3); repeatable")
    ap.add_argument("--duration", type=float, default=None, help="use the first S seconds")
    ap.add_argument("--json", type=Path, default=None, help="write the results (and the per-step series) as JSON")
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR",
                    help="write the top-down figure and the error plot (PNG) into DIR")
    ap.add_argument("--target", type=int, default=1)
    ap.add_argument("--observers", type=int, nargs="+", default=[2, 3, 4, 5], help="tree order: a chain")
    ap.add_argument("--seed", type=int, default=0, help="network seed (and the outliers' seed)")
    ap.add_argument("--perturb", nargs="+", choices=(*PERTURBATIONS, "all"), default=["none"],
                    help="perturbed copies of the dataset to run (dfusion.datasets.perturb_mrclam); "
                         "'all': none, outliers, gap, odometry-scale and combined")
    ap.add_argument("--jobs", type=int, default=2, help="processes for several runs")
    ap.add_argument("--outlier-fraction", type=float, default=None, help="perturbation: default 0.1")
    ap.add_argument("--gap-seconds", type=float, default=None, help="perturbation: default 60")
    ap.add_argument("--gap-start", type=float, default=None, help="perturbation: default the densest window")
    ap.add_argument("--odometry-robot", type=int, default=None,
                    help="perturbation: default the observer with the most sightings of the target")
    ap.add_argument("--odometry-scale", type=float, default=None, help="perturbation: default 1.05")
    ap.add_argument("--no-robust", action="store_true",
                    help="plain gate only: no Huber weights, no lock-out recovery (the behaviour before)")
    ap.add_argument("--target-drift-test", action="store_true",
                    help="turn the drift test of the target trackers on (off by default: docs/robots.md)")
    ap.add_argument("--pose-drift-test", action="store_true",
                    help="turn the drift test of the pose EKFs on (off by default: docs/robots.md)")
    ap.add_argument("--target-model", choices=("cv", "odometry"), default="odometry",
                    help="odometry (default): robot 1's odometry drives its motion model, the observers' fixes "
                         "correct it; cv: constant velocity from the observations only")
    for k, v in DEFAULTS.items():
        ap.add_argument("--" + k.replace("_", "-"), type=float, default=v)
    return ap


ESTIMATOR_ROWS = ("nodes", "centralized", "centralized_tracking")


def summary_rows(runs: dict[str, dict]) -> list[dict]:
    """One row per (run, estimator): RMSE, its ratio to the joint EKF's, ANEES, fixes
    gated out, tracker recoveries and pose-EKF recoveries."""
    rows = []
    for kind, res in runs.items():
        joint = res["centralized"]["rmse"]
        ests = [(f"node robot{o}", v) for o, v in res["nodes"].items()]
        ests += [("joint EKF", res["centralized"]), ("centralized tracking", res["centralized_tracking"])]
        for name, v in ests:
            rows.append({
                "run": kind, "estimator": name, "rmse": v["rmse"], "ratio_to_joint": v["rmse"] / joint,
                "anees": v["anees"], "gated": v.get("gated"), "seen": v.get("target"),
                "detected": v.get("detected"), "recoveries": v.get("recoveries"),
                "pose_recoveries": v.get("pose_recoveries"),
            })
    return rows


def print_summary(runs: dict[str, dict]) -> None:
    """The evaluation table: every run, every node and the references."""
    first = next(iter(runs.values()))
    t0, t1 = first["span"]
    print(f"\nrobot {first['target']} tracked by robots {first['observers']} ({first['target_model']} model), "
          f"{t0:.1f}-{t1:.1f} s; robust updates {'on' if first['robust'] else 'off'}")
    print(f"{'run':<16}{'estimator':<22}{'RMSE':>7}{'x joint':>9}{'ANEES':>8}{'gated/seen':>12}"
          f"{'detected':>10}{'recov.':>8}{'pose rec.':>10}")

    def cell(v) -> str:
        return "" if v is None else str(v)

    for r in summary_rows(runs):
        gs = "" if r["gated"] is None else f"{r['gated']}/{r['seen']}"
        print(f"{r['run']:<16}{r['estimator']:<22}{r['rmse']:>7.3f}{r['ratio_to_joint']:>9.3f}{r['anees']:>8.2f}"
              f"{gs:>12}{cell(r['detected']):>10}{cell(r['recoveries']):>8}{cell(r['pose_recoveries']):>10}")


def _run_kind(args: argparse.Namespace, kind: str) -> dict:
    a = argparse.Namespace(**vars(args))
    a.perturb = kind
    return run(a)


def evaluate(args: argparse.Namespace, kinds: list[str]) -> dict:
    """Run every perturbation in ``kinds`` (``--jobs`` processes) and collect the results."""
    t_wall = time.perf_counter()
    jobs = max(1, min(int(args.jobs), len(kinds)))
    if jobs == 1:
        results = [_run_kind(args, k) for k in kinds]
    else:
        from concurrent.futures import ProcessPoolExecutor  # noqa: PLC0415

        with ProcessPoolExecutor(jobs) as pool:
            results = list(pool.map(_run_kind, [args] * len(kinds), kinds))
    runs = dict(zip(kinds, results))
    return {"runs": runs, "summary": summary_rows(runs), "runtime_s": time.perf_counter() - t_wall}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    kinds = list(PERTURBATIONS) if "all" in args.perturb else list(dict.fromkeys(args.perturb))
    try:
        if len(kinds) == 1:
            args.perturb = kinds[0]
            out = run(args)
            print_tables(out)
            print_summary({kinds[0]: out})
        else:
            out = evaluate(args, kinds)
            print_summary(out["runs"])
            print(f"\nrun time {out['runtime_s']:.1f} s ({args.jobs} processes)")
    except (DfusionError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.plot:
        if len(kinds) == 1:
            print("wrote " + ", ".join(str(p) for p in figures(out, args.plot)))
        else:   # one pair of figures per run
            for kind, res in out["runs"].items():
                print("wrote " + ", ".join(str(p) for p in figures(res, args.plot / kind)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
