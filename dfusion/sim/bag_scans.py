r"""Scans of recorded detections: a bag's detection topics as the multi-target tracker's input.

:func:`scans_from_bag` reads the detection topics of a bag (each a
:class:`~dfusion.bags.detections.DetectionTopic`) and yields, in header-stamp order, one
``(sensor name, Scan)`` per message: the message's detections as world-frame positions
(:func:`dfusion.bags.detections.world_detections`: homography for pixels, ``/tf_static``
into the fixed frame, the message's covariance or the topic's ``std``), the topic's
detection probability and clutter density, and, when the topic has a ``view`` rectangle,
the probability that a track is in it (:meth:`dfusion.sim.plaza.CameraView.probability_inside`:
the track's ``P_D`` in the scan is the topic's times it, and a track that is probably out of
view is not missed). The centralized tracker of ``dfusion replay
--detections`` (:mod:`dfusion.sim.track_replay`) consumes them, and so can any other
consumer of :class:`~dfusion.tracking.Scan` (a decentralized network of tracking nodes, one
per sensor).

**One covariance per scan.** A :class:`~dfusion.tracking.Scan` has one measurement model, so
one noise covariance ``R`` for all its detections. When a message's detections state equal
covariances (or none), ``R`` is that covariance. When they differ, ``R`` is the smallest
multiple of their mean ``M`` that covers every one (``R - R_j`` positive semidefinite for
each ``j``: never over-confident about any detection)::

    R = s M,   s = max_j lambda_max(L^-1 R_j L^-T),   M = L L^T

and the scan is counted in ``scans_covariance_widened``.

**Refusals.** A topic of a type that is not a detection array (and has no user function) is
refused before the first scan, in one line; so is a pixel topic without a homography and a
frame with no static transform to the fixed frame. A detection with a non-finite coordinate
(or a pixel above the horizon) is left out of its scan and counted; a message whose user
function returns ``None`` is skipped and counted. A message without detections is a scan
with none (every track in view is missed): counted in ``empty_scans``, not refused.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from dfusion.bags.convert import DETECTION_TYPES, Detections, convert
from dfusion.bags.detections import DetectionTopic, require_homography, world_detections
from dfusion.bags.reader import Bag
from dfusion.bags.tf import TF_STATIC, StaticTransforms
from dfusion.errors import ValidationError
from dfusion.linalg import Array, cholesky, symmetrize
from dfusion.models.measurement import PositionFix
from dfusion.sim.plaza import CameraView
from dfusion.tracking.track import Scan

log = logging.getLogger(__name__)

__all__ = ["ScanCounts", "scans_from_bag", "scan_covariance", "check_detection_topics"]


@dataclass
class ScanCounts:
    """What :func:`scans_from_bag` read and refused (filled in as it goes)."""

    scans: int = 0
    detections: int = 0
    empty_scans: int = 0
    covariance_stated: int = 0
    scans_covariance_widened: int = 0
    skipped_messages: int = 0
    outside_run: int = 0
    rejected: Counter = field(default_factory=Counter)

    def as_dict(self) -> dict:
        return {"scans": self.scans, "detections": self.detections, "empty_scans": self.empty_scans,
                "covariance_stated": self.covariance_stated,
                "scans_covariance_widened": self.scans_covariance_widened,
                "skipped_messages": self.skipped_messages, "outside_run": self.outside_run,
                "rejected_detections": dict(sorted(self.rejected.items()))}


def scan_covariance(covs: Array, fallback: Array) -> tuple[Array, bool]:
    """The one covariance of a scan whose detections state ``covs`` (k, 2, 2) (module docstring);
    ``fallback`` for a scan with no detection. Returns ``(R, widened)``."""
    covs = np.asarray(covs, dtype=float)
    if len(covs) == 0:
        return np.asarray(fallback, dtype=float), False
    if np.allclose(covs, covs[0], rtol=1e-12, atol=0.0):
        return symmetrize(covs[0]), False
    M = symmetrize(covs.mean(axis=0))
    L = cholesky(M, "mean detection covariance")
    s = max(float(np.linalg.eigvalsh(symmetrize(np.linalg.solve(L, np.linalg.solve(L, C).T)))[-1]) for C in covs)
    return symmetrize(s * M), True


def check_detection_topics(bag: Bag, topics: Sequence[DetectionTopic]) -> None:
    """Refuse, in one line, a topic the bag lacks, a topic given twice, or one whose type is no detection
    array and has no user function, or gives pixels without a homography."""
    seen = set()
    for opts in topics:
        if opts.topic in seen:
            raise ValidationError(f"detection topic {opts.topic} is given twice")
        seen.add(opts.topic)
        msgtype = bag.topics.get(opts.topic)
        if msgtype is None:
            raise ValidationError(f"{bag.path}: no topic {opts.topic!r} (topics: {sorted(bag.topics)})")
        if opts.convert is None and msgtype not in DETECTION_TYPES:
            raise ValidationError(f"topic {opts.topic}: a {msgtype} is no detection array (detection types: "
                                  f"{', '.join(sorted(DETECTION_TYPES))}); map it with a function "
                                  f"{opts.topic}={opts.sensor}:FILE.py:FUNCTION returning (k, 2) positions")
        if opts.convert is None and msgtype == "vision_msgs/msg/Detection2DArray" and opts.homography is None:
            require_homography(opts, msgtype)


def _reading(opts: DetectionTopic, msgtype: str, msg, t: float, frame: str) -> Detections | None:
    if opts.convert is None:
        return convert(msgtype, msg, t)
    out = opts.convert(msg, t)
    if out is None or isinstance(out, Detections):
        return out
    pts = np.asarray(out, dtype=float)
    if pts.size and (pts.ndim != 2 or pts.shape[1] != 2):
        raise ValidationError(f"topic {opts.topic}: its function returned shape {pts.shape}; it returns "
                              f"(k, 2) positions in the fixed frame, a dfusion.bags.Detections or None")
    return Detections(t, pts.reshape(-1, 2), None, frame)


def scans_from_bag(bag: Bag, topics: Sequence[DetectionTopic], *, frame: str = "map", origin_ns: int | None = None,
                   duration: float | None = None, tf_topic: str = TF_STATIC,
                   counts: ScanCounts | None = None) -> Iterator[tuple[str, Scan]]:
    """``(sensor name, Scan)`` of every message of ``topics``, in header-stamp order (module docstring).

    ``bag`` must hold ``topics`` (and ``tf_topic`` when frames differ). Scan times are seconds
    after ``origin_ns`` (default: the earliest stamp among the topics); messages at negative times
    or after ``duration`` are left out (counted in ``outside_run``). ``counts`` is filled in as
    the scans are yielded.
    """
    check_detection_topics(bag, topics)
    counts = counts if counts is not None else ScanCounts()
    by_topic = {o.topic: o for o in topics}
    if origin_ns is None:
        origin_ns = min((m.stamp_ns for m in bag.messages if m.topic in by_topic), default=bag.origin_ns)
    tf = StaticTransforms.from_bag(bag, tf_topic)
    views = {o.topic: CameraView(o.sensor, *o.view).probability_inside for o in topics if o.view is not None}
    for m in bag.messages:
        opts = by_topic.get(m.topic)
        if opts is None:
            continue
        t = bag.seconds(m.stamp_ns, origin_ns)
        if t < -1e-12 or (duration is not None and t > duration + 1e-9):
            counts.outside_run += 1
            continue
        reading = _reading(opts, m.msgtype, m.msg, t, frame)
        if reading is None:
            counts.skipped_messages += 1
            continue
        wd = world_detections(reading, opts, tf, frame, m.msgtype)
        counts.rejected.update(wd.rejected)
        fallback = np.eye(2) * opts.std**2
        R, widened = scan_covariance(wd.covs, fallback)
        counts.scans += 1
        counts.detections += len(wd.points)
        counts.empty_scans += int(len(wd.points) == 0)
        counts.covariance_stated += int(wd.stated.sum())
        counts.scans_covariance_widened += int(widened)
        yield opts.sensor, Scan(t, wd.points, PositionFix(np.zeros(2), R), opts.clutter_density,
                                opts.detection_probability, source=opts.sensor, view_probability=views.get(m.topic))
