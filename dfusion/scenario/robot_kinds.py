r"""Scenario kinds for robot localizers (``docs/robots.md``).

``sensor = "robot_mcl"``, ``"robot_icp"`` or ``"robot_env_camera"`` in a node table of a
scenario file. In all three the scenario's *target is a robot* (state ``(x, y, vx, vy)``
of a 2-D constant-velocity target; its heading is the direction of motion), and the
node's front end runs a localizer and contributes the robot's position to the node
(:mod:`dfusion.frontends.mcl`, :mod:`dfusion.frontends.icp`,
:mod:`dfusion.frontends.env_camera`):

``robot_mcl``
    The simulated world measures a laser scan (:class:`LaserScanSensor`) in the node's
    map; :class:`MCLFrontEnd` runs Monte Carlo localization and adds the Gaussian fit of
    its posterior minus that of its prediction (:mod:`dfusion.frontends.base`).
``robot_icp``
    Same scan; :class:`ICPFrontEnd` matches it against the map (point-to-line ICP) and
    adds the match as a position measurement.
``robot_env_camera``
    A ceiling camera (:class:`~dfusion.models.PinholeCamera`) sees the robot's marker;
    :class:`EnvCameraFrontEnd` back-projects the pixel and adds the fix, with the
    camera reliability of the switching paper (eq. 1-9) reported to the node's policy.

Node-table keys (besides the common ones of ``docs/scenarios.md``):

* laser kinds: ``map`` (``"rooms"``, ``"corridor"``, ``"repetitive_corridor"`` -- the
  generators of :mod:`dfusion.maps.buildings`, with the table ``map_args`` of
  their keyword arguments -- or the path of a ROS map YAML file, relative to the
  scenario file), ``beams`` (61), ``fov`` (degrees, 360), ``max_range`` (m, 10),
  ``range_std`` (m, 0.05);
* ``robot_mcl``: ``particles`` (2,000, the KLD maximum), ``min_particles`` (200),
  ``sensor_model`` (``"likelihood_field"`` or ``"erfc"``), ``max_beams`` (60), ``q_pos``
  (m^2/s, 0.05), ``q_heading`` (rad^2/s, 0.05), ``heading_std`` (rad, 0.5);
* ``robot_icp``: ``cov_scale`` (4), ``min_std`` (m, 0.02), ``max_rmse`` (m, 0.1),
  ``min_inliers`` (20);
* ``robot_env_camera``: ``camera_position`` ([x, y, z], m), ``camera_target`` ([x, y, z],
  the point the optical axis goes through), ``fx``, ``fy`` (pixels, 600), ``width``,
  ``height`` (640, 480), ``cx``, ``cy`` (image centre), ``pixel_std`` (1.0), ``point_height``
  (height of the marker, m, 0), ``k_pixels`` (the ``k`` of eq. 7, default ``pixel_std``),
  ``min_reliability`` (0: fixes below it are dropped).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.frontends.env_camera import EnvCameraFrontEnd
from dfusion.frontends.icp import ICPFrontEnd
from dfusion.frontends.mcl import MCLFrontEnd
from dfusion.localization.env_camera import EnvironmentCameraLocalizer
from dfusion.localization.scan_matching import ScanMatcher
from dfusion.localization.mcl import MonteCarloLocalization
from dfusion.maps.buildings import GENERATORS
from dfusion.maps.grid import OccupancyGrid
from dfusion.maps.io import read_map_yaml
from dfusion.models.camera import PinholeCamera
from dfusion.models.laser import (
    BeamErfcModel,
    LaserConfig,
    LaserScanSensor,
    LikelihoodFieldModel,
)
from dfusion.scenario.spec import NodeSpec, Scenario, SensorKind

__all__ = ["load_map", "ROBOT_MCL", "ROBOT_ICP", "ROBOT_ENV_CAMERA"]

_MAPS: dict[tuple, OccupancyGrid] = {}


def _check_target(sc: Scenario) -> None:
    if sc.target.motion.dim != 4 or getattr(sc.target, "axes", 2) != 2:
        raise ValidationError("robot sensor kinds need a 2-D constant-velocity target (x, y, vx, vy)")


def load_map(table: Mapping[str, Any], base: str | Path | None = None) -> OccupancyGrid:
    """The map of a node table (cached: every node naming the same map shares one grid).

    A relative YAML path starts from the directory ``base`` (the scenario file's).
    """
    name = table.get("map", "rooms")
    args = table.get("map_args", {})
    if not isinstance(name, str):
        raise ValidationError("map must be a generator name or a YAML path")
    if not isinstance(args, dict):
        raise ValidationError("map_args must be a table")
    if name in GENERATORS:
        key = (name, tuple(sorted((k, repr(v)) for k, v in args.items())))
        if key not in _MAPS:
            try:
                _MAPS[key] = GENERATORS[name](**args)
            except TypeError as exc:
                raise ValidationError(f"map_args for {name}: {exc}") from None
        return _MAPS[key]
    path = Path(name)
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    key = ("yaml", str(path.resolve()))
    if key not in _MAPS:
        if not path.is_file():
            raise ValidationError(f"map file {path} not found (or map must be one of {sorted(GENERATORS)})")
        _MAPS[key] = read_map_yaml(path)
    return _MAPS[key]


def _laser(table: Mapping[str, Any]) -> LaserConfig:
    beams = int(table.get("beams", 61))
    fov = math.radians(float(table.get("fov", 360.0)))
    return LaserConfig.uniform(beams, fov, float(table.get("max_range", 10.0)))


def _laser_sensor(table: Mapping[str, Any], sc: Scenario) -> LaserScanSensor:
    _check_target(sc)
    grid = load_map(table, sc.base_dir)
    return LaserScanSensor(grid, _laser(table), float(table.get("range_std", 0.05)))


def _mcl_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> MCLFrontEnd:
    p = spec.params
    sensor: LaserScanSensor = spec.sensor
    kind = p.get("sensor_model", "likelihood_field")
    if kind == "likelihood_field":
        model = LikelihoodFieldModel()
    elif kind == "erfc":
        model = BeamErfcModel(sigma=max(float(p.get("range_std", 0.05)), 0.05))
    else:
        raise ValidationError(f"sensor_model must be 'likelihood_field' or 'erfc', got {kind!r}")
    mcl = MonteCarloLocalization(
        sensor.grid, sensor.laser, sensor=model, min_particles=int(p.get("min_particles", 200)),
        max_particles=int(p.get("particles", 2000)), max_beams=int(p.get("max_beams", 60)), rng=seed,
    )
    return MCLFrontEnd(mcl, q_pos=float(p.get("q_pos", 0.05)), q_heading=float(p.get("q_heading", 0.05)),
                       heading_std=float(p.get("heading_std", 0.5)))


def _icp_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> ICPFrontEnd:
    p = spec.params
    sensor: LaserScanSensor = spec.sensor
    matcher = ScanMatcher.from_grid(sensor.grid, "point_to_line", max_correspondence_distance=0.5,
                                    trim_fraction=0.1, tolerance=1e-4)
    return ICPFrontEnd(matcher, sensor.laser, cov_scale=float(p.get("cov_scale", 4.0)),
                       min_std=float(p.get("min_std", 0.02)), min_inliers=int(p.get("min_inliers", 20)),
                       max_rmse=float(p.get("max_rmse", 0.1)))


def _camera(table: Mapping[str, Any], sc: Scenario) -> PinholeCamera:
    _check_target(sc)
    if "camera_position" not in table or "camera_target" not in table:
        raise ValidationError("robot_env_camera needs camera_position and camera_target ([x, y, z])")
    w, h = int(table.get("width", 640)), int(table.get("height", 480))
    return PinholeCamera.looking_at(
        np.asarray(table["camera_position"], dtype=float), np.asarray(table["camera_target"], dtype=float),
        fx=float(table.get("fx", 600.0)), fy=float(table.get("fy", 600.0)),
        cx=float(table.get("cx", w / 2)), cy=float(table.get("cy", h / 2)), width=w, height=h,
        pixel_std=float(table.get("pixel_std", 1.0)), point_height=float(table.get("point_height", 0.0)),
    )


def _camera_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> EnvCameraFrontEnd:
    p = spec.params
    k = p.get("k_pixels")
    loc = EnvironmentCameraLocalizer(spec.sensor, k_pixels=None if k is None else float(k))
    return EnvCameraFrontEnd(loc, min_reliability=float(p.get("min_reliability", 0.0)))


#: Node-table keys of the laser kinds.
LASER_KEYS = frozenset({"map", "map_args", "beams", "fov", "max_range", "range_std"})
#: The ``robot_mcl`` sensor kind.
ROBOT_MCL = SensorKind("robot_mcl", LASER_KEYS | {"particles", "min_particles", "sensor_model", "max_beams", "q_pos",
                                                 "q_heading", "heading_std"},
                       _laser_sensor, _mcl_front_end, "a robot localized by Monte Carlo localization (laser, map)")
#: The ``robot_icp`` sensor kind.
ROBOT_ICP = SensorKind("robot_icp", LASER_KEYS | {"cov_scale", "min_std", "max_rmse", "min_inliers"},
                       _laser_sensor, _icp_front_end, "a robot localized by ICP scan matching against a map")
#: The ``robot_env_camera`` sensor kind.
ROBOT_ENV_CAMERA = SensorKind("robot_env_camera", frozenset({
    "camera_position", "camera_target", "fx", "fy", "width", "height", "cx", "cy", "pixel_std", "point_height",
    "k_pixels", "min_reliability"}), _camera, _camera_front_end, "a ceiling camera localizing a robot's marker")
