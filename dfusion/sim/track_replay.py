r"""Recorded detections tracked: ``dfusion replay BAG --detections TOPIC=SENSOR ...``.

The scans of the bag's detection topics (:func:`dfusion.sim.bag_scans.scans_from_bag`, one
per message, world-frame positions) go through one centralized
:class:`~dfusion.tracking.MultiTargetTracker` in header-stamp order (scans of several sensors
at one stamp one after another): constant-velocity tracks (acceleration noise ``q``), JPDA
(exact, EHM) or GNN association, M-of-N two-point initiation (with a velocity prior) and
deletion when a track has no hit for ``max_age`` seconds (and, optionally, after
``max_misses`` consecutive misses in view). :class:`TrackerSettings` holds these; the defaults
are the settings of ``benchmarks/multi_target.py`` (people at 10 Hz).

**Output.** After every scan, every confirmed track's identity, mean ``(x, y, vx, vy)`` and
4x4 covariance (:meth:`TrackReplay.to_json`).

**Truth** (optional, ``truth_topics``): each topic of a pose type (``nav_msgs/Odometry``,
``PoseStamped``, ``PoseWithCovarianceStamped``, ``PointStamped``) is one target, named by its
topic; a ``vision_msgs/Detection3DArray`` holds every target of one time, each named by its
``id`` (an empty ``id`` is refused). Truth positions are taken into the fixed frame like the
detections. A target is present at time ``t`` when two of its samples at most
``truth_max_gap`` seconds apart bracket ``t`` (its position is interpolated linearly between
them) or one is stamped at ``t``. The metrics are evaluated after the last scan of every
stamp inside the span of the truth: GOSPA (``c``, ``p = 1``, ``alpha = 2``;
:func:`dfusion.metrics.gospa`) and its parts, CLEAR MOT and IDF1 (match within ``match``
metres; :func:`dfusion.metrics.identity_metrics`).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from dfusion.bags.convert import PoseReading, PositionFix, convert, detection3d_array
from dfusion.bags.detections import DetectionTopic
from dfusion.bags.reader import Bag, read_bag
from dfusion.bags.tf import TF_STATIC, StaticTransforms
from dfusion.errors import ValidationError
from dfusion.geometry import transform_points
from dfusion.metrics import TrackingFrame, gospa, identity_metrics
from dfusion.models.motion import ConstantVelocity
from dfusion.sim.bag_scans import ScanCounts, scans_from_bag
from dfusion.tracking.association import GNN, JPDA
from dfusion.tracking.deletion import AnyDeleter, MissDeleter, StaleDeleter
from dfusion.tracking.initiation import MofNInitiator
from dfusion.tracking.tracker import MultiTargetTracker

log = logging.getLogger(__name__)

__all__ = ["ASSOCIATIONS", "TOPIC_KEYS", "TrackerSettings", "TrackReplay", "build_tracker", "replay_tracks",
           "open_detection_bag",
           "truth_tracks", "parse_detection_topic"]

#: Values of ``association``.
ASSOCIATIONS = ("jpda", "gnn")

_TRUTH_ARRAY = "vision_msgs/msg/Detection3DArray"


@dataclass(frozen=True)
class TrackerSettings:
    """The tracker of a detection replay (module docstring)."""

    association: str = "jpda"
    q: float = 0.05
    velocity_std: float | None = 1.5
    confirm: tuple[int, int] = (3, 5)
    max_age: float = 0.45
    max_misses: int | None = None
    gate: float = 0.99
    max_speed: float = 3.0
    max_seed_age: float = 0.35

    def __post_init__(self) -> None:
        if self.association not in ASSOCIATIONS:
            raise ValidationError(f"association must be one of {ASSOCIATIONS}, got {self.association!r}")

    def as_dict(self) -> dict:
        return {"association": self.association, "q": self.q, "velocity_std": self.velocity_std,
                "confirm": list(self.confirm), "max_age": self.max_age, "max_misses": self.max_misses,
                "gate": self.gate, "max_speed": self.max_speed, "max_seed_age": self.max_seed_age}


def build_tracker(s: TrackerSettings, origin: str = "replay") -> MultiTargetTracker:
    """The :class:`~dfusion.tracking.MultiTargetTracker` of ``s``."""
    motion = ConstantVelocity(2, s.q)
    deleters = [StaleDeleter(s.max_age)] + ([MissDeleter(s.max_misses)] if s.max_misses else [])
    m, n = s.confirm
    return MultiTargetTracker(motion, JPDA() if s.association == "jpda" else GNN(),
                              MofNInitiator(motion, m=m, n=n, gate=s.gate, velocity_std=s.velocity_std,
                                            max_speed=s.max_speed, max_seed_age=s.max_seed_age),
                              AnyDeleter(*deleters), origin=origin)


# --- truth ----------------------------------------------------------------------------------------------------


def truth_tracks(bag: Bag, topics: Sequence[str], frame: str, origin_ns: int,
                 tf_topic: str = TF_STATIC) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Target name -> ``(times (n,), positions (n, 2))`` of the truth topics, in ``frame`` (module docstring)."""
    tf = StaticTransforms.from_bag(bag, tf_topic)
    samples: dict[str, list[tuple[float, float, float]]] = {}

    def add(name: str, t: float, pts: np.ndarray, src: str, topic: str) -> None:
        T = tf.require(src.lstrip("/") or frame, frame, f"truth topic {topic}")
        p = transform_points(np.asarray(pts, dtype=float).reshape(-1, 2), T)[0]
        if np.all(np.isfinite(p)):
            samples.setdefault(name, []).append((t, float(p[0]), float(p[1])))

    for topic in topics:
        for m in bag.on(topic):
            t = bag.seconds(m.stamp_ns, origin_ns)
            if m.msgtype == _TRUTH_ARRAY:
                d = detection3d_array(m.msg, t)
                for i, ident in enumerate(d.ids):
                    if not ident:
                        raise ValidationError(f"truth topic {topic}: a detection without an id (each target of a "
                                              f"{_TRUTH_ARRAY} truth is named by its id)")
                    add(ident, t, d.points[i], d.frame, topic)
                continue
            try:
                r = convert(m.msgtype, m.msg, t)
            except ValidationError:
                r = None
            if isinstance(r, PoseReading):
                add(topic, t, r.pose[:2], r.frame, topic)
            elif isinstance(r, PositionFix):
                add(topic, t, r.z[:2], r.frame, topic)
            else:
                raise ValidationError(f"truth topic {topic}: a {m.msgtype} gives no target position (truth types: "
                                      f"Odometry, PoseStamped, PoseWithCovarianceStamped, PointStamped: one target "
                                      f"per topic; {_TRUTH_ARRAY} with ids: every target)")
    out = {}
    for name, rows in samples.items():
        a = np.array(sorted(rows))
        out[name] = (a[:, 0], a[:, 1:3])
    return out


