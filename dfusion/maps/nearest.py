r"""Nearest point of a fixed 2-D point set by a lookup grid (scan matching, the similarity rate)."""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import distance_transform_edt

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import rotation
from dfusion.linalg import Array

__all__ = ["NearestPointGrid"]

class NearestPointGrid:
    """Approximate nearest point of a fixed 2-D point set, by a lookup table over a grid.

    Every cell of a grid (``resolution`` metres, lower-left corner ``origin``, rotated by
    ``yaw``, ``shape = (nx, ny)`` cells) stores the point whose own cell is nearest to it
    (:func:`scipy.ndimage.distance_transform_edt` with ``return_indices``, computed once).
    A query returns that point for the cell containing it, and the exact distance to it:
    within one cell diagonal of the true nearest neighbour (a k-d tree is exact and
    several times slower for scan-sized queries). Queries off the grid use the nearest
    border cell.

    Parameters
    ----------
    points : (M, 2)
        The point set.
    resolution : float
        Cell size (m).
    origin : (2,), optional
        World position of the grid's lower-left corner; default: the points' bounding
        box lowered by ``margin``.
    shape : (nx, ny), optional
        Cells along x and y; default: the bounding box plus ``margin`` on each side.
    cells : ((M,), (M,)) int arrays, optional
        The cell ``(ix, iy)`` of each point, when it is not the one containing it (an
        occupancy grid's wall cells, say); default: the cell containing each point.
    yaw : float
        Rotation of the grid's axes in the world (rad).
    margin : float
        Room around the points when ``origin`` / ``shape`` are not given (m).
    """

    MAX_CELLS = 50_000_000

    def __init__(self, points: ArrayLike, resolution: float, *, origin: ArrayLike | None = None,
                 shape: tuple[int, int] | None = None, cells: tuple[np.ndarray, np.ndarray] | None = None,
                 yaw: float = 0.0, margin: float = 0.0) -> None:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1:
            raise ShapeError(f"points must be (M, 2) with M >= 1, got {p.shape}")
        res = float(resolution)
        if not (res > 0 and math.isfinite(res) and margin >= 0):
            raise ValidationError("resolution must be positive and margin >= 0")
        self.points = p
        self.resolution = res
        self.yaw = float(yaw)
        self._rot = rotation(-self.yaw) if self.yaw else None
        if origin is None:
            origin = self._to_grid_frame(p, np.zeros(2)).min(axis=0) - margin
        self.origin = np.asarray(origin, dtype=float).reshape(2)
        local = self._to_grid_frame(p, self.origin) / res
        if shape is None:
            shape = tuple(int(v) for v in np.floor(local.max(axis=0) + margin / res).astype(int) + 1)
        nx, ny = int(shape[0]), int(shape[1])
        if nx * ny > self.MAX_CELLS:
            raise ValidationError(f"grid of {nx} x {ny} cells is too large: raise the resolution")
        if cells is None:
            ix, iy = np.floor(local).astype(np.intp).T
        else:
            ix, iy = (np.asarray(c, dtype=np.intp) for c in cells)
        ix, iy = np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1)
        owner = np.full((nx, ny), -1, dtype=np.int64)
        owner[ix, iy] = np.arange(p.shape[0])
        _, (ox, oy) = distance_transform_edt(owner < 0, return_indices=True)
        self._owner = owner[ox, oy].reshape(-1)
        self._shape = (nx, ny)

    def _to_grid_frame(self, q: Array, origin: Array) -> Array:
        d = q - origin
        return d if self._rot is None else d @ self._rot.T

    def nearest(self, queries: ArrayLike) -> tuple[Array, np.ndarray]:
        """``(squared distance, index)`` of the stored point for each query point ``(N, 2)``."""
        q = np.asarray(queries, dtype=float)
        g = self._to_grid_frame(q, self.origin) * (1.0 / self.resolution)
        nx, ny = self._shape
        ix = np.clip(np.floor(g[:, 0]), 0, nx - 1).astype(np.intp)
        iy = np.clip(np.floor(g[:, 1]), 0, ny - 1).astype(np.intp)
        idx = self._owner[ix * ny + iy]
        diff = q - self.points[idx]
        diff *= diff
        return diff[:, 0] + diff[:, 1], idx
