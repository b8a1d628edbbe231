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

File format (``load`` / ``save``)
---------------------------------
ROS map_server YAML + image, as documented at http://wiki.ros.org/map_server: keys
``image``, ``resolution``, ``origin``, ``negate``, ``occupied_thresh``, ``free_thresh`` and
optional ``mode`` (``trinary`` default, ``scale``, ``raw``). A pixel of grey level ``v``
(0..255) has occupancy probability ``p = (255 - v) / 255`` (``p = v / 255`` when
``negate: 1``); ``p > occupied_thresh`` -> 100, ``p < free_thresh`` -> 0, otherwise -1
(``trinary``) or ``1 + 98 (p - free) / (occ - free)`` (``scale``); ``raw`` stores ``v``.
The image's top row is the map's last row (the image is flipped). PGM (P2/P5, 8 or 16 bit)
is read and written natively; other formats (PNG, ...) are read through Pillow when it is
installed. ``save`` writes the map_saver convention: free 254, occupied 0, unknown 205.
The YAML subset needed here (``key: value`` lines, numbers, strings, flow lists ``[a, b]``,
``#`` comments) is parsed by :func:`parse_simple_yaml`; no YAML library is required.

Generated maps
--------------
:meth:`OccupancyGrid.rooms`, :meth:`OccupancyGrid.corridor` and
:meth:`OccupancyGrid.repetitive_corridor` draw synthetic buildings (outside unknown, inside
free, walls occupied), deterministic for a given ``seed``.

Map constraint (particle motion)
--------------------------------
:meth:`OccupancyGrid.is_blocked` (points) and :meth:`OccupancyGrid.segment_blocked`
(straight moves, exact grid traversal, vectorized) treat occupied cells, unknown cells
(``unknown_blocks=True``) and everything off the map as blocking;
:meth:`OccupancyGrid.sample_free` draws points uniformly over the free cells. The WSN
particle filter (:class:`dfusion.pf.WSNTracker`) uses them; ``dfusion.pf.OccupancyGrid``
is only a node-lattice view of this class (x-first indexing, node-centred origin), kept
for the BLE RSSI dataset's ``.occ`` grids (:meth:`OccupancyGrid.from_occ_file`,
:meth:`OccupancyGrid.from_nodes`).

Maps from scans
---------------
:meth:`OccupancyGrid.from_scans` runs the log-odds occupancy-grid mapping algorithm with
known poses (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, table 9.1) with a
simple inverse sensor model (table 9.2): every cell a beam passes through before its end
point gets ``l_free``, the end-point cell of a beam shorter than ``max_range`` gets
``l_occ``. Each cell is counted at most once per beam.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import distance_transform_edt

from ..errors import NonFiniteError, ShapeError, ValidationError
from ..models.base import Array, wrap_angle

__all__ = ["OccupancyGrid", "parse_simple_yaml", "read_pgm", "write_pgm", "FREE", "OCCUPIED", "UNKNOWN"]

#: ROS occupancy values.
FREE, OCCUPIED, UNKNOWN = 0, 100, -1


# ----------------------------------------------------------------------------------------
# Minimal YAML and PGM support
# ----------------------------------------------------------------------------------------
def _yaml_scalar(text: str) -> Any:
    s = text.strip()
    if not s:
        return None
    if len(s) >= 2 and s[0] == s[-1] and s[0] in "'\"":
        return s[1:-1]
    low = s.lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    if low in ("null", "~"):
        return None
    try:
        return int(s)
    except ValueError:
        pass
    try:
        return float(s)
    except ValueError:
        return s


def _strip_comment(line: str) -> str:
    """Remove a ``#`` comment that is not inside quotes."""
    quote = None
    for k, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (k == 0 or line[k - 1].isspace()):
            return line[:k]
    return line