def _truth_at(truth: dict[str, tuple[np.ndarray, np.ndarray]], t: float,
              max_gap: float) -> tuple[list[str], np.ndarray]:
    ids, pts = [], []
    for name, (ts, xy) in truth.items():
        k = int(np.searchsorted(ts, t - 1e-9))
        if k < ts.size and abs(ts[k] - t) <= 1e-9:
            ids.append(name)
            pts.append(xy[k])
        elif 0 < k < ts.size and ts[k] - ts[k - 1] <= max_gap + 1e-9:
            w = (t - ts[k - 1]) / (ts[k] - ts[k - 1])
            ids.append(name)
            pts.append((1.0 - w) * xy[k - 1] + w * xy[k])
    return ids, np.array(pts, dtype=float).reshape(-1, 2)


# --- the run --------------------------------------------------------------------------------------------------


@dataclass
class TrackReplay:
    """A detection replay's result: per scan the tracks, the counts, and the metrics when a truth was given."""

    bag: str
    frame: str
    origin_ns: int
    sensors: list[str]
    settings: TrackerSettings
    scans: list[dict] = field(default_factory=list)
    counts: ScanCounts = field(default_factory=ScanCounts)
    tracks_started: int = 0
    tracks_deleted: int = 0
    metrics: dict | None = None
    gospa_series: list[dict] = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps({"kind": "detection_replay", "bag": self.bag, "frame": self.frame,
                           "origin_ns": self.origin_ns, "sensors": self.sensors, "settings": self.settings.as_dict(),
                           "counts": self.counts.as_dict(), "tracks_started": self.tracks_started,
                           "tracks_deleted": self.tracks_deleted, "metrics": self.metrics,
                           "gospa": self.gospa_series, "scans": self.scans})

    def table(self) -> str:
        c = self.counts
        rej = ", ".join(f"{k} {v}" for k, v in sorted(c.rejected.items())) or "none"
        lines = [f"detections replay of {self.bag}: {len(self.sensors)} sensor(s) {', '.join(self.sensors)}, "
                 f"{self.settings.association.upper()}, fixed frame {self.frame}",
                 f"  scans {c.scans} (empty {c.empty_scans}, covariance widened {c.scans_covariance_widened}), "
                 f"detections {c.detections} (covariance from the message {c.covariance_stated}), "
                 f"messages skipped {c.skipped_messages}, outside the run {c.outside_run}",
                 f"  detections refused: {rej}",
                 f"  tracks confirmed {self.tracks_started}, deleted {self.tracks_deleted}, at the end "
                 f"{len(self.scans[-1]['tracks']) if self.scans else 0}"]
        m = self.metrics
        if m is None:
            lines.append("  (no --truth topic: GOSPA and IDF1 are unknown)")
        elif not m["frames"]:
            lines.append("  the truth covers no scan time: GOSPA and IDF1 are unknown")
        else:
            lines.append(f"  over {m['frames']} frames: mean GOSPA {m['gospa']:.3f} m (c = {m['gospa_c']:g} m; "
                         f"localization {m['localization']:.3f}, missed {m['missed']:.3f}, false {m['false']:.3f}), "
                         f"IDF1 {m['idf1']:.3f}, MOTA {m['mota']:.3f}, identity switches {m['switches']}")
        return "\n".join(lines)


