r"""Bags in the shape of dfusion's dataset readers: every pipeline that runs on a dataset
runs on a robot's recording.

* :func:`mrclam_from_bag` -> :class:`~dfusion.datasets.MRCLAMDataset`: per robot,
  velocity odometry (``geometry_msgs/TwistStamped``, ``Twist`` or the twist of
  ``nav_msgs/Odometry``), sightings of landmarks and robots (a custom type, see
  :data:`SIGHTINGS_MSGDEF`, or any type through a user function) and, optionally, ground
  truth (``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``). The landmark map is
  not in a robot's recording: pass it (:func:`dfusion.datasets.read_landmarks`).
* :func:`carmen_from_bag` -> :class:`~dfusion.datasets.CarmenLog`: laser scans
  (``sensor_msgs/LaserScan``), the odometry stream (``nav_msgs/Odometry``) and the pose of
  each scan (``geometry_msgs/PoseStamped`` with the scan's stamp; CARMEN's corrected
  ``FLASER`` pose; any pose type, matched by nearest stamp within a tolerance), or,
  without that topic, the odometry pose at the scan's time; a laser mounted off the
  robot's centre is folded in from ``/tf_static``.

Times are header stamps (:mod:`dfusion.bags.reader`), so the record order of the bag
does not change the result.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from dfusion.bags.convert import PoseReading, Velocity, convert, laser_scan, read_pose
from dfusion.bags.reader import Bag, read_bag
from dfusion.bags.tf import TF_STATIC, StaticTransforms
from dfusion.datasets.carmen import CarmenLog, LaserScan
from dfusion.datasets.mrclam import ROBOTS, MRCLAMDataset, RobotLog
from dfusion.errors import ValidationError
from dfusion.geometry import se2_compose, wrap_angle

log = logging.getLogger(__name__)

__all__ = ["SIGHTINGS_MSGDEF", "SIGHTINGS_TYPE", "sightings", "mrclam_from_bag", "carmen_from_bag",
           "MRCLAM_TOPICS", "POSE_TOLERANCE"]

#: Seconds a scan's pose may be stamped away from the scan (:func:`carmen_from_bag`): a
#: pose stamped further away is refused, not replaced.
POSE_TOLERANCE = 0.01

#: The message type of MRCLAM's sightings: everything one camera frame saw. MRCLAM has no
#: standard ROS message (a range and a bearing to a barcode); this definition travels in
#: the bag (ROS 2 MCAP and sqlite3 bags and ROS 1 bags all store it).
SIGHTINGS_TYPE = "mrclam_msgs/msg/Sightings"
SIGHTINGS_MSGDEF = """std_msgs/Header header
int32[] subject
float64[] range
float64[] bearing
"""

#: Default topic names of robot ``{n}``.
MRCLAM_TOPICS = {"odometry": "/robot{n}/odom", "sightings": "/robot{n}/sightings",
                 "ground_truth": "/robot{n}/ground_truth"}


def sightings(msg: Any, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:data:`SIGHTINGS_TYPE` -> ``(subject, range, bearing)`` arrays (the default
    sightings converter; a bag with another type passes its own function)."""
    return (np.asarray(msg.subject, dtype=int).ravel(), np.asarray(msg.range, dtype=float).ravel(),
            np.asarray(msg.bearing, dtype=float).ravel())


def _velocity(r: Any) -> tuple[float, float]:
    if isinstance(r, Velocity):
        return r.v, r.w
    if isinstance(r, PoseReading) and r.twist is not None:
        return float(r.twist[0]), float(r.twist[1])
    raise ValidationError(f"odometry messages must give a velocity, got {type(r).__name__}")