def parse_simple_yaml(text: str) -> dict[str, Any]:
    """Parse the flat YAML subset used by map_server files.

    Supports one ``key: value`` per line, scalars (int, float, bool, quoted or bare
    strings) and flow lists ``[a, b, c]`` of scalars; ``#`` starts a comment. Anything
    else (nesting, block lists, multi-line values) raises :class:`ValidationError`.
    """
    out: dict[str, Any] = {}
    for n, raw in enumerate(text.splitlines(), 1):
        line = _strip_comment(raw).rstrip()
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        if line[0].isspace() or ":" not in line:
            raise ValidationError(f"unsupported YAML on line {n}: {raw!r}")
        key, _, value = line.partition(":")
        key = key.strip().strip("'\"")
        value = value.strip()
        if value.startswith("["):
            if not value.endswith("]"):
                raise ValidationError(f"unterminated flow list on line {n}: {raw!r}")
            inner = value[1:-1].strip()
            out[key] = [_yaml_scalar(v) for v in inner.split(",")] if inner else []
        elif value.startswith("{") or value.startswith("- ") or value in ("|", ">"):
            raise ValidationError(f"unsupported YAML value on line {n}: {raw!r}")
        else:
            out[key] = _yaml_scalar(value)
    return out


def read_pgm(path: str | Path) -> np.ndarray:
    """Read a PGM image (P5 binary or P2 ASCII, maxval up to 65535) as a 2-D array.

    Row 0 is the top row of the image. 16-bit binary samples are big-endian (Netpbm).
    """
    data = Path(path).read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos : pos + 1] == b"#":
            while pos < len(data) and data[pos : pos + 1] not in (b"\n", b"\r"):
                pos += 1
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace() and data[pos : pos + 1] != b"#":
            pos += 1
        if start == pos:
            raise ValidationError(f"{path}: truncated PGM header")
        tokens.append(data[start:pos])
    magic = tokens[0]
    if magic not in (b"P5", b"P2"):
        raise ValidationError(f"{path}: not a PGM file (magic {magic!r})")
    try:
        width, height, maxval = (int(t) for t in tokens[1:4])
    except ValueError:
        raise ValidationError(f"{path}: bad PGM header {tokens!r}") from None
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise ValidationError(f"{path}: bad PGM size or maxval ({width}, {height}, {maxval})")
    if magic == b"P5":
        pos += 1  # exactly one whitespace byte after maxval
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
        n = width * height
        buf = data[pos : pos + n * dtype.itemsize]
        if len(buf) < n * dtype.itemsize:
            raise ValidationError(f"{path}: PGM pixel data truncated")
        img = np.frombuffer(buf, dtype=dtype, count=n).reshape(height, width)
    else:
        vals = data[pos:].split()
        if len(vals) < width * height:
            raise ValidationError(f"{path}: PGM pixel data truncated")
        img = np.array([int(v) for v in vals[: width * height]]).reshape(height, width)
    img = img.astype(np.int64)
    if maxval != 255:  # map_server works on 8-bit grey levels
        img = np.rint(img * (255.0 / maxval)).astype(np.int64)
    return img