def open_detection_bag(bag: str | Path | Bag, topics: Sequence[DetectionTopic], truth_topics: Sequence[str] = (),
                       origin_ns: int | None = None, tf_topic: str = TF_STATIC, msgdefs=None) -> tuple[Bag, int]:
    """The bag of a detection replay (read with the detection and truth topics and ``tf_topic``
    unless already read) and the time origin: ``origin_ns``, or the earliest stamp of those topics."""
    if not isinstance(bag, Bag):
        bag = read_bag(bag, [o.topic for o in topics] + list(truth_topics), optional=[tf_topic], msgdefs=msgdefs)
    if origin_ns is None:
        names = [o.topic for o in topics] + list(truth_topics)
        origin_ns = min((m.stamp_ns for m in bag.messages if m.topic in names), default=bag.origin_ns)
    return bag, int(origin_ns)


def replay_tracks(bag: str | Path | Bag, topics: Sequence[DetectionTopic], *, settings: TrackerSettings | None = None,
                  frame: str = "map", truth_topics: Sequence[str] = (), origin_ns: int | None = None,
                  duration: float | None = None, tf_topic: str = TF_STATIC, gospa_c: float = 2.0,
                  match: float = 1.0, truth_max_gap: float = 1.0, msgdefs=None) -> TrackReplay:
    """Track the detections of ``topics`` (module docstring)."""
    settings = settings or TrackerSettings()
    if not topics:
        raise ValidationError("a detection replay needs at least one detection topic")
    bag, origin_ns = open_detection_bag(bag, topics, truth_topics, origin_ns, tf_topic, msgdefs)
    out = TrackReplay(str(bag.path), frame, int(origin_ns), sorted({o.sensor for o in topics}), settings)
    truth = truth_tracks(bag, truth_topics, frame, origin_ns, tf_topic) if truth_topics else None
    span = None
    if truth:
        span = (min(ts[0] for ts, _ in truth.values()), max(ts[-1] for ts, _ in truth.values()))
    tracker = build_tracker(settings)
    frames: list[tuple[float, list[str], np.ndarray]] = []
    for sensor, scan in scans_from_bag(bag, topics, frame=frame, origin_ns=origin_ns, duration=duration,
                                       tf_topic=tf_topic, counts=out.counts):
        tracker.step(scan)
        est = tracker.estimates()
        out.scans.append({"t": round(scan.time, 9), "sensor": sensor, "detections": len(scan.detections),
                          "tracks": [{"id": str(i), "mean": mean.tolist(), "cov": cov.tolist()}
                                     for i, mean, cov in est]})
        row = (scan.time, [str(i) for i, _, _ in est], np.array([m[:2] for _, m, _ in est]).reshape(-1, 2))
        if frames and abs(frames[-1][0] - scan.time) <= 1e-9:
            frames[-1] = row                     # the last scan of a stamp stands for the frame
        else:
            frames.append(row)
    out.tracks_started = tracker.issuer.issued
    out.tracks_deleted = tracker.deleted
    if truth is not None:
        out.metrics, out.gospa_series = _metrics(frames, truth, span, gospa_c, match, truth_max_gap)
    return out


