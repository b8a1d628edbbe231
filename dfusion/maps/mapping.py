r"""Occupancy-grid mapping with known poses.

:func:`grid_from_scans` runs the log-odds occupancy-grid mapping algorithm with known
poses (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, table 9.1) with a simple
inverse sensor model (table 9.2): every cell a beam passes through before its end point
gets ``l_free``, the end-point cell of a beam shorter than ``max_range`` gets ``l_occ``.
Each cell is counted at most once per beam; the log odds are clamped to ``+-l_clamp``.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.maps.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

__all__ = ["grid_from_scans"]


def grid_from_scans(
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
) -> OccupancyGrid:
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
    return OccupancyGrid(data, res, (xmin, ymin, 0.0), occupied_thresh, free_thresh)
