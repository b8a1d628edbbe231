r"""Scenario kind ``camera``: a calibrated camera detecting the target in its image.

The node table gives the camera's pose and intrinsics (``docs/scenarios.md``); the
simulated world measures with a :class:`~dfusion.models.camera.SceneCamera` (true
detections when the target is in view, plus Poisson false detections), and the node
fuses them with a :class:`~dfusion.frontends.camera.CameraFrontEnd`: the detections of a
frame gated and associated by PDA (``clutter_model = "pda"``, the default of
``[protection]``) or each fused on its own inside the gate (``"gate"``).

Scenario kind ``robot_camera``: the same camera carried by a robot that drives the node's
``path`` (:class:`~dfusion.models.camera.MountedCamera`, mounted ``mount_height`` metres up,
looking along the robot's heading turned by ``yaw_offset`` and tilted down by ``pitch``
degrees), fused with a :class:`~dfusion.frontends.camera.MountedCameraFrontEnd` (the same
gate and clutter model, with the camera where it was at each frame's time).
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.frontends.camera import CLUTTER_MODELS, CameraFrontEnd, MountedCameraFrontEnd, gate_threshold
from dfusion.models.camera import MountedCamera, PinholeCamera, SceneCamera
from dfusion.scenario.spec import COMMON_NODE_KEYS, NodeSpec, Scenario, SensorKind
from dfusion.scenario.values import check_keys, number, vector, waypoint_path

__all__ = ["CAMERA", "CAMERA_KEYS", "camera_from_table", "ROBOT_CAMERA", "ROBOT_CAMERA_KEYS"]


#: Keys of a ``sensor = "camera"`` node table, besides the common node keys.
CAMERA_KEYS = frozenset({"position", "look_at", "yaw", "pitch", "fx", "fy", "cx", "cy", "width", "height", "pixel_std",
               "point_height", "false_detection_rate", "gate", "recognition_error", "clutter_model"})


def _image_size(table: Mapping[str, Any]) -> tuple[int, int]:
    """``width`` and ``height`` of a camera table (pixels, default 640 x 480)."""
    width = table.get("width", 640)
    height = table.get("height", 480)
    for key, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValidationError(f"{key} must be a positive integer (pixels), got {v!r}")
    return width, height


def camera_from_table(table: Mapping[str, Any]) -> SceneCamera:
    """Build the camera of a ``sensor = "camera"`` node table (keys: see ``docs/scenarios.md``)."""
    check_keys(table, COMMON_NODE_KEYS | CAMERA_KEYS, "a camera node")
    position = vector(table, "position", (3,))
    width, height = _image_size(table)
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


def _check_front_end_keys(table: Mapping[str, Any]) -> None:
    """Validate the front end's keys at load time: ``gate``, ``clutter_model``, ``recognition_error``."""
    gate_threshold(table.get("gate", 0.99))
    if table.get("clutter_model", "pda") not in CLUTTER_MODELS:
        raise ValidationError(f"clutter_model must be one of {CLUTTER_MODELS}, got {table['clutter_model']!r}")
    if "recognition_error" in table:
        number(table, "recognition_error", nonneg=True)


def _camera_sensor(table: Mapping[str, Any], sc: Scenario) -> SceneCamera:
    cam = camera_from_table(table)
    _check_front_end_keys(table)
    if cam.position[2] <= cam.point_height:
        raise ValidationError("position: the camera must be above point_height")
    return cam


def _camera_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> CameraFrontEnd:
    """The camera's front end: its ``clutter_model`` (default ``protection.clutter_model``; the
    hard gate alone when ``protection.enabled = false``), PDA with the camera's
    ``false_detection_rate`` and ``detection``; a fused frame is confirmed by the next one, and
    a gap of two frame periods without a fused frame starts a new track segment."""
    return CameraFrontEnd(spec.sensor, **_front_end_options(spec, sc))


def _front_end_options(spec: NodeSpec, sc: Scenario) -> dict[str, Any]:
    """The keyword arguments of a camera node's front end (fixed or on a robot)."""
    confirm = 1
    return dict(gate=spec.params.get("gate", 0.99), recognition_error=spec.params.get("recognition_error"),
                clutter_model=sc.protection.camera_model(spec.params.get("clutter_model")),
                detection=spec.detection, confirm=confirm,
                segment_gap=(confirm + 1) / spec.rate if spec.rate > 0 else None)


#: The ``camera`` sensor kind.
CAMERA = SensorKind("camera", CAMERA_KEYS, _camera_sensor, _camera_front_end,
                    "a calibrated camera detecting the target (pixels): frames gated and associated by PDA")


#: Keys of a ``sensor = "robot_camera"`` node table, besides the common node keys (``path`` is required).
ROBOT_CAMERA_KEYS = frozenset({"fx", "fy", "cx", "cy", "width", "height", "pixel_std", "point_height",
                               "false_detection_rate", "gate", "recognition_error", "clutter_model",
                               "mount_height", "pitch", "yaw_offset"})


def _robot_camera_sensor(table: Mapping[str, Any], sc: Scenario) -> MountedCamera:
    check_keys(table, COMMON_NODE_KEYS | ROBOT_CAMERA_KEYS, "a robot_camera node")
    path = waypoint_path(table)
    if path is None:
        raise ValidationError("a robot_camera node needs a path = [[x, y], ...] and a speed (m/s)")
    width, height = _image_size(table)
    fx = number(table, "fx", 500.0, positive=True)
    _check_front_end_keys(table)
    return MountedCamera(path.pose, mount_height=number(table, "mount_height", 1.5, positive=True),
                         pitch=math.radians(number(table, "pitch", 20.0)),
                         yaw_offset=math.radians(number(table, "yaw_offset", 0.0)),
                         fx=fx, fy=number(table, "fy", fx, positive=True), cx=number(table, "cx", width / 2.0),
                         cy=number(table, "cy", height / 2.0), width=width, height=height,
                         pixel_std=number(table, "pixel_std", 2.0, positive=True),
                         point_height=number(table, "point_height", 0.0),
                         clutter_rate=number(table, "false_detection_rate", 0.0, nonneg=True))


def _robot_camera_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> MountedCameraFrontEnd:
    """As a fixed camera's front end (:func:`_front_end_options`), with the camera at each frame's time."""
    return MountedCameraFrontEnd(spec.sensor, **_front_end_options(spec, sc))


#: The ``robot_camera`` sensor kind: a camera on a robot driving the node's path.
ROBOT_CAMERA = SensorKind("robot_camera", ROBOT_CAMERA_KEYS, _robot_camera_sensor, _robot_camera_front_end,
                          "a camera on a robot driving the node's path (pixels): frames gated and associated by PDA")
