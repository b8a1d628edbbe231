"""Occupancy grids: the grid, map files, ray casting, grids from scans, synthetic buildings, node lattices."""
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