def mrclam_from_bag(
    bag: str | Path | Bag,
    landmarks: Mapping[int, Any],
    robots: tuple[int, ...] = ROBOTS,
    *,
    topics: Mapping[str, str] | None = None,
    sightings_converter: Callable[[Any, float], tuple] = sightings,
    duration: float | None = None,
    msgdefs: Mapping[str, str | Path] | None = None,
) -> MRCLAMDataset:
    """An MRCLAM dataset from a bag (see the module docstring).

    Parameters
    ----------
    bag : path or :class:`Bag`
    landmarks : landmark subject -> ``(x, y)`` (:func:`dfusion.datasets.read_landmarks`)
    robots : robot numbers whose topics to read
    topics : ``{"odometry", "sightings", "ground_truth"}`` -> topic pattern with ``{n}``
        (default :data:`MRCLAM_TOPICS`); a missing ground-truth topic leaves
        ``gt_t`` empty
    sightings_converter : ``f(msg, t) -> (subjects, ranges, bearings)``
    duration : keep messages up to this many seconds after the first stamp
    msgdefs : message definitions for a bag that stores none (:func:`~dfusion.bags.read_bag`)

    Only these topics are read; a robot without a sightings topic saw nothing (logged;
    none for every robot is refused). Ground truth is any of
    :data:`~dfusion.bags.convert.POSE_TYPES`.

    Times are relative to the earliest stamp read (``t0``, in seconds, as the reader's).
    """
    pat = {**MRCLAM_TOPICS, **(topics or {})}
    if not isinstance(bag, Bag):
        bag = read_bag(bag, [pat["odometry"].format(n=n) for n in robots],
                       optional=[pat[k].format(n=n) for n in robots for k in ("sightings", "ground_truth")],
                       msgdefs=msgdefs)
    no_sightings = [n for n in robots if pat["sightings"].format(n=n) not in bag.topics]
    if len(no_sightings) == len(robots):
        raise ValidationError(f"{bag.path}: no sightings topic {pat['sightings']!r} of any robot "
                              f"(topics: {sorted(bag.topics)})")
    if no_sightings:
        log.warning("%s: robots %s have no %s topic: no sightings", bag.path, no_sightings, pat["sightings"])
    t0_ns = min((m.stamp_ns for m in bag.messages
                 if any(m.topic == pat[k].format(n=n) for k in pat for n in robots)), default=None)
    if t0_ns is None:
        raise ValidationError(f"{bag.path}: no message on the MRCLAM topics of robots {list(robots)}")
    ds = MRCLAMDataset(bag.path, t0_ns * 1e-9, {}, {int(k): np.asarray(v, float) for k, v in landmarks.items()})
    keep = (lambda t: True) if duration is None else (lambda t: t <= duration)
    for n in robots:
        odo_topic, sig_topic, gt_topic = (pat[k].format(n=n) for k in ("odometry", "sightings", "ground_truth"))
        od_t, od = [], []
        for m in bag.on(odo_topic):
            t = bag.seconds(m.stamp_ns, t0_ns)
            if keep(t):
                od_t.append(t)
                od.append(_velocity(convert(m.msgtype, m.msg, t)))
        me_t, subj, rng, brg = [], [], [], []
        for m in (bag.on(sig_topic) if sig_topic in bag.topics else []):
            t = bag.seconds(m.stamp_ns, t0_ns)
            if not keep(t):
                continue
            s, r, b = sightings_converter(m.msg, t)
            me_t += [t] * len(s)
            subj += list(s)
            rng += list(r)
            brg += list(b)
        gt_t, gt = [], []
        if gt_topic in bag.topics:
            for m in bag.on(gt_topic):
                t = bag.seconds(m.stamp_ns, t0_ns)
                if keep(t):
                    gt_t.append(t)
                    gt.append(read_pose(m.msgtype, m.msg, t, gt_topic).pose)
        gt_a = np.array(gt, dtype=float).reshape(-1, 3)
        gt_a[:, 2] = wrap_angle(gt_a[:, 2])
        ds.robots[n] = RobotLog(n, np.array(gt_t), gt_a, np.array(od_t), np.array(od, dtype=float).reshape(-1, 2),
                                np.array(me_t), np.array(subj, dtype=int), np.array(rng), np.array(brg))
    return ds


