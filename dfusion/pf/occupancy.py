r"""A small 2-D occupancy grid for map-constrained particle motion.

The grid holds one boolean per *node* ``(i, j)`` at world position
``origin + (i * cell, j * cell)``; node ``(i, j)`` owns the square cell
``[x_i - cell/2, x_i + cell/2) x [y_j - cell/2, y_j + cell/2)`` centred on it.
Everything outside the grid counts as occupied.

The segment test (:meth:`OccupancyGrid.segment_blocked`) is exact: a move is
blocked when its straight segment passes through an occupied cell (start and
end cells included). Every cell the segment visits after its start cell is
entered through exactly one cell boundary, a vertical line
``x = x_i + cell/2`` or a horizontal line ``y = y_j + cell/2``; the entered
cell is known from the boundary's index and the segment's other coordinate
where it crosses that line (the grid traversal of Amanatides & Woo, "A fast
voxel traversal algorithm for ray tracing", Eurographics 1987, computed for
all segments at once instead of stepping cell by cell). A segment that only
touches a cell at a single corner point does not count as entering it.

Two shortcuts keep it fast without changing the answer: a segment stays inside
the rectangle of cells spanned by its two end cells, so if a summed-area table
says that rectangle holds no obstacle the segment is accepted at once (four
look-ups); a segment that crosses at most one boundary (a move within a cell
or into a 4-neighbour) visits only its end cells. The crossings of the
remaining segments are listed in one flat array (``np.repeat``), so the work
is proportional to their total number of crossings.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ShapeError, ValidationError
from ..linalg import Array

__all__ = ["OccupancyGrid"]


class OccupancyGrid:
    """Boolean occupancy grid; ``occupied[i, j]`` is the node at ``origin + cell * (i, j)``.

    Parameters
    ----------
    occupied : (nx, ny) bool array
        ``True`` where the cell is an obstacle (index order x, then y).
    cell : float
        Cell size (m).
    origin : (2,) float
        World position of node ``(0, 0)`` (m).
    """

    _PAD = 3

    def __init__(self, occupied: ArrayLike, cell: float, origin: ArrayLike = (0.0, 0.0)) -> None:
        occ = np.array(occupied, dtype=bool)
        if occ.ndim != 2 or min(occ.shape) < 1:
            raise ShapeError(f"occupied must be a non-empty 2-D array, got shape {occ.shape}")
        cell = float(cell)
        if not (np.isfinite(cell) and cell > 0):
            raise ValidationError(f"cell size must be positive, got {cell}")
        org = np.array(origin, dtype=float).reshape(-1)
        if org.shape != (2,) or not np.all(np.isfinite(org)):
            raise ShapeError(f"origin must be 2 finite numbers, got {origin!r}")
        self.occupied = occ
        self.cell = cell
        self.origin = org
        self.shape = occ.shape
        # Padded copy: an occupied border of _PAD cells makes out-of-grid lookups a plain index
        # (continuous coordinates are clipped to [-2, shape + 2] first, see _u1).
        P = self._PAD
        self._padded = np.ones((occ.shape[0] + 2 * P, occ.shape[1] + 2 * P), dtype=bool)
        self._padded[P:-P, P:-P] = occ
        self._flat = self._padded.ravel()
        self._width = occ.shape[1] + 2 * P
        self._offset = P * self._width + P
        self._free_idx = np.flatnonzero(~occ.ravel())
        self._ulim = np.array(occ.shape, dtype=float) + 2.0
        # Summed-area table of the padded occupancy: the number of occupied cells in any
        # index rectangle costs four look-ups (used to clear segments whose cell bounding
        # box holds no obstacle).
        sat = np.zeros((self._padded.shape[0] + 1, self._padded.shape[1] + 1), dtype=np.int32)
        sat[1:, 1:] = np.cumsum(np.cumsum(self._padded, axis=0, dtype=np.int32), axis=1, dtype=np.int32)
        self._sat = sat.ravel()
        self._sat_width = sat.shape[1]

    def __repr__(self) -> str:
        return (f"OccupancyGrid(shape={self.shape}, cell={self.cell}, origin={self.origin.tolist()}, "
                f"occupied={int(self.occupied.sum())}/{self.occupied.size})")

    # -------------------------------------------------------------- loading
    @classmethod
    def from_occ_file(cls, path: str | Path, occupied_value: int = 1) -> "OccupancyGrid":
        """Read a ``.occ`` grid of the BLE RSSI dataset (Daniş et al.).

        Format: line 1 ``[[x_min, y_min], [x_max, y_max]]::cell``; every other line
        ``[x, y]::v``, one per node, in any order. ``occupied_value`` is the value
        that marks an obstacle: the dataset's own README says 1 = traversable, but the
        data show the reverse (tracks run on 0-nodes, tables and the border are 1),
        so 1 = occupied is the default. Raises :class:`ValidationError` on a
        malformed file, a missing or duplicated node, or a node off the lattice.
        """
        path = Path(path)
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
        if not lines:
            raise ValidationError(f"{path}: empty occupancy file")
        try:
            head, cell_s = lines[0].rsplit("::", 1)
            (x0, y0), (x1, y1) = json.loads(head)
            cell = float(cell_s)
            pts = np.array([json.loads(ln.split("::", 1)[0]) for ln in lines[1:]], dtype=float)
            vals = np.array([int(ln.rsplit("::", 1)[1]) for ln in lines[1:]])
        except (ValueError, TypeError) as exc:
            raise ValidationError(f"{path}: malformed occupancy file ({exc})") from None
        if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isin(vals, (0, 1))):
            raise ValidationError(f"{path}: node lines must be '[x, y]::0' or '[x, y]::1'")
        ij = np.rint((pts - np.array([x0, y0])) / cell).astype(int)
        if np.max(np.abs(ij * cell + np.array([x0, y0]) - pts)) > 1e-6 * max(1.0, cell) or np.any(ij < 0):
            raise ValidationError(f"{path}: node positions are not on the {cell} m lattice from ({x0}, {y0})")
        nx, ny = ij.max(axis=0) + 1
        if nx * ny != len(ij):
            raise ValidationError(f"{path}: expected {nx} x {ny} = {nx * ny} nodes, found {len(ij)}")
        occ = np.zeros((nx, ny), dtype=bool)
        seen = np.zeros((nx, ny), dtype=bool)
        seen[ij[:, 0], ij[:, 1]] = True
        if not seen.all():
            raise ValidationError(f"{path}: duplicated or missing nodes")
        occ[ij[:, 0], ij[:, 1]] = vals == occupied_value
        return cls(occ, cell, (x0, y0))

    # ---------------------------------------------------------- conversions
    def world_to_cell(self, xy: ArrayLike) -> np.ndarray:
        """Integer cell indices ``(..., 2)`` of world points ``(..., 2)`` (nearest node; may be outside)."""
        p = np.asarray(xy, dtype=float)
        return np.floor((p - self.origin) / self.cell + 0.5).astype(np.int64)

    def cell_to_world(self, ij: ArrayLike) -> Array:
        """World position ``(..., 2)`` of cell centres ``(..., 2)``."""
        return self.origin + self.cell * np.asarray(ij, dtype=float)

    def in_bounds(self, ij: ArrayLike) -> np.ndarray:
        """Whether integer indices lie inside the grid."""
        ij = np.asarray(ij)
        return (ij[..., 0] >= 0) & (ij[..., 0] < self.shape[0]) & (ij[..., 1] >= 0) & (ij[..., 1] < self.shape[1])

    def _flat_index(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Index into the flattened padded grid for cells in ``[-3, shape + 3)`` (the occupied border)."""
        return i * self._width + j + self._offset

    def _occupied_ij(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Occupancy of integer cells; anything outside the grid is occupied."""
        return self._flat[self._flat_index(i, j)]

    def is_occupied(self, xy: ArrayLike) -> np.ndarray:
        """Occupancy of world points ``(..., 2)``; points outside the grid (or NaN) are occupied."""
        p = np.asarray(xy, dtype=float)
        if p.shape[-1:] != (2,):
            raise ShapeError(f"points must have shape (..., 2), got {p.shape}")
        p = np.where(np.isfinite(p), p, -1e9)
        i = np.floor(self._u1(p[..., 0], 0)).astype(np.int64)
        j = np.floor(self._u1(p[..., 1], 1)).astype(np.int64)
        return self._occupied_ij(i, j)

    def is_free(self, xy: ArrayLike) -> np.ndarray:
        """``~is_occupied(xy)``."""
        return ~self.is_occupied(xy)

    @property
    def free_fraction(self) -> float:
        """Fraction of free cells."""
        return float(self._free_idx.size / self.occupied.size)

    # ------------------------------------------------------------- sampling
    def sample_free(self, n: int, rng: np.random.Generator) -> Array:
        """``n`` points drawn uniformly over the free area (uniform free cell, uniform inside it)."""
        if self._free_idx.size == 0:
            raise ValidationError("the grid has no free cell")
        k = self._free_idx[rng.integers(0, self._free_idx.size, size=int(n))]
        ij = np.column_stack(np.unravel_index(k, self.shape))
        return self.cell_to_world(ij) + (rng.random((int(n), 2)) - 0.5) * self.cell

    # --------------------------------------------------------- segment test
    def _u1(self, v: Array, ax: int) -> Array:
        """Continuous cell coordinate along ``ax`` (cell ``i`` covers ``[i, i + 1)``), clipped to ``[-2, n + 2]``."""
        u = v - (self.origin[ax] - 0.5 * self.cell)
        u *= 1.0 / self.cell
        np.maximum(u, -2.0, out=u)
        np.minimum(u, self.shape[ax] + 2.0, out=u)
        return u

    def segment_blocked(self, p0: ArrayLike, p1: ArrayLike) -> np.ndarray:
        """For segments ``p0[k] -> p1[k]`` (``(N, 2)`` each): does segment ``k`` enter an occupied cell?

        Includes the start and end cells. Exact (see the module docstring) and
        vectorized: four look-ups per segment, plus work proportional to the number of
        cell boundaries crossed by the segments whose bounding box holds an obstacle.
        """
        a = np.asarray(p0, dtype=float)
        b = np.asarray(p1, dtype=float)
        if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
            raise ShapeError(f"p0 and p1 must both have shape (N, 2), got {a.shape} and {b.shape}")
        # Work on contiguous per-axis vectors: row-wise (N, 2) operations are slow in numpy.
        ax0, ay0, bx, by = (np.ascontiguousarray(c) for c in (a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
        ux0, uy0 = self._u1(ax0, 0), self._u1(ay0, 1)
        ux1, uy1 = self._u1(bx, 0), self._u1(by, 1)
        ix0, iy0 = np.floor(ux0).astype(np.int64), np.floor(uy0).astype(np.int64)
        ix1, iy1 = np.floor(ux1).astype(np.int64), np.floor(uy1).astype(np.int64)
        # A segment stays inside the index rectangle spanned by its end cells: if that
        # rectangle holds no occupied cell (summed-area table), the segment is free.
        i0 = np.minimum(ix0, ix1) + self._PAD
        i1 = np.maximum(ix0, ix1) + (self._PAD + 1)
        j0 = np.minimum(iy0, iy1) + self._PAD
        j1 = np.maximum(iy0, iy1) + (self._PAD + 1)
        i0 *= self._sat_width
        i1 *= self._sat_width
        sat = self._sat
        count = sat[i1 + j1]
        count -= sat[i0 + j1]
        count -= sat[i1 + j0]
        count += sat[i0 + j0]
        blocked = np.zeros(a.shape[0], dtype=bool)
        k = np.flatnonzero(count)
        if k.size:
            blocked[k] = self._blocked_exact(ux0[k], uy0[k], ix0[k], iy0[k], ux1[k], uy1[k])
        return blocked

    def _blocked_exact(self, ux0: Array, uy0: Array, ix0: np.ndarray, iy0: np.ndarray,
                       ux1: Array, uy1: Array) -> np.ndarray:
        """Exact cell traversal of segments given in continuous cell coordinates.

        Every visited cell after the start cell is entered through exactly one cell
        boundary. Along axis ``ax`` the ``s``-th boundary crossed (``s = 1 .. n_ax``)
        leads into index ``i0 + s`` (moving up; the boundary is at ``u = i0 + s``) or
        ``i0 - s`` (moving down; boundary at ``u = i0 - s + 1``); the index along the
        other axis is the floor of the segment's other coordinate at that boundary. The
        crossings of all segments are listed in one flat array (``np.repeat``), so the
        work is proportional to the total number of crossings.
        """
        ix1, iy1 = np.floor(ux1).astype(np.int64), np.floor(uy1).astype(np.int64)
        blocked = self._occupied_ij(ix0, iy0)
        blocked |= self._occupied_ij(ix1, iy1)
        nx, ny = np.abs(ix1 - ix0), np.abs(iy1 - iy0)
        # Moves within a cell or into a 4-neighbour visit only the start and end cells.
        todo = np.flatnonzero(~blocked & ((nx + ny > 1) | ((nx == 1) & (ny == 1))))
        if todo.size == 0:
            return blocked
        n = todo.size
        hit = np.zeros(n, dtype=np.int64)
        axes = ((ux0[todo], ux1[todo], ix0[todo], nx[todo], uy0[todo], uy1[todo], 0),
                (uy0[todo], uy1[todo], iy0[todo], ny[todo], ux0[todo], ux1[todo], 1))
        for u0, u1, i0, cnt, v0, v1, ax in axes:
            total = int(cnt.sum())
            if total == 0:
                continue
            seg = np.repeat(np.arange(n), cnt)
            step = np.arange(1, total + 1) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            du = u1 - u0
            down = du < 0
            with np.errstate(divide="ignore", invalid="ignore"):  # du = 0 only where cnt = 0
                slope = (v1 - v0) / du
            step[down[seg]] *= -1  # signed step
            idx = i0[seg] + step  # entered index along ax
            w = (i0 + down - u0)[seg]  # boundary - start = (i0 + down - u0) + step
            w += step
            w *= slope[seg]
            w += v0[seg]
            jo = np.floor(w).astype(np.int64)
            occ = self._occupied_ij(idx, jo) if ax == 0 else self._occupied_ij(jo, idx)
            hit += np.bincount(seg[occ], minlength=n)
        blocked[todo] |= hit > 0
        return blocked