def write_pgm(path: str | Path, image: ArrayLike) -> None:
    """Write an 8-bit binary PGM (P5); ``image[0]`` is the top row."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ShapeError(f"PGM image must be 2-D, got shape {img.shape}")
    if img.min(initial=0) < 0 or img.max(initial=0) > 255:
        raise ValidationError("PGM image values must be in 0..255")
    h, w = img.shape
    header = f"P5\n# dfusion\n{w} {h}\n255\n".encode("ascii")
    Path(path).write_bytes(header + np.ascontiguousarray(img, dtype=np.uint8).tobytes())


def _read_image(path: Path) -> np.ndarray:
    """Grey levels 0..255 (top row first) of a PGM or, through Pillow, any image."""
    if path.suffix.lower() in (".pgm", ".pnm"):
        return read_pgm(path)
    try:
        from PIL import Image  # noqa: PLC0415  (optional dependency)
    except ImportError:  # pragma: no cover
        raise ValidationError(f"{path}: only PGM can be read without Pillow") from None
    with Image.open(path) as im:
        if im.mode in ("RGBA", "LA"):
            arr = np.asarray(im.convert("RGBA"), dtype=np.float64)
            grey = arr[..., :3].mean(axis=2)
            # map_server: pixels with alpha < 255 become unknown
            grey[arr[..., 3] < 255] = np.nan
            return grey
        if im.mode not in ("L", "I", "I;16"):
            im = im.convert("RGB")
            return np.asarray(im, dtype=np.float64).mean(axis=2).round()
        return np.asarray(im, dtype=np.float64)


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
        the order of the former ``dfusion.pf`` grid, so seeded draws are unchanged), then a
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
        :class:`dfusion.pf.WSNTracker`.)
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

    # -- file I/O ----------------------------------------------------------------------
    @classmethod
    def load(cls, yaml_path: str | Path) -> "OccupancyGrid":
        """Load a ROS map_server map (YAML + image; see the module docstring)."""
        yaml_path = Path(yaml_path)
        meta = parse_simple_yaml(yaml_path.read_text())
        for key in ("image", "resolution", "origin"):
            if key not in meta:
                raise ValidationError(f"{yaml_path}: missing key {key!r}")
        image_path = Path(str(meta["image"]))
        if not image_path.is_absolute():
            image_path = yaml_path.parent / image_path
        negate = bool(int(meta.get("negate", 0)))
        occ_th = float(meta.get("occupied_thresh", 0.65))
        free_th = float(meta.get("free_thresh", 0.196))
        mode = str(meta.get("mode", "trinary")).lower()
        if mode not in ("trinary", "scale", "raw"):
            raise ValidationError(f"{yaml_path}: unknown mode {mode!r}")
        grey = _read_image(image_path)
        data = cls._grey_to_occupancy(grey, negate, occ_th, free_th, mode)
        origin = meta["origin"]
        if not isinstance(origin, list) or len(origin) not in (2, 3):
            raise ValidationError(f"{yaml_path}: origin must be a list [x, y, yaw]")
        return cls(data[::-1], float(meta["resolution"]), [float(v) for v in origin], occ_th, free_th)

    @staticmethod
    def _grey_to_occupancy(grey: np.ndarray, negate: bool, occ_th: float, free_th: float, mode: str) -> np.ndarray:
        g = np.asarray(grey, dtype=np.float64)
        nan = np.isnan(g)
        g = np.where(nan, 0.0, g)
        if negate:
            g = 255.0 - g
        if mode == "raw":
            out = np.clip(g, -1, 100).astype(np.int16)
            out[g > 100] = UNKNOWN
            out[nan] = UNKNOWN
            return out
        p = (255.0 - g) / 255.0
        out = np.full(g.shape, UNKNOWN, dtype=np.int16)
        if mode == "scale":
            ratio = (p - free_th) / (occ_th - free_th)
            out = np.rint(1.0 + 98.0 * ratio).astype(np.int16)
        out[p > occ_th] = OCCUPIED
        out[p < free_th] = FREE
        out[nan] = UNKNOWN
        return out

    def save(self, yaml_path: str | Path, image_name: str | None = None) -> Path:
        """Write the map as map_saver does (trinary PGM + YAML); returns the image path.

        Free cells are written as 254, occupied as 0 and everything else as 205, so that
        ``load`` gives back the same free/occupied/unknown classification.
        """
        yaml_path = Path(yaml_path)
        image_name = image_name or yaml_path.with_suffix(".pgm").name
        img = np.full(self.shape, 205, dtype=np.uint8)
        img[self.free] = 254
        img[self.occupied] = 0
        image_path = yaml_path.parent / image_name
        write_pgm(image_path, img[::-1])
        x, y, yaw = (float(v) for v in self.origin)
        yaml_path.write_text(
            f"image: {image_name}\n"
            f"resolution: {self.resolution!r}\n"
            f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
            f"negate: 0\n"
            f"occupied_thresh: {self.occupied_thresh!r}\n"
            f"free_thresh: {self.free_thresh!r}\n"
        )
        return image_path

    # -- node lattices (the BLE RSSI dataset's .occ grids) -----------------------------
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

    @classmethod
    def from_occ_file(cls, path: str | Path, occupied_value: int = 1) -> "OccupancyGrid":
        """Read a ``.occ`` node grid of the BLE RSSI dataset (Danis et al.).

        Format: line 1 ``[[x_min, y_min], [x_max, y_max]]::cell``; every other line
        ``[x, y]::v``, one per node, in any order; node ``(x, y)`` is the centre of a
        ``cell`` x ``cell`` square (see :meth:`from_nodes`). ``occupied_value`` is the
        value that marks an obstacle: the dataset's own README says 1 = traversable, but
        the data show the reverse (tracks run on 0-nodes, tables and the border are 1), so
        1 = occupied is the default. Raises :class:`ValidationError` on a malformed file,
        a missing or duplicated node, or a node off the lattice.
        """
        import json  # noqa: PLC0415

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
        return cls.from_nodes(occ, cell, (x0, y0))

    # -- maps from laser scans ---------------------------------------------------------
    @classmethod
    def from_scans(
        cls,
        poses: ArrayLike,
        ranges: ArrayLike,
        angles: ArrayLike,
        resolution: float = 0.05,
        max_range: float = 30.0,
        *,
        bounds: tuple[float, float, float, float] | None = None,
        margin: float = 1.0,
        l_occ: float = 0.85,
        l_free: float = -0.4,
        l_clamp: float = 10.0,
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.196,
    ) -> "OccupancyGrid":
        """Occupancy-grid mapping with known poses (log odds; see the module docstring).

        Parameters
        ----------
        poses : (S, 3)
            World poses of the laser for each scan.
        ranges : (S, B)
            Ranges (m); values ``>= max_range`` (or non-finite) are "no return": the beam
            clears cells up to ``max_range`` and marks nothing occupied.
        angles : (B,)
            Beam angles in the laser frame (rad).
        bounds : (xmin, xmax, ymin, ymax), optional
            Map extent; by default the bounding box of poses and end points plus ``margin``.
        l_occ, l_free : float
            Log-odds increments of the inverse sensor model; ``l_clamp`` bounds the total.
        """
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        ranges = np.asarray(ranges, dtype=float)
        if ranges.ndim == 1:
            ranges = ranges[None, :]
        angles = np.asarray(angles, dtype=float).reshape(-1)
        if ranges.shape != (poses.shape[0], angles.size):
            raise ShapeError(f"ranges must have shape {(poses.shape[0], angles.size)}, got {ranges.shape}")
        res = float(resolution)
        hit = np.isfinite(ranges) & (ranges < max_range) & (ranges > 0)
        r = np.where(hit, ranges, max_range)
        ang = poses[:, 2:3] + angles[None, :]
        ex = poses[:, 0:1] + r * np.cos(ang)
        ey = poses[:, 1:2] + r * np.sin(ang)
        if bounds is None:
            xs = np.concatenate([poses[:, 0], ex[hit]])
            ys = np.concatenate([poses[:, 1], ey[hit]])
            bounds = (xs.min() - margin, xs.max() + margin, ys.min() - margin, ys.max() + margin)
        xmin, xmax, ymin, ymax = (float(b) for b in bounds)
        W = int(math.ceil((xmax - xmin) / res))
        H = int(math.ceil((ymax - ymin) / res))
        if W < 1 or H < 1:
            raise ValidationError(f"empty map bounds {bounds}")
        logodds = np.zeros(H * W)
        step = 0.5 * res
        for s in range(poses.shape[0]):  # one scan at a time keeps memory bounded
            rs = r[s]
            n_steps = int(math.ceil(rs.max() / step)) + 1
            t = np.arange(n_steps) * step
            px = poses[s, 0] + t[None, :] * np.cos(ang[s])[:, None]
            py = poses[s, 1] + t[None, :] * np.sin(ang[s])[:, None]
            j = np.floor((px - xmin) / res).astype(np.int64)
            i = np.floor((py - ymin) / res).astype(np.int64)
            # end-point cells of beams with a return
            ej = np.floor((ex[s] - xmin) / res).astype(np.int64)
            ei = np.floor((ey[s] - ymin) / res).astype(np.int64)
            valid = (t[None, :] < rs[:, None]) & (i >= 0) & (i < H) & (j >= 0) & (j < W)
            cell = i * W + j
            endcell = np.where(hit[s], ei * W + ej, -1)
            valid &= cell != endcell[:, None]
            beam = np.broadcast_to(np.arange(rs.size)[:, None], cell.shape)
            key = np.unique(beam[valid].astype(np.int64) * (H * W) + cell[valid])
            np.add.at(logodds, key % (H * W), l_free)
            ok = hit[s] & (ei >= 0) & (ei < H) & (ej >= 0) & (ej < W)
            np.add.at(logodds, (ei * W + ej)[ok], l_occ)
            np.clip(logodds, -l_clamp, l_clamp, out=logodds)
        lo = logodds.reshape(H, W)
        data = np.full((H, W), UNKNOWN, dtype=np.int16)
        data[lo > math.log(occupied_thresh / (1 - occupied_thresh))] = OCCUPIED
        data[lo < math.log(free_thresh / (1 - free_thresh))] = FREE
        return cls(data, res, (xmin, ymin, 0.0), occupied_thresh, free_thresh)

    # -- generated maps ----------------------------------------------------------------
    @staticmethod
    def _canvas(width: float, height: float, resolution: float, pad: float) -> tuple[np.ndarray, float]:
        W = int(round((width + 2 * pad) / resolution))
        H = int(round((height + 2 * pad) / resolution))
        return np.full((H, W), UNKNOWN, dtype=np.int16), pad

    @staticmethod
    def _fill(data: np.ndarray, res: float, pad: float, x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        """Set cells whose centres lie in the world rectangle ``[x0, x1] x [y0, y1]``."""
        xa, xb = sorted((x0, x1))
        ya, yb = sorted((y0, y1))
        j0 = int(math.ceil((xa + pad) / res - 0.5 - 1e-9))
        j1 = int(math.floor((xb + pad) / res - 0.5 + 1e-9))
        i0 = int(math.ceil((ya + pad) / res - 0.5 - 1e-9))
        i1 = int(math.floor((yb + pad) / res - 0.5 + 1e-9))
        H, W = data.shape
        j0, i0 = max(j0, 0), max(i0, 0)
        j1, i1 = min(j1, W - 1), min(i1, H - 1)
        if j1 >= j0 and i1 >= i0:
            data[i0 : i1 + 1, j0 : j1 + 1] = value

    @classmethod
    def rooms(
        cls,
        width: float = 16.0,
        height: float = 10.0,
        rooms_x: int = 3,
        rooms_y: int = 2,
        *,
        resolution: float = 0.05,
        wall: float = 0.15,
        door: float = 1.0,
        obstacles: int = 8,
        seed: int = 0,
    ) -> "OccupancyGrid":
        """A building of ``rooms_x x rooms_y`` rooms joined by doors, with box obstacles.

        The building's interior spans world ``[0, width] x [0, height]``; walls of
        thickness ``wall`` surround it and separate the rooms; every internal wall has one
        door of width ``door`` at a random position, and ``obstacles`` boxes (0.3..0.9 m)
        are placed at random, so the map has no symmetry. Outside is unknown.
        """
        rng = np.random.default_rng(seed)
        res = float(resolution)
        data, pad = cls._canvas(width, height, res, wall + 0.5)
        f = lambda *a: cls._fill(data, res, pad, *a)  # noqa: E731
        f(-wall, -wall, width + wall, height + wall, OCCUPIED)
        f(0, 0, width, height, FREE)
        dx, dy = width / rooms_x, height / rooms_y
        for a in range(1, rooms_x):  # vertical walls with one door per room row
            x = a * dx
            f(x - wall / 2, 0, x + wall / 2, height, OCCUPIED)
            for b in range(rooms_y):
                c = rng.uniform(b * dy + door / 2 + wall, (b + 1) * dy - door / 2 - wall)
                f(x - wall, c - door / 2, x + wall, c + door / 2, FREE)
        for b in range(1, rooms_y):
            y = b * dy
            f(0, y - wall / 2, width, y + wall / 2, OCCUPIED)
            for a in range(rooms_x):
                c = rng.uniform(a * dx + door / 2 + wall, (a + 1) * dx - door / 2 - wall)
                f(c - door / 2, y - wall, c + door / 2, y + wall, FREE)
        for _ in range(obstacles):
            sx, sy = rng.uniform(0.3, 0.9, size=2)
            cx = rng.uniform(sx, width - sx)
            cy = rng.uniform(sy, height - sy)
            f(cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2, OCCUPIED)
        return cls(data, res, (-pad, -pad, 0.0))

    @classmethod
    def corridor(
        cls,
        length: float = 20.0,
        width: float = 2.0,
        *,
        resolution: float = 0.05,
        wall: float = 0.15,
        openings: int = 5,
        opening_width: float = 1.0,
        opening_depth: float = 1.5,
        seed: int = 0,
    ) -> "OccupancyGrid":
        """A straight corridor ``[0, length] x [0, width]`` with side openings.

        ``openings`` door-like recesses (``opening_width`` wide, ``opening_depth`` deep) are
        placed at random positions on random sides, which makes places distinguishable.
        """
        rng = np.random.default_rng(seed)
        res = float(resolution)
        data, pad = cls._canvas(length, width + 2 * opening_depth, res, wall + 0.5)
        off = opening_depth
        f = lambda x0, y0, x1, y1, v: cls._fill(data, res, pad, x0, y0 + off, x1, y1 + off, v)  # noqa: E731
        f(-wall, -wall, length + wall, width + wall, OCCUPIED)
        f(0, 0, length, width, FREE)
        # one opening per equal segment of the corridor, so openings never overlap
        seg = (length - 2.0) / max(openings, 1)
        if openings and seg < opening_width + 2 * wall + 0.1:
            raise ValidationError("too many openings for the corridor length")
        xs = 1.0 + seg * np.arange(openings) + rng.uniform(wall, seg - opening_width - wall, size=openings)
        for x in xs:
            if rng.random() < 0.5:
                f(x - wall, -opening_depth - wall, x + opening_width + wall, 0, OCCUPIED)
                f(x, -opening_depth, x + opening_width, 0.01, FREE)
            else:
                f(x - wall, width, x + opening_width + wall, width + opening_depth + wall, OCCUPIED)
                f(x, width - 0.01, x + opening_width, width + opening_depth, FREE)
        return cls(data, res, (-pad, -pad - off, 0.0))

    @classmethod
    def repetitive_corridor(
        cls,
        length: float = 30.0,
        width: float = 2.0,
        *,
        period: float = 3.0,
        alcove_width: float = 1.0,
        alcove_depth: float = 0.8,
        resolution: float = 0.05,
        wall: float = 0.15,
    ) -> "OccupancyGrid":
        """A corridor with identical alcoves every ``period`` metres on both sides.

        The map is periodic along x (only the two ends break the symmetry), the kind of
        repetitive environment in which global localization is ambiguous (Zhang et al.'s
        survey, 001 in the seeds). Deterministic: no random elements.
        """
        res = float(resolution)
        data, pad = cls._canvas(length, width + 2 * alcove_depth, res, wall + 0.5)
        off = alcove_depth
        f = lambda x0, y0, x1, y1, v: cls._fill(data, res, pad, x0, y0 + off, x1, y1 + off, v)  # noqa: E731
        f(-wall, -wall, length + wall, width + wall, OCCUPIED)
        f(0, 0, length, width, FREE)
        x = period / 2 - alcove_width / 2
        while x + alcove_width <= length - 0.5:
            for y0, y1, c0, c1 in (
                (-alcove_depth - wall, 0, -alcove_depth, 0.01),
                (width, width + alcove_depth + wall, width - 0.01, width + alcove_depth),
            ):
                f(x - wall, y0, x + alcove_width + wall, y1, OCCUPIED)
                f(x, c0, x + alcove_width, c1, FREE)
            x += period
        return cls(data, res, (-pad, -pad - off, 0.0))
