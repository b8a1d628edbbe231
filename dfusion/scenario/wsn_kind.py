r"""Scenario kind ``wsn_rssi``: a wireless sensor network tracking a radio tag with a particle filter.

The simulated world measures one RSSI reading per receiver at every measurement time with
the log-distance model of :class:`~dfusion.models.RSSISensor`; the node runs a
:class:`~dfusion.localization.WSNTracker` in a :class:`~dfusion.frontends.wsn.WSNFrontEnd`.
Keys: ``docs/scenarios.md``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.frontends.wsn import WSNFrontEnd
from dfusion.localization.wsn_tracker import MOTIONS, WSNTracker
from dfusion.maps.buildings import obstacle_grid
from dfusion.maps.lattice import NodeLattice
from dfusion.models.measurement import RSSISensor
from dfusion.scenario.spec import COMMON_NODE_KEYS, NodeSpec, Scenario, SensorKind
from dfusion.scenario.values import check_keys, number

__all__ = ["WSN_RSSI", "WSN_KEYS", "rssi_sensor_from_table", "grid_from_table"]


#: Keys of a ``sensor = "wsn_rssi"`` node table, besides the common node keys.
WSN_KEYS = frozenset({"std", "receivers", "p0", "exponent", "d0", "tag_height", "particles", "pf_motion", "pf_q", "max_speed",
            "std_scale", "outlier_prob", "roughening", "map", "map_occupied_value", "obstacles", "map_bounds",
            "map_cell", "pf_information"})


def rssi_sensor_from_table(table: Mapping[str, Any]) -> RSSISensor:
    """The :class:`RSSISensor` of a ``sensor = "wsn_rssi"`` node table."""
    check_keys(table, COMMON_NODE_KEYS | WSN_KEYS, "a wsn_rssi node")
    rec = table.get("receivers")
    if not (isinstance(rec, list) and rec and all(isinstance(r, list) and len(r) in (2, 3) for r in rec)):
        raise ValidationError("receivers must be a non-empty list of [x, y] or [x, y, z] positions")
    if len({len(r) for r in rec}) != 1:
        raise ValidationError("receivers must all be [x, y] or all be [x, y, z]")
    std = table.get("std", 4.0)
    if isinstance(std, list) and len(std) != len(rec):
        raise ValidationError(f"std must be one value or one per receiver ({len(rec)}), got {len(std)}")
    return RSSISensor(rec, number(table, "p0", -45.0), number(table, "exponent", 2.0, positive=True), std,
                      d0=number(table, "d0", 1.0, positive=True), height=number(table, "tag_height", 0.0))


def grid_from_table(table: Mapping[str, Any], base: Path | None = None) -> NodeLattice | None:
    """The optional map of a ``wsn_rssi`` node: ``map`` (an ``.occ`` file) or ``obstacles``; None without."""
    if "map" in table and "obstacles" in table:
        raise ValidationError("give either map (an .occ file) or obstacles, not both")
    if "map" in table:
        path = table["map"]
        if not isinstance(path, str) or not path:
            raise ValidationError(f"map must be a path to an .occ grid file, got {path!r}")
        p = Path(path)
        if not p.is_absolute() and base is not None:
            p = base / p
        value = table.get("map_occupied_value", 1)
        if value not in (0, 1) or isinstance(value, bool):
            raise ValidationError(f"map_occupied_value must be 0 or 1, got {value!r}")
        try:
            return NodeLattice.from_occ_file(p, occupied_value=value)
        except OSError as exc:
            raise ValidationError(f"map: cannot read {p}: {exc}") from None
    if "obstacles" in table:
        obs = table["obstacles"]
        ok = isinstance(obs, list) and all(
            isinstance(r, list) and len(r) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                       and math.isfinite(v) for v in r) and r[2] > r[0] and r[3] > r[1]
            for r in obs)
        if not ok:
            raise ValidationError("obstacles must be a list of [x_min, y_min, x_max, y_max] rectangles")
        b = table.get("map_bounds")
        if not (isinstance(b, list) and len(b) == 4 and all(isinstance(v, (int, float)) for v in b)
                and b[2] > b[0] and b[3] > b[1]):
            raise ValidationError("obstacles need map_bounds = [x_min, y_min, x_max, y_max]")
        cell = number(table, "map_cell", 0.25, positive=True)
        return obstacle_grid(obs, np.asarray(b, dtype=float), cell)
    for key in ("map_bounds", "map_cell", "map_occupied_value"):
        if key in table:
            raise ValidationError(f"{key} given without map or obstacles")
    return None


def _wsn_sensor(table: Mapping[str, Any], sc: Scenario) -> RSSISensor:
    sensor = rssi_sensor_from_table(table)
    # validate the tracker's keys now, so that errors name the scenario file
    _tracker_options(table, sc)
    _information(table)
    base = None if sc.base_dir is None else Path(sc.base_dir)
    grid_from_table(table, base)
    return sensor


def _tracker_options(table: Mapping[str, Any], sc: Scenario) -> dict[str, Any]:
    motion = table.get("pf_motion", "constant_velocity")
    if motion not in MOTIONS:
        raise ValidationError(f"pf_motion must be one of {MOTIONS}, got {motion!r}")
    q_default = getattr(sc.target.motion, "q", 0.1) if motion == "constant_velocity" else 0.5
    particles = table.get("particles", 5000)
    if isinstance(particles, bool) or not isinstance(particles, int) or particles < 2:
        raise ValidationError(f"particles must be an integer >= 2, got {particles!r}")
    max_speed = table.get("max_speed")
    if max_speed is not None:
        max_speed = number(table, "max_speed", None, positive=True)
    outlier = number(table, "outlier_prob", 0.0, nonneg=True)
    if outlier >= 1:
        raise ValidationError(f"outlier_prob must be in [0, 1), got {outlier}")
    return dict(n_particles=particles, motion=motion, q=number(table, "pf_q", q_default, positive=True),
                max_speed=max_speed, std_scale=number(table, "std_scale", 1.0, positive=True),
                outlier_prob=outlier, roughening=number(table, "roughening", 0.0, nonneg=True))


def _wsn_front_end(spec: NodeSpec, sc: Scenario, seed: int) -> WSNFrontEnd:
    table = {"sensor": "wsn_rssi", **spec.params}
    base = None if sc.base_dir is None else Path(sc.base_dir)
    grid = grid_from_table(table, base)
    tracker = WSNTracker(spec.sensor, grid=grid, seed=seed, **_tracker_options(table, sc))
    return WSNFrontEnd(tracker, (0.0, sc.target.initial_mean, sc.target.initial_cov), axes=sc.target.axes,
                       information=_information(table))


def _information(table: Mapping[str, Any]) -> str:
    v = table.get("pf_information", "quotient")
    if v not in ("quotient", "regression"):
        raise ValidationError(f"pf_information must be 'quotient' or 'regression', got {v!r}")
    return v


#: The ``wsn_rssi`` sensor kind.
WSN_RSSI = SensorKind("wsn_rssi", WSN_KEYS, _wsn_sensor, _wsn_front_end,
                      "RSSI of a radio tag at fixed receivers, tracked by a particle filter")
