r"""Occupancy grid maps in the ROS ``map_server`` convention.

Layout
------
``data[i, j]`` (``int8``) is the cell in row ``i`` (along the map's ``y`` axis) and
column ``j`` (along ``x``), exactly as in a ROS ``nav_msgs/OccupancyGrid``: row 0 is the
*bottom* row, at the map origin. Values are ROS occupancy values: ``0`` free, ``100``
occupied, ``-1`` unknown, ``1..99`` an occupancy probability in percent (only maps loaded
with ``mode: scale`` have those). A cell counts as *occupied* when its value is
``>= 100 * occupied_thresh`` and as *free* when it is in ``0 .. 100 * free_thresh``.

Frames
------
``origin = (x0, y0, yaw)`` is the pose of the lower-left corner of cell ``(0, 0)`` in the
world (map_server's definition). The *grid frame* is that corner's frame, in metres:
cell ``(i, j)`` covers ``[j r, (j + 1) r) x [i r, (i + 1) r)`` with ``r`` the resolution;
``world = (x0, y0) + Rot(yaw) grid``. Every method that takes world coordinates converts
them; ``yaw`` may be non-zero (many ROS tools ignore it; this class does not).

Map constraint (particle motion)
--------------------------------
:meth:`OccupancyGrid.is_blocked` (points) and :meth:`OccupancyGrid.segment_blocked`
(straight moves, exact grid traversal, vectorized) treat occupied cells, unknown cells
(``unknown_blocks=True``) and everything off the map as blocking;
:meth:`OccupancyGrid.sample_free` draws points uniformly over the free cells. The WSN
particle filter (:class:`dfusion.localization.WSNTracker`) uses them;
:class:`dfusion.maps.NodeLattice` is a node-lattice view of this class (x-first indexing,
node-centred origin) for the BLE RSSI dataset's ``.occ`` grids
(:func:`dfusion.maps.io.read_occ`, :meth:`OccupancyGrid.from_nodes`).

Related modules
---------------
Map files (map_server YAML + image, ``.occ`` node grids) are read and written by
:mod:`dfusion.maps.io`; :mod:`dfusion.maps.mapping` builds a grid from scans at known
poses; :mod:`dfusion.maps.buildings` draws synthetic buildings; :mod:`dfusion.maps.raycast`
casts rays.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import NonFiniteError, ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array

__all__ = ["OccupancyGrid", "FREE", "OCCUPIED", "UNKNOWN"]

#: ROS occupancy values.
FREE, OCCUPIED, UNKNOWN = 0, 100, -1



def distance_transform_edt(mask: np.ndarray) -> Array:
    """:func:`scipy.ndimage.distance_transform_edt` (imported on first use: only maps with a
    distance field need scipy, not every node program that reads a grid)."""
    from scipy.ndimage import distance_transform_edt as edt

    return edt(mask)


# ----------------------------------------------------------------------------------------
# OccupancyGrid
# ----------------------------------------------------------------------------------------
def _as_origin(origin: ArrayLike) -> Array:
    o = np.array(origin, dtype=float).reshape(-1)
    if o.shape == (2,):
        o = np.append(o, 0.0)
    if o.shape != (3,):
        raise ShapeError(f"map origin must be (x, y) or (x, y, yaw), got {np.shape(origin)}")
    if not np.all(np.isfinite(o)):
        raise NonFiniteError("map origin contains NaN or inf")
    return o


class OccupancyGrid:
    """A 2-D occupancy grid (ROS map_server layout, see the module docstring).

    Parameters
    ----------
    data : (H, W) int array
        ROS occupancy values: 0 free, 100 occupied, -1 unknown, 1..99 probability (%).
    resolution : float
        Cell size (m), ``> 0``.
    origin : (x, y) or (x, y, yaw)
        World pose of the lower-left corner of cell ``(0, 0)``.
    occupied_thresh, free_thresh : float
        Probability thresholds (as in map_server) classifying cells with values 1..99.
    """

    def __init__(
        self,
        data: ArrayLike,
        resolution: float,
        origin: ArrayLike = (0.0, 0.0, 0.0),
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.196,
    ) -> None:
        d = np.array(data)
        if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
            raise ShapeError(f"occupancy data must be a non-empty 2-D array, got shape {d.shape}")
        if not np.issubdtype(d.dtype, np.number) and d.dtype != bool:
            raise ValidationError("occupancy data must be numeric")
        if d.dtype == bool:
            d = np.where(d, OCCUPIED, FREE)
        if np.any((d < -1) | (d > 100)):
            raise ValidationError("occupancy values must be -1 (unknown) or 0..100")
        res = float(resolution)
        if not (np.isfinite(res) and res > 0):
            raise ValidationError(f"resolution must be positive and finite, got {resolution!r}")
        if not (0.0 <= free_thresh < occupied_thresh <= 1.0):
            raise ValidationError(
                f"need 0 <= free_thresh < occupied_thresh <= 1, got {free_thresh}, {occupied_thresh}"
            )
        self._data = d.astype(np.int8)
        self._data.setflags(write=False)
        self.resolution = res
        self.origin = _as_origin(origin)
        self.occupied_thresh = float(occupied_thresh)
        self.free_thresh = float(free_thresh)
        self._cache: dict[str, Any] = {}

    # -- basic properties --------------------------------------------------------------
    def __repr__(self) -> str:
        h, w = self.shape
        return (
            f"OccupancyGrid({w}x{h} cells, resolution={self.resolution}, "
            f"origin={tuple(np.round(self.origin, 6))})"
        )

    @property
    def data(self) -> np.ndarray:
        """Read-only ``(H, W)`` int8 ROS occupancy values (row 0 at the origin)."""
        return self._data

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: rows (along y) and columns (along x)."""
        return self._data.shape  # type: ignore[return-value]

    @property
    def height(self) -> int:
        return self._data.shape[0]

    @property
    def width(self) -> int:
        return self._data.shape[1]

    @property
    def size(self) -> tuple[float, float]:
        """Map extent ``(width_m, height_m)`` in metres."""
        return self.width * self.resolution, self.height * self.resolution

    def cached(self, key: str, build: Callable[[], Any]) -> Any:
        """``build()``, computed once per grid and kept under ``key`` (for tables derived
        from the grid by other modules, such as the ray caster's distance field; the grid's
        cells must not change afterwards)."""
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    @property
    def occupied(self) -> np.ndarray:
        """Boolean ``(H, W)``: cells with value ``>= 100 * occupied_thresh``."""
        if "occupied" not in self._cache:
            m = self._data >= 100.0 * self.occupied_thresh
            m.setflags(write=False)
            self._cache["occupied"] = m
        return self._cache["occupied"]

    @property
    def free(self) -> np.ndarray:
        """Boolean ``(H, W)``: cells with value in ``0 .. 100 * free_thresh``."""
        if "free" not in self._cache:
            m = (self._data >= 0) & (self._data <= 100.0 * self.free_thresh)
            m.setflags(write=False)
            self._cache["free"] = m
        return self._cache["free"]

    @property
    def unknown(self) -> np.ndarray:
        """Boolean ``(H, W)``: neither free nor occupied."""
        return ~(self.occupied | self.free)

    def blocking(self, unknown_blocks: bool = True) -> np.ndarray:
        """Cells that stop a laser ray: occupied, and unknown ones if ``unknown_blocks``."""
        return self.occupied | self.unknown if unknown_blocks else self.occupied

    # -- frames ------------------------------------------------------------------------
    def world_to_grid(self, points: ArrayLike) -> Array:
        """World ``(..., 2)`` points to grid-frame metres (cell ``(i, j)`` at ``[j r, i r]``)."""
        p = np.asarray(points, dtype=float)
        if p.shape[-1] != 2:
            raise ShapeError(f"points must have shape (..., 2), got {p.shape}")
        d = p - self.origin[:2]
        c, s = math.cos(self.origin[2]), math.sin(self.origin[2])
        return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)

    def grid_to_world(self, points: ArrayLike) -> Array:
        """Inverse of :meth:`world_to_grid`."""
        p = np.asarray(points, dtype=float)
        c, s = math.cos(self.origin[2]), math.sin(self.origin[2])
        return np.stack(
            [c * p[..., 0] - s * p[..., 1] + self.origin[0], s * p[..., 0] + c * p[..., 1] + self.origin[1]],
            axis=-1,
        )

    def pose_to_grid(self, poses: ArrayLike) -> Array:
        """World poses ``(..., 3)`` to grid-frame poses (heading relative to the grid x axis)."""
        q = np.asarray(poses, dtype=float)
        if q.shape[-1] != 3:
            raise ShapeError(f"poses must have shape (..., 3), got {q.shape}")
        xy = self.world_to_grid(q[..., :2])
        th = q[..., 2] - self.origin[2]
        if self.origin[2] != 0.0:
            th = wrap_angle(th)
        return np.concatenate([xy, th[..., None]], axis=-1)

    def world_to_cell(self, points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices ``(i, j)`` of the cells containing world points (may be outside)."""
        g = self.world_to_grid(points) / self.resolution
        return np.floor(g[..., 1]).astype(np.int64), np.floor(g[..., 0]).astype(np.int64)

    def cell_to_world(self, i: ArrayLike, j: ArrayLike) -> Array:
        """World coordinates of the centres of cells ``(i, j)``."""
        i = np.asarray(i, dtype=float)
        j = np.asarray(j, dtype=float)
        g = np.stack([(j + 0.5) * self.resolution, (i + 0.5) * self.resolution], axis=-1)
        return self.grid_to_world(g)

    def in_bounds(self, i: ArrayLike, j: ArrayLike) -> np.ndarray:
        i = np.asarray(i)
        j = np.asarray(j)
        return (i >= 0) & (i < self.height) & (j >= 0) & (j < self.width)

    def is_free(self, points: ArrayLike) -> np.ndarray:
        """True for world points inside a free cell (points outside the map are not free)."""
        i, j = self.world_to_cell(points)
        ok = self.in_bounds(i, j)
        out = np.zeros(i.shape, dtype=bool)
        out[ok] = self.free[i[ok], j[ok]]
        return out

    def value_at(self, points: ArrayLike, outside: int = UNKNOWN) -> np.ndarray:
        """Occupancy values at world points (``outside`` for points off the map)."""
        i, j = self.world_to_cell(points)
        ok = self.in_bounds(i, j)
        out = np.full(i.shape, outside, dtype=np.int16)
        out[ok] = self._data[i[ok], j[ok]]
        return out

    # -- map constraint: point and segment tests ---------------------------------------
    #: Width of the blocking border added around the grid for the point and segment tests.
    _PAD = 3

    def _constraint_tables(self, unknown_blocks: bool) -> dict[str, Any]:
        """Padded flat blocking mask and its summed-area table (cached per ``unknown_blocks``).

        The blocking mask (occupied cells, and unknown ones if ``unknown_blocks``) gets a
        blocking border of ``_PAD`` cells, so that a lookup of any cell in
        ``[-_PAD, n + _PAD)`` along each axis is a plain index: everything off the map
        blocks. The summed-area table gives the number of blocking cells in any index
        rectangle with four look-ups.
        """
        key = f"_constraint_{bool(unknown_blocks)}"
        tab = self._cache.get(key)
        if tab is None:
            P = self._PAD
            blk = self.blocking(unknown_blocks)
            H, W = blk.shape
            padded = np.ones((H + 2 * P, W + 2 * P), dtype=bool)
            padded[P:-P, P:-P] = blk
            sat = np.zeros((H + 2 * P + 1, W + 2 * P + 1), dtype=np.int32)
            sat[1:, 1:] = np.cumsum(np.cumsum(padded, axis=0, dtype=np.int32), axis=1, dtype=np.int32)
            tab = {
                "flat": padded.ravel(),
                "width": W + 2 * P,
                "offset": P * (W + 2 * P) + P,
                "sat": sat.ravel(),
                "sat_width": W + 2 * P + 1,
                "ulim": (W + 2.0, H + 2.0),
            }
            self._cache[key] = tab
        return tab

    def _u1(self, g: Array, ax: int) -> Array:
        """Continuous cell coordinate (cell ``k`` covers ``[k, k + 1)``) of grid-frame metres ``g``
        along axis ``ax`` (0 = x = columns, 1 = y = rows), clipped to ``[-2, n + 2]``."""
        u = np.multiply(g, 1.0 / self.resolution)
        np.maximum(u, -2.0, out=u)
        np.minimum(u, float(self.width if ax == 0 else self.height) + 2.0, out=u)
        return u

    def _grid_xy(self, points: Array) -> tuple[Array, Array]:
        """Grid-frame coordinates of world points ``(N, 2)`` as two contiguous vectors."""
        if self.origin[2] == 0.0:
            return points[:, 0] - self.origin[0], points[:, 1] - self.origin[1]
        g = self.world_to_grid(points)
        return np.ascontiguousarray(g[:, 0]), np.ascontiguousarray(g[:, 1])

    def _blocked_cells(self, ix: np.ndarray, iy: np.ndarray, tab: dict[str, Any]) -> np.ndarray:
        """Blocking state of integer cells (column ``ix``, row ``iy``), each in ``[-_PAD, n + _PAD)``."""
        return tab["flat"][iy * tab["width"] + ix + tab["offset"]]

    def is_blocked(self, points: ArrayLike, unknown_blocks: bool = True) -> np.ndarray:
        """True for world points ``(..., 2)`` in a blocking cell, off the map, or NaN.

        Blocking cells are the occupied ones and, with ``unknown_blocks`` (default), the
        unknown ones: the motion constraint of :meth:`segment_blocked`.
        """
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (2,):
            raise ShapeError(f"points must have shape (..., 2), got {p.shape}")
        shape = p.shape[:-1]
        q = p.reshape(-1, 2)
        q = np.where(np.isfinite(q), q, -1e9)
        gx, gy = self._grid_xy(q)
        tab = self._constraint_tables(unknown_blocks)
        ix = np.floor(self._u1(gx, 0)).astype(np.int64)
        iy = np.floor(self._u1(gy, 1)).astype(np.int64)
        return self._blocked_cells(ix, iy, tab).reshape(shape)

    def sample_free(self, n: int, rng: np.random.Generator | int | None = None) -> Array:
        """``n`` world points ``(n, 2)`` uniform over the free cells.

        A free cell is drawn uniformly (cells enumerated column by column, i.e. x-major:
        the node-lattice order of the BLE grids, kept so that seeded draws did not change
        when the grid classes were merged), then a
        point uniformly inside it.
        """
        rng = np.random.default_rng(rng)
        n = int(n)
        if "free_xmajor" not in self._cache:
            fj, fi = np.nonzero(self.free.T)
            self._cache["free_xmajor"] = (fi, fj)
        fi, fj = self._cache["free_xmajor"]
        if fi.size == 0:
            raise ValidationError("the map has no free cell")
        k = rng.integers(0, fi.size, size=n)
        u = rng.random((n, 2))
        g = np.empty((n, 2))
        g[:, 0] = (fj[k] + u[:, 0]) * self.resolution
        g[:, 1] = (fi[k] + u[:, 1]) * self.resolution
        return self.grid_to_world(g)

    def segment_blocked(self, p0: ArrayLike, p1: ArrayLike, unknown_blocks: bool = True) -> np.ndarray:
        r"""For segments ``p0[k] -> p1[k]`` (world, ``(N, 2)`` each): does segment ``k`` enter a
        blocking cell (occupied, unknown if ``unknown_blocks``, or off the map)?

        The start and end cells count. Exact: every cell the segment visits after its start
        cell is entered through exactly one cell boundary, a vertical grid line or a
        horizontal one; the entered cell is known from the boundary's index and the
        segment's other coordinate where it crosses that line (the grid traversal of
        Amanatides & Woo, Eurographics 1987, computed for all segments at once). A segment
        that only touches a cell at a corner point does not enter it.

        Two shortcuts keep it fast without changing the answer: a segment stays inside the
        rectangle of cells spanned by its two end cells, so if the summed-area table says
        that rectangle holds no blocking cell the segment is free (four look-ups); a segment
        that crosses at most one boundary visits only its end cells. The crossings of the
        remaining segments are listed in one flat array, so the work is proportional to
        their number. (This is the map constraint of the WSN particle filter,
        :class:`dfusion.localization.WSNTracker`.)
        """
        a = np.asarray(p0, dtype=float)
        b = np.asarray(p1, dtype=float)
        if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
            raise ShapeError(f"p0 and p1 must both have shape (N, 2), got {a.shape} and {b.shape}")
        tab = self._constraint_tables(unknown_blocks)
        ax0, ay0 = self._grid_xy(a)
        bx, by = self._grid_xy(b)
        ux0, uy0 = self._u1(ax0, 0), self._u1(ay0, 1)
        ux1, uy1 = self._u1(bx, 0), self._u1(by, 1)
        ix0, iy0 = np.floor(ux0).astype(np.int64), np.floor(uy0).astype(np.int64)
        ix1, iy1 = np.floor(ux1).astype(np.int64), np.floor(uy1).astype(np.int64)
        P = self._PAD
        sw = tab["sat_width"]
        r0 = (np.minimum(iy0, iy1) + P) * sw
        r1 = (np.maximum(iy0, iy1) + (P + 1)) * sw
        c0 = np.minimum(ix0, ix1) + P
        c1 = np.maximum(ix0, ix1) + (P + 1)
        sat = tab["sat"]
        count = sat[r1 + c1]
        count -= sat[r0 + c1]
        count -= sat[r1 + c0]
        count += sat[r0 + c0]
        blocked = np.zeros(a.shape[0], dtype=bool)
        k = np.flatnonzero(count)
        if k.size:
            blocked[k] = self._blocked_exact(ux0[k], uy0[k], ix0[k], iy0[k], ux1[k], uy1[k], unknown_blocks)
        return blocked

    def _blocked_exact(self, ux0: Array, uy0: Array, ix0: np.ndarray, iy0: np.ndarray,
                       ux1: Array, uy1: Array, unknown_blocks: bool = True) -> np.ndarray:
        """Exact cell traversal of segments given in continuous cell coordinates (x, y).

        Along axis ``ax`` the ``s``-th boundary crossed (``s = 1 .. n_ax``) leads into index
        ``i0 + s`` (moving up; the boundary is at ``u = i0 + s``) or ``i0 - s`` (moving
        down; boundary at ``u = i0 - s + 1``); the index along the other axis is the floor
        of the segment's other coordinate at that boundary.
        """
        tab = self._constraint_tables(unknown_blocks)
        ix1, iy1 = np.floor(ux1).astype(np.int64), np.floor(uy1).astype(np.int64)
        blocked = self._blocked_cells(ix0, iy0, tab)
        blocked |= self._blocked_cells(ix1, iy1, tab)
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
            occ = self._blocked_cells(idx, jo, tab) if ax == 0 else self._blocked_cells(jo, idx, tab)
            hit += np.bincount(seg[occ], minlength=n)
        blocked[todo] |= hit > 0
        return blocked

    # -- derived fields ----------------------------------------------------------------
    def distance_field(self) -> Array:
        """Euclidean distance (m) from each cell centre to the nearest occupied cell centre.

        Computed once with :func:`scipy.ndimage.distance_transform_edt` and cached
        (read-only); occupied cells have distance 0. A map without occupied cells gives
        ``inf`` everywhere.
        """
        if "edt" not in self._cache:
            occ = self.occupied
            if occ.any():
                from scipy.ndimage import (
                    distance_transform_edt,  # here: only maps with a distance field need scipy
                )

                d = distance_transform_edt(~occ) * self.resolution
            else:
                d = np.full(self.shape, np.inf)
            d.setflags(write=False)
            self._cache["edt"] = d
        return self._cache["edt"]

    def surface_distance_field(self) -> Array:
        """Approximate distance (m) from each cell centre to the nearest obstacle *surface*.

        The surface is the boundary between occupied and *free* cells (the face of a wall
        a laser in free space can see; the face towards unknown space does not count).
        For a non-occupied cell the value is ``d_occ - r/2`` (``d_occ`` as in
        :meth:`distance_field`), for an occupied cell ``d_free - r/2`` with ``d_free`` the
        distance to the nearest free cell centre: exact for axis-aligned walls, never
        negative. Unlike :meth:`distance_field` it grows again inside thick obstacles, so
        a point deep inside (or behind) a wall is not mistaken for a point on it. Cached,
        read-only.
        """
        if "surface" not in self._cache:
            occ = self.occupied
            half = 0.5 * self.resolution
            if occ.any() and self.free.any():
                d_in = distance_transform_edt(~self.free) * self.resolution
                d = np.where(occ, d_in, self.distance_field()) - half
                np.maximum(d, 0.0, out=d)
            else:
                d = np.full(self.shape, np.inf)
            d.setflags(write=False)
            self._cache["surface"] = d
        return self._cache["surface"]

    def occupied_points(self, boundary_only: bool = True) -> Array:
        """World coordinates ``(K, 2)`` of occupied cell centres.

        With ``boundary_only`` only occupied cells with a free 4-neighbour are returned
        (the wall surfaces a laser can see), which is what scan matching needs.
        """
        occ = self.occupied
        if boundary_only:
            f = self.free
            nb = np.zeros_like(occ)
            nb[1:, :] |= f[:-1, :]
            nb[:-1, :] |= f[1:, :]
            nb[:, 1:] |= f[:, :-1]
            nb[:, :-1] |= f[:, 1:]
            occ = occ & nb
        i, j = np.nonzero(occ)
        return self.cell_to_world(i, j)

    def free_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of all free cells."""
        if "free_ij" not in self._cache:
            self._cache["free_ij"] = np.nonzero(self.free)
        return self._cache["free_ij"]

    def sample_free_poses(self, n: int, rng: np.random.Generator | int | None = None) -> Array:
        """``n`` world poses uniform over the free area, headings uniform in ``[-pi, pi)``.

        A free cell is chosen uniformly, then a position uniformly inside it: together a
        uniform density over the union of free cells.
        """
        rng = np.random.default_rng(rng)
        n = int(n)
        fi, fj = self.free_cells()
        if fi.size == 0:
            raise ValidationError("the map has no free cell")
        k = rng.integers(0, fi.size, size=n)
        g = np.empty((n, 2))
        g[:, 0] = (fj[k] + rng.random(n)) * self.resolution
        g[:, 1] = (fi[k] + rng.random(n)) * self.resolution
        th = rng.uniform(-np.pi, np.pi, size=n)
        out = np.empty((n, 3))
        out[:, :2] = self.grid_to_world(g)
        out[:, 2] = wrap_angle(th + self.origin[2])
        return out




    # -- node lattices ----------------------------------------------------------------
    @classmethod
    def from_nodes(cls, occupied: ArrayLike, cell: float, node_origin: ArrayLike = (0.0, 0.0)) -> "OccupancyGrid":
        """A grid from a boolean node lattice indexed ``occupied[ix, iy]`` (x first).

        Node ``(ix, iy)`` is the centre of a cell at world ``node_origin + cell (ix, iy)``;
        the returned grid has ``data[iy, ix]`` (ROS layout) occupied (100) or free (0),
        resolution ``cell`` and origin ``node_origin - cell / 2`` (the lower-left corner of
        the first cell), yaw 0.
        """
        occ = np.array(occupied, dtype=bool)
        if occ.ndim != 2 or min(occ.shape) < 1:
            raise ShapeError(f"occupied must be a non-empty 2-D array, got shape {occ.shape}")
        c = float(cell)
        if not (np.isfinite(c) and c > 0):
            raise ValidationError(f"cell size must be positive, got {cell}")
        org = np.array(node_origin, dtype=float).reshape(-1)
        if org.shape != (2,) or not np.all(np.isfinite(org)):
            raise ShapeError(f"node_origin must be 2 finite numbers, got {node_origin!r}")
        data = np.where(occ.T, OCCUPIED, FREE)
        return cls(data, c, (org[0] - 0.5 * c, org[1] - 0.5 * c, 0.0))
