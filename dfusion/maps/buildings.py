r"""Synthetic buildings for tests, examples and scenario files.

:func:`rooms`, :func:`corridor` and :func:`repetitive_corridor` draw occupancy grids
(outside unknown, inside free, walls occupied), deterministic for a given ``seed``. They
are the map generators a scenario file names with ``map = "rooms"`` and so on
(``docs/robots.md``).
"""
from __future__ import annotations

import math

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.maps.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
from dfusion.maps.lattice import NodeLattice

__all__ = ["rooms", "corridor", "repetitive_corridor", "obstacle_grid", "GENERATORS"]


def _canvas(width: float, height: float, resolution: float, pad: float) -> tuple[np.ndarray, float]:
    W = int(round((width + 2 * pad) / resolution))
    H = int(round((height + 2 * pad) / resolution))
    return np.full((H, W), UNKNOWN, dtype=np.int16), pad


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


def rooms(
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
) -> OccupancyGrid:
    """A building of ``rooms_x x rooms_y`` rooms joined by doors, with box obstacles.

    The building's interior spans world ``[0, width] x [0, height]``; walls of
    thickness ``wall`` surround it and separate the rooms; every internal wall has one
    door of width ``door`` at a random position, and ``obstacles`` boxes (0.3..0.9 m)
    are placed at random, so the map has no symmetry. Outside is unknown.
    """
    rng = np.random.default_rng(seed)
    res = float(resolution)
    data, pad = _canvas(width, height, res, wall + 0.5)
    f = lambda *a: _fill(data, res, pad, *a)  # noqa: E731
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
    return OccupancyGrid(data, res, (-pad, -pad, 0.0))


def corridor(
    length: float = 20.0,
    width: float = 2.0,
    *,
    resolution: float = 0.05,
    wall: float = 0.15,
    openings: int = 5,
    opening_width: float = 1.0,
    opening_depth: float = 1.5,
    seed: int = 0,
) -> OccupancyGrid:
    """A straight corridor ``[0, length] x [0, width]`` with side openings.

    ``openings`` door-like recesses (``opening_width`` wide, ``opening_depth`` deep) are
    placed at random positions on random sides, which makes places distinguishable.
    """
    rng = np.random.default_rng(seed)
    res = float(resolution)
    data, pad = _canvas(length, width + 2 * opening_depth, res, wall + 0.5)
    off = opening_depth
    f = lambda x0, y0, x1, y1, v: _fill(data, res, pad, x0, y0 + off, x1, y1 + off, v)  # noqa: E731
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
    return OccupancyGrid(data, res, (-pad, -pad - off, 0.0))


def repetitive_corridor(
    length: float = 30.0,
    width: float = 2.0,
    *,
    period: float = 3.0,
    alcove_width: float = 1.0,
    alcove_depth: float = 0.8,
    resolution: float = 0.05,
    wall: float = 0.15,
) -> OccupancyGrid:
    """A corridor with identical alcoves every ``period`` metres on both sides.

    The map is periodic along x (only the two ends break the symmetry), the kind of
    repetitive environment in which global localization is ambiguous (Zhang et al.,
    "Infrastructure-Free Global Localization in Repetitive Environments: An Overview").
    Deterministic: no random elements.
    """
    res = float(resolution)
    data, pad = _canvas(length, width + 2 * alcove_depth, res, wall + 0.5)
    off = alcove_depth
    f = lambda x0, y0, x1, y1, v: _fill(data, res, pad, x0, y0 + off, x1, y1 + off, v)  # noqa: E731
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
    return OccupancyGrid(data, res, (-pad, -pad - off, 0.0))


def obstacle_grid(obstacles: list, bounds: Array, cell: float) -> NodeLattice:
    """A :class:`NodeLattice` over ``bounds = (x_min, y_min, x_max, y_max)`` with square cells.

    A cell is occupied when its square overlaps the interior of one of the
    rectangles ``[x_min, y_min, x_max, y_max]``.
    """
    x0, y0, x1, y1 = bounds
    nx, ny = int(math.floor((x1 - x0) / cell)) + 1, int(math.floor((y1 - y0) / cell)) + 1
    xs = x0 + cell * np.arange(nx)
    ys = y0 + cell * np.arange(ny)
    occ = np.zeros((nx, ny), dtype=bool)
    for r in obstacles:
        a, b, c, d = r
        ix = (xs + cell / 2 > a) & (xs - cell / 2 < c)
        iy = (ys + cell / 2 > b) & (ys - cell / 2 < d)
        occ |= ix[:, None] & iy[None, :]
    return NodeLattice(occ, cell, (x0, y0))


#: The generators by the name a scenario file gives them.
GENERATORS = {"rooms": rooms, "corridor": corridor, "repetitive_corridor": repetitive_corridor}
