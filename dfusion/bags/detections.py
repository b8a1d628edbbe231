r"""A detection array of a bag topic as world-frame positions with covariances.

A topic of detections (``geometry_msgs/PoseArray``, ``vision_msgs/Detection3DArray``,
``vision_msgs/Detection2DArray``, or any type through a user function) is configured by a
:class:`DetectionTopic`; :func:`world_detections` turns one message's
:class:`~dfusion.bags.convert.Detections` into positions in the fixed frame:

1. **Pixels to the ground** (``Detection2DArray``): the topic's ``homography`` ``H`` (3x3)
   maps a pixel ``(u, v)`` to the ground plane, ``(X, Y, W)^T = H (u, v, 1)^T`` and
   ``p = (X / W, Y / W)`` in ``ground_frame`` (Hartley & Zisserman, *Multiple View Geometry*,
   2nd ed., 2004, sec. 2.3 and 8.1: a plane's image is a homography of it). ``H`` is the
   inverse of the ground-to-image homography ``K [r_1 r_2 t]`` (a calibrated camera's
   intrinsics ``K`` and the pose of the ground plane in the camera's frame); so scaled, a
   ground point in front of the camera has ``W > 0``, and a pixel with ``W <= 0`` looks at or
   above the horizon: it is refused (counted). A pixel array without a homography is refused
   in one line that says what is needed.
2. **Frames**: a position in frame ``s`` (the message's ``header.frame_id``; for pixels the
   topic's ``ground_frame``; empty: already the fixed frame) is expressed in the fixed frame
   ``f`` by the static transform ``T = (x, y, yaw)`` of ``s`` in ``f``
   (:mod:`dfusion.bags.tf`): ``p' = R(yaw) p + (x, y)``, a covariance ``C' = R C R^T``. A frame
   not connected to ``f`` by ``/tf_static`` is refused in one line naming the frames.
3. **Covariance**: the one the detection states (:func:`~dfusion.bags.convert.known_covariance`:
   ``Detection3D``'s hypothesis pose), else the topic's ``std^2 I``.
4. **Bad detections** (a non-finite coordinate) are left out and counted; the others of the
   message are kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dfusion.bags.convert import Detections
from dfusion.bags.tf import StaticTransforms, rotate_covariance
from dfusion.errors import ValidationError
from dfusion.geometry import transform_points

__all__ = ["DetectionTopic", "WorldDetections", "world_detections", "read_homography", "require_homography"]


@dataclass(frozen=True)
class DetectionTopic:
    """A bag topic of detections and how to read it.

    Attributes
    ----------
    topic : the bag topic.
    sensor : the name of the sensor (a scan's ``source``).
    convert : optional user function ``f(msg, t) -> Detections | (k, 2) positions in the fixed
        frame | None`` (``None``: skip the message, counted); default: the standard conversion
        of the message type (:data:`dfusion.bags.convert.DETECTION_TYPES`).
    std : noise standard deviation (m, per axis) of a detection that states no covariance.
    detection_probability : ``P_D`` of a target in the sensor's view.
    clutter_density : false detections per m^2 per message.
    homography : 3x3 pixels -> ground (module docstring); needed for pixel detections.
    ground_frame : frame of the homography's ground coordinates (default: the fixed frame).
    view : optional ``(x0, x1, y0, y1)``: the rectangle of the fixed frame the sensor sees (m);
        ``None``: every target is in view of every message.
    """

    topic: str
    sensor: str
    convert: Callable[[Any, float], Any] | None = None
    std: float = 0.3
    detection_probability: float = 0.9
    clutter_density: float = 0.0025
    homography: np.ndarray | None = None
    ground_frame: str | None = None
    view: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if not self.topic or not self.sensor:
            raise ValidationError(f"a detection topic needs a topic and a sensor name, "
                                  f"got {self.topic!r}={self.sensor!r}")
        if not (math.isfinite(self.std) and self.std > 0):
            raise ValidationError(f"topic {self.topic}: std must be positive and finite, got {self.std!r}")
        if not 0.0 < self.detection_probability <= 1.0:
            raise ValidationError(f"topic {self.topic}: detection probability must be in (0, 1], "
                                  f"got {self.detection_probability!r}")
        if not (math.isfinite(self.clutter_density) and self.clutter_density >= 0):
            raise ValidationError(f"topic {self.topic}: clutter density must be >= 0, got {self.clutter_density!r}")
        if self.view is not None:
            v = tuple(float(a) for a in self.view)
            if len(v) != 4 or not all(math.isfinite(a) for a in v) or not (v[1] > v[0] and v[3] > v[2]):
                raise ValidationError(f"topic {self.topic}: a view is x0, x1, y0, y1 with x1 > x0 and y1 > y0, "
                                      f"got {self.view!r}")
            object.__setattr__(self, "view", v)
        if self.homography is not None:
            H = np.asarray(self.homography, dtype=float)
            if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-300:
                raise ValidationError(f"topic {self.topic}: a homography is an invertible 3x3 matrix of finite "
                                      f"numbers, got shape {H.shape}")
            object.__setattr__(self, "homography", H)


@dataclass
class WorldDetections:
    """One message's detections in the fixed frame: ``points`` (k, 2), ``covs`` (k, 2, 2),
    ``stated`` (k,) whether each covariance came from the message, ``rejected`` reason -> count."""

    points: np.ndarray
    covs: np.ndarray
    stated: np.ndarray
    rejected: dict[str, int] = field(default_factory=dict)


def read_homography(path: str | Path) -> np.ndarray:
    """A 3x3 homography from a text file (9 numbers, row-major, separated by spaces, commas or
    newlines; ``#`` starts a comment) or a ``.npy`` file."""
    p = Path(path)
    if not p.is_file():
        raise ValidationError(f"homography file {path}: no such file")
    if p.suffix == ".npy":
        H = np.load(p, allow_pickle=False)
    else:
        text = "\n".join(line.split("#", 1)[0] for line in p.read_text().splitlines())
        try:
            H = np.array([float(v) for v in text.replace(",", " ").split()])
        except ValueError:
            raise ValidationError(f"homography file {path}: not 9 numbers") from None
    H = np.asarray(H, dtype=float)
    if H.size != 9:
        raise ValidationError(f"homography file {path}: a homography is 9 numbers (3x3, row-major), got {H.size}")
    return H.reshape(3, 3)


def require_homography(opts: DetectionTopic, msgtype: str) -> None:
    """Refuse, in one line that says what is needed, a topic of pixel detections without a homography."""
    if opts.homography is None:
        raise ValidationError(f"topic {opts.topic}: a {msgtype} gives pixel boxes, which need a camera model to be "
                              f"ground positions: give the topic a homography from pixels to the ground "
                              f"(--detections {opts.topic}={opts.sensor},homography=H.txt; docs/ros.md), or map it "
                              f"with a function TOPIC=SENSOR:FILE.py:FUNCTION")


def _to_ground(opts: DetectionTopic, msgtype: str, pix: np.ndarray, rejected: dict[str, int]) -> np.ndarray:
    require_homography(opts, msgtype)
    hom = np.c_[pix, np.ones(len(pix))] @ opts.homography.T
    w = hom[:, 2]
    ahead = w > 1e-12 * np.abs(hom[:, :2]).max(axis=1, initial=1.0)
    out = np.full((len(pix), 2), np.nan)
    out[ahead] = hom[ahead, :2] / w[ahead, None]
    off = int(np.sum(~ahead & np.all(np.isfinite(pix), axis=1)))
    if off:
        rejected["above_horizon"] = rejected.get("above_horizon", 0) + off
    return out


def world_detections(reading: Detections, opts: DetectionTopic, tf: StaticTransforms, frame: str,
                     msgtype: str = "detection array") -> WorldDetections:
    """The detections of one message in ``frame`` (module docstring).

    Raises
    ------
    ValidationError
        Pixel detections without a homography; a frame not connected to ``frame``.
    """
    rejected: dict[str, int] = {}
    pts = np.asarray(reading.points, dtype=float).reshape(-1, 2)
    k = len(pts)
    covs = (np.full((k, 2, 2), np.nan) if reading.covs is None
            else np.asarray(reading.covs, dtype=float).reshape(k, 2, 2))
    if reading.pixels:
        pts = _to_ground(opts, msgtype, pts, rejected)
        covs = np.full((k, 2, 2), np.nan)
        src = (opts.ground_frame or frame).lstrip("/")
    else:
        src = reading.frame.lstrip("/") or frame
    finite = np.all(np.isfinite(pts), axis=1)
    bad = int(np.sum(~finite)) - rejected.get("above_horizon", 0)
    if bad:
        rejected["not_finite"] = bad
    pts, covs = pts[finite], covs[finite]
    T = tf.require(src, frame, f"topic {opts.topic}")
    pts = transform_points(pts, T) if len(pts) else pts.reshape(0, 2)
    stated = np.all(np.isfinite(covs), axis=(1, 2))
    default = np.eye(2) * opts.std**2
    out = np.empty_like(covs)
    for i in range(len(covs)):
        out[i] = rotate_covariance(covs[i], float(T[2])) if stated[i] else default
    return WorldDetections(pts, out, stated, rejected)
