"""Occupancy grids: the grid, map files, ray casting, grids from scans, synthetic buildings, node lattices."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.maps.magnetic import MagneticMap
    from dfusion.maps.nearest import NearestPointGrid
    from dfusion.maps.buildings import (
        GENERATORS,
        corridor,
        obstacle_grid,
        repetitive_corridor,
        rooms,
    )
    from dfusion.maps.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
    from dfusion.maps.io import (
        read_map_meta,
        read_map_yaml,
        read_occ,
        read_pgm,
        write_map_yaml,
        write_pgm,
    )
    from dfusion.maps.lattice import NodeLattice, as_map_grid
    from dfusion.maps.mapping import grid_from_scans
    from dfusion.maps.raycast import RayCastTable, cast_rays

__all__ = [
    "MagneticMap",
    "NearestPointGrid",
    "rooms",
    "corridor",
    "repetitive_corridor",
    "obstacle_grid",
    "GENERATORS",
    "OccupancyGrid",
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "read_map_yaml",
    "write_map_yaml",
    "read_map_meta",
    "read_pgm",
    "write_pgm",
    "read_occ",
    "NodeLattice",
    "as_map_grid",
    "grid_from_scans",
    "cast_rays",
    "RayCastTable",
]

_WHERE = {
    "MagneticMap": ("dfusion.maps.magnetic", "MagneticMap"),
    "NearestPointGrid": ("dfusion.maps.nearest", 'NearestPointGrid'),
    "GENERATORS": ("dfusion.maps.buildings", 'GENERATORS'),
    "corridor": ("dfusion.maps.buildings", 'corridor'),
    "obstacle_grid": ("dfusion.maps.buildings", 'obstacle_grid'),
    "repetitive_corridor": ("dfusion.maps.buildings", 'repetitive_corridor'),
    "rooms": ("dfusion.maps.buildings", 'rooms'),
    "FREE": ("dfusion.maps.grid", 'FREE'),
    "OCCUPIED": ("dfusion.maps.grid", 'OCCUPIED'),
    "UNKNOWN": ("dfusion.maps.grid", 'UNKNOWN'),
    "OccupancyGrid": ("dfusion.maps.grid", 'OccupancyGrid'),
    "read_map_meta": ("dfusion.maps.io", 'read_map_meta'),
    "read_map_yaml": ("dfusion.maps.io", 'read_map_yaml'),
    "read_occ": ("dfusion.maps.io", 'read_occ'),
    "read_pgm": ("dfusion.maps.io", 'read_pgm'),
    "write_map_yaml": ("dfusion.maps.io", 'write_map_yaml'),
    "write_pgm": ("dfusion.maps.io", 'write_pgm'),
    "NodeLattice": ("dfusion.maps.lattice", 'NodeLattice'),
    "as_map_grid": ("dfusion.maps.lattice", 'as_map_grid'),
    "grid_from_scans": ("dfusion.maps.mapping", 'grid_from_scans'),
    "RayCastTable": ("dfusion.maps.raycast", 'RayCastTable'),
    "cast_rays": ("dfusion.maps.raycast", 'cast_rays'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
