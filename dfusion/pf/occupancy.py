r"""A small 2-D occupancy grid for map-constrained particle motion.

The grid holds one boolean per *node* ``(i, j)`` at world position
``origin + (i * cell, j * cell)``; node ``(i, j)`` owns the square cell
``[x_i - cell/2, x_i + cell/2) x [y_j - cell/2, y_j + cell/2)`` centred on it.
Everything outside the grid counts as occupied.

The segment test (:meth:`OccupancyGrid.segment_blocked`) is exact: it finds,
for every segment at once, the parameters ``t`` at which the segment crosses
a cell boundary (the vertical lines ``x = x_i + cell/2`` and the horizontal
lines ``y = y_j + cell/2``), sorts them, and checks the cell that contains the
midpoint of each piece between consecutive crossings: these are exactly the
cells the segment passes through (Amanatides & Woo, "A fast voxel traversal
algorithm for ray tracing", Eurographics 1987, done for all segments at once
with padded numpy arrays instead of a loop). A segment that only touches a
cell at a single corner point does not count as entering it.
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
        # Padded copy: a one-cell occupied border makes out-of-grid lookups a plain index.
        self._padded = np.ones((occ.shape[0] + 2, occ.shape[1] + 2), dtype=bool)
        self._padded[1:-1, 1:-1] = occ
        self._flat = self._padded.ravel()
        self._free_idx = np.flatnonzero(~occ.ravel())

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

    def _occupied_ij(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        # Clip into the padded border (which is occupied) and index the flat array.
        i = np.clip(i + 1, 0, self.shape[0] + 1)
        j = np.clip(j + 1, 0, self.shape[1] + 1)
        return self._flat[i * (self.shape[1] + 2) + j]

    def is_occupied(self, xy: ArrayLike) -> np.ndarray:
        """Occupancy of world points ``(..., 2)``; points outside the grid are occupied."""
        p = np.asarray(xy, dtype=float)
        u = (p - self.origin) / self.cell + 0.5
        # floor of huge or non-finite values: treat as outside
        u = np.where(np.isfinite(u), u, -1.0)
        ij = np.floor(np.clip(u, -2.0, np.array(self.shape) + 2.0)).astype(np.int64)
        return self._occupied_ij(ij[..., 0], ij[..., 1])

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
    def segment_blocked(self, p0: ArrayLike, p1: ArrayLike) -> np.ndarray:
        """For segments ``p0[k] -> p1[k]`` (``(N, 2)`` each): does segment ``k`` enter an occupied cell?

        Includes the start and end cells. Exact (see the module docstring), fully
        vectorized; the work is ``N x (crossings of the longest segment)``.
        """
        a = np.asarray(p0, dtype=float)
        b = np.asarray(p1, dtype=float)
        if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
            raise ShapeError(f"p0 and p1 must both have shape (N, 2), got {a.shape} and {b.shape}")
        if a.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        lim = np.array(self.shape, dtype=float) + 2.0
        ua = np.clip((a - self.origin) / self.cell + 0.5, -2.0, lim)  # cell i covers u in [i, i + 1)
        ub = np.clip((b - self.origin) / self.cell + 0.5, -2.0, lim)
        fa = np.floor(ua)
        fb = np.floor(ub)
        blocked = self._occupied_ij(fa[:, 0].astype(np.int64), fa[:, 1].astype(np.int64))
        blocked |= self._occupied_ij(fb[:, 0].astype(np.int64), fb[:, 1].astype(np.int64))
        ncross = np.abs(fb - fa).astype(np.int64)  # boundaries crossed per axis
        multi = ~blocked & (ncross.sum(axis=1) > 0)
        if not np.any(multi):
            return blocked
        k = np.flatnonzero(multi)
        ua, ub, fa, fb, nc = ua[k], ub[k], fa[k], fb[k], ncross[k]
        du = ub - ua
        ts = []
        for ax in (0, 1):
            m = int(nc[:, ax].max())
            if m == 0:
                continue
            step = np.arange(1, m + 1)
            # boundaries between fa and fb: fa + s (moving up) or fa + 1 - s (moving down)
            up = du[:, ax] > 0
            bnd = np.where(up[:, None], fa[:, ax, None] + step, fa[:, ax, None] + 1.0 - step)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (bnd - ua[:, ax, None]) / du[:, ax, None]
            t = np.where(step <= nc[:, ax, None], t, 1.0)  # padding repeats the end point
            ts.append(t)
        t = np.concatenate([np.zeros((len(k), 1)), *ts, np.ones((len(k), 1))], axis=1)
        t.sort(axis=1)
        mid = 0.5 * (t[:, :-1] + t[:, 1:])
        pts = ua[:, None, :] + mid[..., None] * du[:, None, :]
        ij = np.floor(pts).astype(np.int64)
        hit = self._occupied_ij(ij[..., 0], ij[..., 1]).any(axis=1)
        blocked[k] = hit
        return blocked