def carmen_from_bag(
    bag: str | Path | Bag,
    *,
    scan_topic: str = "/scan",
    odom_topic: str | None = "/odom",
    scan_pose_topic: str | None = "/scan_pose",
    origin_ns: int = 0,
    pose_tolerance: float = POSE_TOLERANCE,
    tf_topic: str = TF_STATIC,
    base_frame: str | None = None,
    msgdefs: Mapping[str, str | Path] | None = None,
) -> CarmenLog:
    """A CARMEN log from a bag (see the module docstring).

    ``origin_ns`` is subtracted from every stamp (0: times are the stamps in seconds, as
    a CARMEN log's; pass ``bag.origin_ns`` for epoch stamps). Beam angles are
    ``angle_min + i * angle_increment`` and ranges the float32 values of the message
    (:func:`dfusion.bags.convert.laser_scan`); a reading at or above ``range_max`` is a
    "no return" (``valid = False``), as in the CARMEN reader.

    **Poses.** Each scan takes the ``scan_pose_topic`` pose (any of
    :data:`~dfusion.bags.convert.POSE_TYPES`) nearest to its stamp; none within
    ``pose_tolerance`` seconds is refused in one line. ``scan_pose_topic=None``: the
    odometry pose at the scan's time instead (logged: it drifts, so it is no truth).
    **Mount.** When ``tf_topic`` has a static transform from the scan's ``frame_id`` to
    ``base_frame`` (default: the odometry's ``child_frame_id``, else ``base_link``), the
    scan's pose is the robot's pose composed with it (:mod:`dfusion.bags.tf`).
    """
    if not isinstance(bag, Bag):
        need = [scan_topic] + [t for t in (scan_pose_topic,) if t is not None]
        if scan_pose_topic is None and odom_topic is not None:
            need.append(odom_topic)
        try:
            bag = read_bag(bag, need, optional=[t for t in (odom_topic, tf_topic) if t], msgdefs=msgdefs)
        except ValidationError as exc:
            if scan_pose_topic is not None and f"no topic {scan_pose_topic!r}" in str(exc):
                raise ValidationError(f"{exc}; name the scans' pose topic (--pose-topic), or take odometry poses, "
                                      f"which are no ground truth (--pose-topic none)") from None
            raise
    out = CarmenLog()
    odom_t, odom, vel = [], [], []
    child = ""
    if odom_topic is not None and odom_topic in bag.topics:
        for m in bag.on(odom_topic):
            t = bag.seconds(m.stamp_ns, origin_ns)
            r = read_pose(m.msgtype, m.msg, t, odom_topic)
            odom_t.append(t)
            odom.append(r.pose)
            tw = r.twist if r.twist is not None else np.zeros(2)
            vel.append((float(tw[0]), float(tw[1]), 0.0))
            child = child or str(getattr(m.msg, "child_frame_id", "") or "")
    out.odom_t = np.array(odom_t, dtype=float)
    out.odom = np.array(odom, dtype=float).reshape(-1, 3)
    out.odom_vel = np.array(vel, dtype=float).reshape(-1, 3)
    pose_ns = np.zeros(0, dtype=np.int64)
    pose_xyt = np.zeros((0, 3))
    if scan_pose_topic is not None:
        msgs = bag.on(scan_pose_topic)
        if not msgs:
            raise ValidationError(f"{bag.path}: {scan_pose_topic} has no message")
        pose_ns = np.array([m.stamp_ns for m in msgs], dtype=np.int64)
        pose_xyt = np.array([read_pose(m.msgtype, m.msg, 0.0, scan_pose_topic).pose for m in msgs])
    else:
        log.warning("%s: no scan pose topic: the scans' poses are odometry poses, which drift (no ground truth)",
                    bag.path)
    tf = StaticTransforms.from_bag(bag, tf_topic)
    base = base_frame or child or "base_link"
    tol_ns = int(round(pose_tolerance * 1e9))
    unmounted: set[str] = set()
    for m in bag.on(scan_topic):
        t = bag.seconds(m.stamp_ns, origin_ns)
        s = laser_scan(m.msg, t)
        if pose_ns.size:
            k = _nearest(pose_ns, m.stamp_ns)
            off = abs(int(pose_ns[k]) - m.stamp_ns)
            if off > tol_ns:
                raise ValidationError(f"{bag.path}: the scan at {t:.6f} s has no {scan_pose_topic} pose within "
                                      f"{pose_tolerance * 1e3:g} ms (nearest {off * 1e-6:.3f} ms away; "
                                      f"set pose_tolerance / --pose-tolerance)")
            pose = pose_xyt[k]
        else:
            if not out.odom_t.size:
                raise ValidationError(f"{bag.path}: scan at {t:.6f} s has no pose: no scan pose topic and no odometry")
            k = max(int(np.searchsorted(out.odom_t, t, side="right")) - 1, 0)
            pose = out.odom[k]
        mount = tf.lookup(base, s.frame) if s.frame else None
        if mount is None:
            unmounted.add(s.frame)
        laser_pose = se2_compose(pose, mount) if mount is not None else pose.copy()
        out.scans.append(LaserScan(t, s.ranges, s.angles, laser_pose, pose.copy(), s.valid, None, 0))
    if unmounted:
        log.info("%s: no static transform from the scans' frame %s to %s: the pose is the laser's", bag.path,
                 sorted(unmounted), base)
    out.backward_steps = {"scans": 0, "odom": 0}
    log.info("%s: %d scans, %d odometry poses", bag.path, len(out.scans), out.odom_t.size)
    return out


def _nearest(sorted_ns: np.ndarray, ns: int) -> int:
    """Index of the value of ``sorted_ns`` nearest to ``ns``."""
    k = int(np.searchsorted(sorted_ns, ns))
    if k == 0:
        return 0
    if k == sorted_ns.size:
        return k - 1
    return k if int(sorted_ns[k]) - ns < ns - int(sorted_ns[k - 1]) else k - 1
