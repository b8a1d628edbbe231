r"""Scenario kind ``camera``: a calibrated camera detecting the target in its image.

The node table gives the camera's pose and intrinsics (``docs/scenarios.md``); the
simulated world measures with a :class:`~dfusion.models.camera.SceneCamera` (true
detections when the target is in view, plus Poisson false detections), and the node
fuses them with a :class:`~dfusion.frontends.camera.CameraFrontEnd`: the detections of a
frame gated and associated by PDA (``clutter_model = "pda"``, the default of
``[protection]``) or each fused on its own inside the gate (``"gate"``).
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.frontends.camera import CLUTTER_MODELS, CameraFrontEnd, gate_threshold
from dfusion.models.camera import PinholeCamera, SceneCamera
from dfusion.scenario.spec import COMMON_NODE_KEYS, NodeSpec, Scenario, SensorKind
from dfusion.scenario.values import check_keys, number, vector

__all__ = ["CAMERA", "CAMERA_KEYS", "camera_from_table"]


#: Keys of a ``sensor = "camera"`` node table, besides the common node keys.
CAMERA_KEYS = frozenset({"position", "look_at", "yaw", "pitch", "fx", "fy", "cx", "cy", "width", "height", "pixel_std",
               "point_height", "false_detection_rate", "gate", "recognition_error", "clutter_model"})


def camera_from_table(table: Mapping[str, Any]) -> SceneCamera:
    """Build the camera of a ``sensor = "camera"`` node table (keys: see ``docs/scenarios.md``)."""
    check_keys(table, COMMON_NODE_KEYS | CAMERA_KEYS, "a camera node")
    position = vector(table, "position", (3,))
    width = table.get("width", 640)
    height = table.get("height", 480)
    for key, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValidationError(f"{key} must be a positive integer (pixels), got {v!r}")
    fx = number(table, "fx", 500.0, positive=True)
    fy = number(table, "fy", fx, positive=True)
    cx = number(table, "cx", width / 2.0)
    cy = number(table, "cy", height / 2.0)
    point_height = number(table, "point_height", 0.0)
    kw = dict(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
              pixel_std=number(table, "pixel_std", 2.0, positive=True), point_height=point_height)
    has_look = "look_at" in table
    has_angles = "yaw" in table or "pitch" in table
    if has_look == has_angles:
        raise ValidationError("give either look_at = [x, y(, z)] or yaw and pitch (degrees)")
    if has_look:
        target = vector(table, "look_at", (2, 3))
        if target.shape[0] == 2:
            target = np.append(target, point_height)
        up = (0.0, 0.0, 1.0)
    else:
        yaw = math.radians(number(table, "yaw"))
        pitch = math.radians(number(table, "pitch"))
        if not -math.pi / 2 <= pitch <= math.pi / 2:
            raise ValidationError(f"pitch must be in [-90, 90] degrees, got {table['pitch']!r}")
        fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
        target = position + fwd
        # looking straight down: the image's top faces the yaw direction
        up = (0.0, 0.0, 1.0) if abs(math.cos(pitch)) > 1e-6 else (math.cos(yaw), math.sin(yaw), 0.0)
    cam = PinholeCamera.looking_at(position, target, up, **kw)
    return SceneCamera(cam.position, cam.R_wc, fx, fy, cx, cy, width, height, kw["pixel_std"], point_height,
                       clutter_rate=number(table, "false_detection_rate", 0.0, nonneg=True))


def _camera_sensor(table: Mapping[str, Any], sc: Scenario) -> SceneCamera:
    cam = camera_from_table(table)
    gate_threshold(table.get("gate", 0.99))   # validate at load time
    if table.get("clutter_model", "pda") not in CLUTTER_MODELS:
        raise ValidationError(f"clutter_model must be one of {CLUTTER_MODELS}, got {table['clutter_model']!r}")
    if "recognition_error" in table:
        number(table, "recognition_error", nonneg=True)
    if cam.position[2] <= cam.point_height:
        raise ValidationError("position: the camera must be above point_height")
    return cam


def _camera_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> CameraFrontEnd:
    """The camera's front end: its ``clutter_model`` (default ``protection.clutter_model``; the
    hard gate alone when ``protection.enabled = false``), PDA with the camera's
    ``false_detection_rate`` and ``detection``; a fused frame is confirmed by the next one, and
    a gap of two frame periods without a fused frame starts a new track segment."""
    confirm = 1
    return CameraFrontEnd(spec.sensor, gate=spec.params.get("gate", 0.99),
                          recognition_error=spec.params.get("recognition_error"),
                          clutter_model=sc.protection.camera_model(spec.params.get("clutter_model")),
                          detection=spec.detection, confirm=confirm,
                          segment_gap=(confirm + 1) / spec.rate if spec.rate > 0 else None)


#: The ``camera`` sensor kind.
CAMERA = SensorKind("camera", CAMERA_KEYS, _camera_sensor, _camera_front_end,
                    "a calibrated camera detecting the target (pixels): frames gated and associated by PDA")
