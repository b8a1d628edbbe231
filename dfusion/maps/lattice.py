r"""A node-lattice view of :class:`dfusion.maps.OccupancyGrid` (the BLE RSSI dataset's grids).

There is one occupancy-grid class in dfusion, :class:`dfusion.maps.OccupancyGrid` (ROS
layout: ``data[row = y, column = x]``, origin at the lower-left *corner* of the first
cell). It holds everything the WSN particle filter needs: the exact vectorized segment
test (:meth:`~dfusion.maps.OccupancyGrid.segment_blocked`), the point test
(:meth:`~dfusion.maps.OccupancyGrid.is_blocked`) and uniform sampling of free space
(:meth:`~dfusion.maps.OccupancyGrid.sample_free`); the ``.occ`` files of the dataset are
read by :func:`dfusion.maps.io.read_occ`. :class:`dfusion.localization.WSNTracker`
accepts a grid directly.

:class:`NodeLattice` is only a thin *view* of such a grid in the conventions of the BLE
RSSI dataset's node lattices: ``occupied[ix, iy]`` indexed x first, ``origin`` the world
position of node ``(0, 0)`` (the *centre* of the first cell), ``shape = (nx, ny)``. It
stores the map grid in :attr:`NodeLattice.map` and delegates every test to it; it adds
no algorithm of its own.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.maps.grid import OccupancyGrid
from dfusion.maps.io import read_occ

__all__ = ["NodeLattice", "as_map_grid"]


class NodeLattice:
    """Node-lattice view (x-first, node-centred) of a :class:`dfusion.maps.OccupancyGrid`.

    Parameters
    ----------
    occupied : (nx, ny) bool array
        ``True`` where the node's cell is an obstacle (index order x, then y).
    cell : float
        Cell size (m).
    origin : (2,) float
        World position of node ``(0, 0)`` (m), the centre of its cell.

    Attributes
    ----------
    map : dfusion.maps.OccupancyGrid
        The grid itself (``data[iy, ix]``, origin ``origin - cell / 2``).
    """

    def __init__(self, occupied: ArrayLike, cell: float, origin: ArrayLike = (0.0, 0.0)) -> None:
        grid = OccupancyGrid.from_nodes(occupied, cell, origin)
        self._init_from_map(grid, np.array(origin, dtype=float).reshape(2))

    def _init_from_map(self, grid: OccupancyGrid, origin: Array | None = None) -> None:
        self.map = grid
        self.cell = grid.resolution
        self.origin = grid.origin[:2] + 0.5 * grid.resolution if origin is None else origin
        self.shape = (grid.width, grid.height)

    @classmethod
    def from_map(cls, grid: OccupancyGrid) -> "NodeLattice":
        """The node view of a map grid with yaw 0."""
        if grid.origin[2] != 0.0:

            raise ValidationError("the node-lattice view needs a map origin with yaw 0")
        self = cls.__new__(cls)
        self._init_from_map(grid)
        return self

    def __repr__(self) -> str:
        return (f"NodeLattice(shape={self.shape}, cell={self.cell}, origin={self.origin.tolist()}, "
                f"occupied={int(self.occupied.sum())}/{self.occupied.size})")

    # -------------------------------------------------------------- loading
    @classmethod
    def from_occ_file(cls, path: str | Path, occupied_value: int = 1) -> "NodeLattice":
        """Read a ``.occ`` grid (see :func:`dfusion.maps.io.read_occ`)."""
        return cls.from_map(read_occ(path, occupied_value))

    # ---------------------------------------------------------- conventions
    @property
    def occupied(self) -> np.ndarray:
        """``(nx, ny)`` boolean, x first (a read-only view of the map's occupied cells)."""
        return self.map.occupied.T

    @property
    def free_fraction(self) -> float:
        """Fraction of free cells."""
        return float(np.count_nonzero(self.map.free) / self.map.free.size)

    def world_to_cell(self, xy: ArrayLike) -> np.ndarray:
        """Integer node indices ``(..., 2)`` (x, y) of world points (nearest node; may be outside)."""
        p = np.asarray(xy, dtype=float)
        return np.floor((p - self.origin) / self.cell + 0.5).astype(np.int64)

    def cell_to_world(self, ij: ArrayLike) -> Array:
        """World position ``(..., 2)`` of nodes ``(..., 2)`` (x, y)."""
        return self.origin + self.cell * np.asarray(ij, dtype=float)

    def in_bounds(self, ij: ArrayLike) -> np.ndarray:
        """Whether integer node indices lie inside the grid."""
        ij = np.asarray(ij)
        return (ij[..., 0] >= 0) & (ij[..., 0] < self.shape[0]) & (ij[..., 1] >= 0) & (ij[..., 1] < self.shape[1])

    # ------------------------------------------------- delegated to the map
    def is_occupied(self, xy: ArrayLike) -> np.ndarray:
        """Occupancy of world points ``(..., 2)``; outside the grid (or NaN) is occupied."""
        return self.map.is_blocked(xy)

    def is_free(self, xy: ArrayLike) -> np.ndarray:
        """``~is_occupied(xy)``."""
        return ~self.map.is_blocked(xy)

    def sample_free(self, n: int, rng: np.random.Generator) -> Array:
        """``n`` points drawn uniformly over the free area (:meth:`dfusion.maps.OccupancyGrid.sample_free`)."""
        return self.map.sample_free(n, rng)

    def segment_blocked(self, p0: ArrayLike, p1: ArrayLike) -> np.ndarray:
        """Exact segment test (:meth:`dfusion.maps.OccupancyGrid.segment_blocked`)."""
        return self.map.segment_blocked(p0, p1)


def as_map_grid(grid: OccupancyGrid | NodeLattice) -> OccupancyGrid:
    """The :class:`dfusion.maps.OccupancyGrid` behind ``grid`` (itself, or a view's map)."""
    if isinstance(grid, NodeLattice):
        return grid.map
    if isinstance(grid, OccupancyGrid):
        return grid

    raise ValidationError("grid must be a dfusion.maps.OccupancyGrid or a dfusion.maps.NodeLattice")
