"""A robot wandering through a seeded rooms map (shared by the MCL and recovery tests)."""
from __future__ import annotations

import math

import numpy as np

from dfusion.geometry import se2_between, se2_compose, wrap_angle
from dfusion.maps import OccupancyGrid, cast_rays


def wander_path(grid: OccupancyGrid, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` poses from (2, 2, 0): 15 cm steps with heading jitter, turning away from walls."""
    p = np.array([2.0, 2.0, 0.0])
    path = [p.copy()]
    while len(path) < n:
        look = cast_rays(grid, p[None], [0.0, 0.5, -0.5], 10.0)[0]
        if look[0] < 0.8:
            p[2] = wrap_angle(p[2] + (0.5 if look[1] > look[2] else -0.5))
        else:
            p[2] = wrap_angle(p[2] + rng.normal(0, 0.05))
            p[:2] += 0.15 * np.array([math.cos(p[2]), math.sin(p[2])])
        path.append(p.copy())
    return np.array(path)


def drifting_odometry(path: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Odometry of ``path`` in an unrelated frame, each increment perturbed by (1 cm, 5 mm, 0.01 rad)."""
    odo = [np.array([5.0, -3.0, 1.0])]
    for k in range(1, len(path)):
        d = se2_between(path[k - 1], path[k]) + rng.normal(0, [0.01, 0.005, 0.01])
        odo.append(se2_compose(odo[-1], d))
    return np.array(odo)