def _metrics(frames, truth, span, c: float, match: float, max_gap: float) -> tuple[dict, list[dict]]:
    series, id_frames = [], []
    parts = np.zeros(4)
    for t, ids, pts in frames:
        if span is None or not span[0] - 1e-9 <= t <= span[1] + 1e-9:
            continue
        gids, X = _truth_at(truth, t, max_gap)
        g = gospa(X, pts, c=c, p=1.0)
        parts += (g.distance, g.localization, g.missed, g.false)
        series.append({"t": round(t, 9), "gospa": g.distance, "truths": len(gids), "tracks": len(ids)})
        id_frames.append(TrackingFrame(gids, X, ids, pts))
    n = len(series)
    if not n:
        return {"frames": 0}, series
    idm = identity_metrics(id_frames, threshold=match)
    mean = parts / n
    return ({"frames": n, "gospa_c": c, "gospa": float(mean[0]), "localization": float(mean[1]),
             "missed": float(mean[2]), "false": float(mean[3]), "idf1": idm.idf1, "mota": idm.mota,
             "motp": idm.motp if math.isfinite(idm.motp) else None, "switches": idm.switches,
             "truth_targets": len(truth), "match_m": match}, series)


#: Per-topic keys of ``--detections TOPIC=SENSOR[:FILE.py:FUNC][,KEY=VALUE...]``.
TOPIC_KEYS = ("std", "pd", "clutter", "homography", "ground_frame", "view")


def parse_detection_topic(text: str, *, std: float = 0.3, detection_probability: float = 0.9,
                          clutter_density: float = 0.0025) -> DetectionTopic:
    """``TOPIC=SENSOR[:FILE.py:FUNCTION][,KEY=VALUE...]`` -> :class:`DetectionTopic`; keys
    :data:`TOPIC_KEYS` (``homography`` a file, :func:`~dfusion.bags.detections.read_homography`;
    ``view`` ``X0:X1:Y0:Y1``);
    the keyword arguments are the values of the keys not given."""
    from dfusion.bags.detections import read_homography
    from dfusion.sim.replay import split_converter

    topic, sep, rest = text.partition("=")
    head, *pairs = rest.split(",")
    if not sep or not topic or not head:
        raise ValidationError(f"--detections wants TOPIC=SENSOR[:FILE.py:FUNCTION][,KEY=VALUE...], got {text!r}")
    sensor, fn = split_converter(head, f"--detections {text!r}")
    values: dict[str, str] = {}
    for pair in pairs:
        key, sep3, value = pair.partition("=")
        if not sep3 or key not in TOPIC_KEYS:
            raise ValidationError(f"--detections {text!r}: {pair!r} is no KEY=VALUE with a key of {TOPIC_KEYS}")
        values[key] = value

    def number(key: str, default: float) -> float:
        if key not in values:
            return default
        try:
            return float(values[key])
        except ValueError:
            raise ValidationError(f"--detections {text!r}: {key} must be a number, got {values[key]!r}") from None

    return DetectionTopic(topic, sensor, fn, std=number("std", std),
                          detection_probability=number("pd", detection_probability),
                          clutter_density=number("clutter", clutter_density),
                          homography=read_homography(values["homography"]) if "homography" in values else None,
                          ground_frame=values.get("ground_frame"), view=_view(values.get("view"), text))


def _view(value: str | None, text: str) -> tuple[float, ...] | None:
    if value is None:
        return None
    try:
        return tuple(float(v) for v in value.split(":"))
    except ValueError:
        raise ValidationError(f"--detections {text!r}: view is X0:X1:Y0:Y1 in metres, got {value!r}") from None
