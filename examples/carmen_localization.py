#!/usr/bin/env python
r"""Map-based localization on a real CARMEN laser log: MCL and scan matching + odometry EKF.

Usage::

    python examples/carmen_localization.py LOG.gz [--json OUT] [--plot DIR] [--max-scans N] [--seed S]
    python examples/carmen_localization.py --bag BAG ...   (scans and poses from a ROS bag)

``LOG`` is a CARMEN log with corrected poses, e.g. ``DATA/carmen/intel-corrected.log.gz``
(where to get it: ``tests/data/carmen/README.md``; the slice
``tests/data/carmen/intel-160scans.log.gz`` runs as is) (read with
:func:`dfusion.datasets.carmen.read_carmen`, which handles the log's pitfalls: repeated
``ODOM`` copies after each scan, backward time stamps, 81.83 m "no return" readings).

With ``--bag BAG`` the scans (``/scan``, ``sensor_msgs/LaserScan``), their corrected poses
(``/scan_pose``, ``geometry_msgs/PoseStamped``) and the odometry stream (``/odom``) come
from a ROS 1 or ROS 2 bag (:func:`dfusion.bags.carmen_from_bag`, ``docs/ros.md``).

Protocol (scans in time order, the first ``--max-scans`` of them if given):

1. **Map**: the even-numbered scans (0, 2, 4, ...) at their corrected poses build an
   occupancy grid (:func:`dfusion.maps.grid_from_scans`, 5 cm cells, readings
   below ``--map-range`` = 30 m are hits, longer ones clear the cells up to 30 m).
2. **Localization**: the odd-numbered scans, none of them in the map, are localized
   against it. The ground truth is their corrected pose.
3. **Odometry**: derived from the corrected pose sequence of *all* scans (the ODOM
   stream of this log is not consistent with the scan poses: 5 cm / 2.6 deg median
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
   KLD 500-5,000 particles, 60 beams, odometry motion model with
   ``alpha = ((2 * 0.05)^2, (2 * 0.02)^2, (2 * 0.05)^2, 0.01)``, i.e. about twice the
   simulated noise) is started from the first localization scan's true pose with
   0.1 m / 0.05 rad uncertainty (pose tracking) and updated with every odometry pose and
   every localization scan; its estimate after each scan is compared with the truth.
5. **Scan matching + EKF**: :class:`~dfusion.localization.OdometryEKF` (survey eq. 5-8)
   predicts with the odometry increments (noise 1.5 times the simulated one:
   ``k_d = 0.075``, ``k_theta = 0.075``, ``k_dtheta = 0.03``, floors 1 cm and 5 mrad); at each localization scan point-to-line ICP
   (:meth:`~dfusion.localization.ScanMatcher.from_grid`, 0.5 m correspondence gate,
   10 % trimming) starts from the prediction; the match (covariance scaled by 4 and
   increased by 5 cm / 0.02 rad, since the Hessian covariance is optimistic and the map
   has 5 cm cells) updates the
   EKF unless ICP fails or the chi-square gate (3 dof, 99.9 %) rejects it.

Runtime: the full Intel log (910 scans: 455 in the map, 455 localized) takes 3-10 s
depending on the machine's load (map 1-2 s); no subsampling is needed. Output: a table and, with
``--json``, ``mcl.rmse``, ``mcl.heading_rmse``, ``scan_matching.rmse``,
``scan_matching.heading_rmse`` (m, rad) and more (``docs/robots.md`` has the results).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from dfusion.maps.mapping import grid_from_scans


from dfusion.datasets import read_carmen  # noqa: E402
from dfusion.errors import DfusionError, ValidationError  # noqa: E402
from dfusion.models import LaserConfig, LikelihoodFieldModel, OdometryMotionModel
from dfusion.localization import MonteCarloLocalization, OdometryEKF, scan_to_points, ScanMatcher
from dfusion.geometry import se2_between, se2_compose  # noqa: E402
from dfusion.geometry import wrap_angle  # noqa: E402

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


def ekf_predict(ekf: OdometryEKF, o0: np.ndarray, o1: np.ndarray, t: float) -> None:
    """Predict the EKF with the odometry step ``o0 -> o1`` as two eq. 5-6 steps.

    Eq. 5 moves the robot along its heading; a robot that turns in place here moves its
    laser 3-7 cm *sideways*, which one ``(Delta d, Delta theta)`` step would put along the
    heading. So the step is split exactly into a turn ``rot1`` towards the direction of
    travel and a ``(trans, rot2)`` step (``trans < 0`` for a step backwards). The noise of
    the whole step, ``(k_d trans)^2 + s_d^2`` and ``(k_theta Delta theta)^2 + (k_dtheta
    trans)^2 + s_theta^2``, goes into the second part (``rot1`` is an arbitrary angle when
    ``trans`` is tiny and must not scale the noise).
    """
    d = se2_between(o0, o1)
    trans = math.hypot(d[0], d[1])
    rot1 = math.atan2(d[1], d[0]) if trans > 1e-9 else 0.0
    if abs(rot1) > math.pi / 2:
        rot1 = float(wrap_angle(rot1 + math.pi))
        trans = -trans
    rot2 = float(wrap_angle(d[2] - rot1))
    ekf.predict(None, (0.0, rot1), Sigma_u=np.diag([1e-12, 1e-12]))
    ekf.predict(t, (trans, rot2), Sigma_u=ekf.odometry_covariance(abs(trans), float(d[2])))


def pose_errors(est: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1]), np.abs(wrap_angle(est[:, 2] - truth[:, 2]))


def summary(pos: np.ndarray, head: np.ndarray) -> dict:
    return {
        "rmse": float(np.sqrt(np.mean(pos**2))),
        "heading_rmse": float(np.sqrt(np.mean(head**2))),
        "median": float(np.median(pos)),
        "p95": float(np.percentile(pos, 95)),
        "max": float(np.max(pos)),
    }


def load_log(args: argparse.Namespace):
    """The CARMEN log ``args.log``, or the bag ``args.bag``."""
    if getattr(args, "bag", None):
        from dfusion.bags import carmen_from_bag

        return carmen_from_bag(args.bag)
    if args.log is None:
        raise ValidationError("give a CARMEN log or --bag")
    return read_carmen(args.log)


def run(args: argparse.Namespace, log=None) -> dict:
    """The protocol of the module docstring on ``log`` (default: :func:`load_log`)."""
    t_wall = time.perf_counter()
    log = load_log(args) if log is None else log
    scans = log.scans[: args.max_scans] if args.max_scans else log.scans
    if len(scans) < 6:
        raise ValidationError(f"need at least 6 scans, got {len(scans)}")
    poses = np.array([s.laser_pose for s in scans])
    times = np.array([s.t for s in scans])
    angles = scans[0].angles
    ranges = np.array([s.ranges for s in scans])
    map_idx = np.arange(0, len(scans), 2)
    loc_idx = np.arange(1, len(scans), 2)

    t0 = time.perf_counter()
    grid = grid_from_scans(poses[map_idx], ranges[map_idx], angles, resolution=args.resolution,
                                    max_range=args.map_range)
    t_map = time.perf_counter() - t0

    rng = np.random.default_rng(args.seed)
    odom = noisy_odometry(poses, rng, args.odom_noise)
    # the odometry frame starts at the true first pose: its drift is its error
    odo_pos, odo_head = pose_errors(odom[loc_idx], poses[loc_idx])

    laser = LaserConfig(angles, max_range=args.laser_range)
    k_s, k_r, k_rd = (args.odom_noise * a for a in ODOM_NOISE)
    # MCL's (rot1, trans, rot2) model, about twice the simulated noise: a1 rot^2 -> rotation
    # noise from rotation, a2 trans^2 -> from translation, a3 trans^2 -> translation scale
    a1, a2, a3, a4 = (2 * k_r) ** 2, (2 * k_rd) ** 2, (2 * k_s) ** 2, 0.01
    k0 = int(loc_idx[0])
    P0 = np.diag([0.1**2, 0.1**2, 0.05**2])

    # ---------------------------------------------------------------- MCL
    t0 = time.perf_counter()
    mcl = MonteCarloLocalization(
        grid, laser, sensor=LikelihoodFieldModel(), motion=OdometryMotionModel(a1, a2, a3, a4),
        min_particles=500, max_particles=5000, max_beams=60, rng=args.seed,
    )
    mcl.predict(times[k0], odom[k0])
    mcl.initialize_gaussian(poses[k0], P0, t=times[k0])
    mcl_est, mcl_cov = [], []
    for k in range(k0, len(scans)):
        mcl.predict(times[k], odom[k])
        if k % 2 == 1:
            mcl.update(times[k], ranges[k])
            e = mcl.estimate()
            mcl_est.append(e.mean)
            mcl_cov.append(e.cov)
    mcl_est = np.array(mcl_est)
    t_mcl = time.perf_counter() - t0

    # ---------------------------------------------------------------- ICP + EKF
    t0 = time.perf_counter()
    matcher = ScanMatcher.from_grid(grid, "point_to_line", max_correspondence_distance=0.5, trim_fraction=0.1,
                                    tolerance=1e-4, max_iterations=40)
    ekf = OdometryEKF(poses[k0], P0, k_d=1.5 * k_s, k_theta=1.5 * k_r, k_dtheta=1.5 * k_rd,
                      s_d=0.01, s_theta=0.005, gate=16.3)
    sm_est, sm_cov = [], []
    icp_fail = 0
    for k in range(k0, len(scans)):
        if k > k0:
            ekf_predict(ekf, odom[k - 1], odom[k], times[k])
        if k % 2 == 0:
            continue
        pts = scan_to_points(ranges[k], angles, args.laser_range)
        try:
            res = matcher.match(pts, ekf.x)
        except ValidationError:
            icp_fail += 1
        else:
            if res.converged or res.iterations >= 40:
                C = 4.0 * res.covariance + np.diag([0.05**2, 0.05**2, 0.02**2])
                ekf.update(times[k], res.pose, C)
            else:
                icp_fail += 1
        sm_est.append(ekf.x)
        sm_cov.append(ekf.P.copy())
    sm_est = np.array(sm_est)
    t_sm = time.perf_counter() - t0

    truth = poses[loc_idx]
    out = {
        "log": str(args.log),
        "scans": len(scans),
        "map_scans": int(map_idx.size),
        "localized_scans": int(loc_idx.size),
        "map": {"resolution": grid.resolution, "width": grid.width, "height": grid.height,
                "occupied_cells": int(grid.occupied.sum()), "seconds": t_map},
        "odometry": {**summary(odo_pos, odo_head), "noise": [k_s, k_r, k_rd]},
        "mcl": {**summary(*pose_errors(mcl_est, truth)), "seconds": t_mcl, "ms_per_scan": 1e3 * t_mcl / loc_idx.size},
        "scan_matching": {**summary(*pose_errors(sm_est, truth)), "seconds": t_sm,
                          "ms_per_scan": 1e3 * t_sm / loc_idx.size, "icp_failures": icp_fail,
                          "gated_out": ekf.rejected},
        "seed": args.seed,
        # per localized scan (lists, for --json): time (s), truth and each localizer's pose
        # (x m, y m, theta rad) with its 3x3 covariance
        "series": {"t": times[loc_idx].tolist(), "truth": truth.tolist(), "odometry": odom[loc_idx].tolist(),
                   "mcl": {"mean": np.asarray(mcl_est).tolist(), "cov": np.asarray(mcl_cov).tolist()},
                   "scan_matching": {"mean": sm_est.tolist(), "cov": np.asarray(sm_cov).tolist()}},
    }
    out["runtime_s"] = time.perf_counter() - t_wall
    out["_plot"] = {"grid": grid, "map_poses": poses[map_idx]}   # for the figures; not written to JSON
    return out


def figures(res: dict, grid, out: Path) -> list[Path]:
    """``out/carmen_topdown.png`` (the map built from the even scans, the true path of the
    localized scans, each localizer's estimate with 3-sigma ellipses, the drifting
    odometry) and ``out/carmen_errors.png`` (X and Y errors of both localizers with their
    own ±3σ)."""
    from dfusion.viz.plots import plot_track_errors
    from dfusion.viz.topdown import Scene, Track, draw_scene

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
                       f"odometry {res['odometry']['rmse']:.2f} m")
    out.mkdir(parents=True, exist_ok=True)
    a = draw_scene(scene, out / "carmen_topdown.png")
    b = plot_track_errors(t, truth, [mcl, sm], out / "carmen_errors.png",
                          title=f"CARMEN {Path(res['log']).name}: position error of each localizer with its own ±3σ")
    return [a, b]


def print_table(res: dict) -> None:
    m = res["map"]
    print(f"CARMEN {res['log']}: {res['scans']} scans, map from {res['map_scans']} "
          f"({m['width']}x{m['height']} cells of {m['resolution']} m, built in {m['seconds']:.1f} s), "
          f"{res['localized_scans']} scans localized")
    print(f"{'localizer':<26}{'RMSE m':>9}{'median':>9}{'95 %':>8}{'max':>8}{'heading RMSE rad':>18}{'ms/scan':>9}")
    for key, label in (("odometry", "odometry (dead reckoning)"), ("mcl", "MCL (likelihood field)"),
                       ("scan_matching", "ICP + odometry EKF")):
        v = res[key]
        ms = f"{v['ms_per_scan']:.1f}" if "ms_per_scan" in v else "-"
        print(f"{label:<26}{v['rmse']:>9.3f}{v['median']:>9.3f}{v['p95']:>8.3f}{v['max']:>8.3f}"
              f"{v['heading_rmse']:>18.4f}{ms:>9}")
    sm = res["scan_matching"]
    print(f"ICP failures {sm['icp_failures']}, gated out {sm['gated_out']}; run time {res['runtime_s']:.1f} s")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, nargs="?", default=None, help="CARMEN log (plain or .gz) with corrected poses")
    ap.add_argument("--bag", type=Path, default=None, help="read scans, scan poses and odometry from this ROS bag")
    ap.add_argument("--json", type=Path, default=None, help="write the results and the per-scan series as JSON")
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR",
                    help="write the top-down figure and the error plot (PNG) into DIR")
    ap.add_argument("--max-scans", type=int, default=None, help="use only the first N scans")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resolution", type=float, default=0.05, help="map cell size (m)")
    ap.add_argument("--map-range", type=float, default=30.0, help="readings below this are hits when mapping (m)")
    ap.add_argument("--laser-range", type=float, default=30.0, help="readings at or above this are ignored (m)")
    ap.add_argument("--odom-noise", type=float, default=1.0, help="scale of the simulated odometry noise")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        res = run(args)
    except (DfusionError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print_table(res)
    plot = res.pop("_plot")
    if args.plot:
        print("wrote " + ", ".join(str(p) for p in figures(res, plot["grid"], args.plot)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
