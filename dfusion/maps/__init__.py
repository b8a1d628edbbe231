"""Occupancy grid maps and ray casting for map-based localization.

* :class:`OccupancyGrid` -- ROS map_server grids: load/save YAML + PGM, build from laser
  scans, generated test buildings, distance field.
* :func:`cast_rays` -- exact vectorized ray casting (grid traversal with empty-space skipping).
* :class:`RayCastTable` -- precomputed expected ranges per (cell, heading bin).
"""
from .grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid, parse_simple_yaml, read_pgm, write_pgm
from .raycast import RayCastTable, cast_rays

__all__ = [
    "OccupancyGrid",
    "RayCastTable",
    "cast_rays",
    "parse_simple_yaml",
    "read_pgm",
    "write_pgm",
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
]
