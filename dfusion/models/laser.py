r"""Planar laser range finders: the scanner's geometry and the scan likelihoods.

* :class:`LaserConfig` -- beam angles, range limits and mounting pose of a laser.
* :class:`BeamErfcModel` -- the URUS beam likelihood (Sanfeliu et al., sec. 8.1)::

      L = (1 / N_L) sum_j erfc(|z_j - zhat_j| / (sigma sqrt 2))

  with ``zhat_j`` the range ray-cast in the map from the particle along beam ``j``.
  The paper prints the argument without the absolute value; taken literally
  (``two_sided=False``) ``erfc`` of a negative argument is up to 2, so particles that
  expect *longer* ranges than measured everywhere are preferred (open space wins).
  With ``|.|`` (default) ``erfc(|d| / (sigma sqrt 2))`` is the probability that Gaussian
  range noise is at least as large as the observed discrepancy: 1 for a perfect beam,
  in ``[0, 1]``. The per-beam terms are averaged, not multiplied, which makes the
  model robust to unmodelled obstacles and keeps ``L`` on the same scale for every
  scan. Expected ranges come from a :class:`~dfusion.maps.RayCastTable` (default) or
  exact ray casting (``raycast="exact"``); see the measured costs in
  ``docs/localization.md``.
* :class:`LikelihoodFieldModel` -- Thrun, Burgard & Fox, *Probabilistic Robotics*,
  2005, table 6.3 (the model of ROS AMCL's ``likelihood_field``): every beam end point
  ``e`` scores ``z_hit N(dist(e); 0, sigma_hit^2) + z_rand / z_max`` with ``dist`` the
  distance to the nearest occupied cell; beams at maximum range are skipped; the scan
  likelihood is the product over beams. The per-cell log-likelihood is precomputed from
  the distance field, so a particle costs one table lookup per beam.

  ``exponent`` (both models) raises the likelihood to a power (``< 1`` tempers the
  over-confidence of treating correlated beams as independent).
* :class:`LaserScanSensor` -- the ranges a planar laser would measure in an occupancy
  grid, as a :class:`~dfusion.models.MeasurementModel` (for simulated worlds and the
  centralized reference).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import erfc

from dfusion.errors import NotInitializedError, ValidationError
from dfusion.geometry import heading_of, se2_compose
from dfusion.linalg import Array, as_positive, as_vector
from dfusion.maps.grid import OccupancyGrid
from dfusion.maps.raycast import RayCastTable, cast_rays
from dfusion.models.base import MeasurementModel

__all__ = ["LaserConfig", "BeamErfcModel", "LikelihoodFieldModel", "LaserScanSensor", "laser_grid_poses"]


@dataclass(frozen=True)
class LaserConfig:
    """A planar laser range finder.

    Attributes
    ----------
    angles : (B,) array
        Beam angles in the laser frame (rad, counter-clockwise, 0 = laser x axis).
    max_range : float
        Maximum range (m); readings ``>= max_range`` mean "no return".
    min_range : float
        Readings below this (m) are ignored.
    offset : (3,) array
        Pose of the laser in the robot frame ``(x, y, theta)``.
    """

    angles: Array
    max_range: float
    min_range: float = 0.0
    offset: Array = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        a = np.asarray(self.angles, dtype=float).reshape(-1)
        if a.size == 0 or not np.all(np.isfinite(a)):
            raise ValidationError("laser angles must be a non-empty finite vector")
        object.__setattr__(self, "angles", a)
        mr = float(self.max_range)
        if not (np.isfinite(mr) and mr > 0):
            raise ValidationError(f"max_range must be positive and finite, got {self.max_range}")
        object.__setattr__(self, "max_range", mr)
        object.__setattr__(self, "min_range", float(self.min_range))
        object.__setattr__(self, "offset", as_vector(self.offset, 3, "laser offset"))

    @classmethod
    def uniform(cls, n: int, fov: float, max_range: float, **kw) -> "LaserConfig":
        """``n`` beams evenly spread over ``[-fov/2, fov/2]`` (both ends included; for a full
        circle ``fov = 2 pi`` the last beam is dropped so no direction is duplicated)."""
        if fov >= 2 * math.pi - 1e-12:
            angles = np.linspace(-math.pi, math.pi, int(n), endpoint=False)
        else:
            angles = np.linspace(-fov / 2, fov / 2, int(n))
        return cls(angles, max_range, **kw)


def laser_grid_poses(grid: OccupancyGrid, particles: Array, offset: Array) -> Array:
    """Poses of a laser mounted at ``offset`` (robot frame) on robots at ``particles`` (world
    frame, ``(N, 3)``), in the grid frame of ``grid``."""
    if np.any(offset != 0.0):
        particles = se2_compose(particles, offset)
    return grid.pose_to_grid(particles)


class BeamErfcModel:
    """URUS beam likelihood ``L = mean_j erfc(|z_j - zhat_j| / (sigma sqrt 2))``.

    Parameters
    ----------
    sigma : float
        Laser range noise ``sigma_1`` (m).
    two_sided : bool
        Use ``|z - zhat|`` (default); ``False`` uses the signed ``z - zhat`` as printed in the
        URUS paper (see the module docstring).
    exponent : float
        The likelihood is raised to this power.
    raycast : ``"table"`` or ``"exact"``
        Expected ranges from a precomputed :class:`RayCastTable` or from :func:`cast_rays`.
    theta_bins : int
        Heading bins of the table.
    unknown_blocks : bool
        Unknown cells stop rays (ROS AMCL convention).
    """

    def __init__(
        self,
        sigma: float = 0.1,
        *,
        two_sided: bool = True,
        exponent: float = 1.0,
        raycast: Literal["table", "exact"] = "table",
        theta_bins: int = 360,
        unknown_blocks: bool = True,
    ) -> None:
        self.sigma = float(sigma)
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise ValidationError(f"sigma must be positive, got {sigma}")
        self.two_sided = bool(two_sided)
        self.exponent = float(exponent)
        if raycast not in ("table", "exact"):
            raise ValidationError(f"raycast must be 'table' or 'exact', got {raycast!r}")
        self.raycast = raycast
        self.theta_bins = int(theta_bins)
        self.unknown_blocks = bool(unknown_blocks)
        self.grid: OccupancyGrid | None = None
        self.table: RayCastTable | None = None

    def prepare(self, grid: OccupancyGrid, max_range: float, table: RayCastTable | None = None) -> None:
        """Bind to a map; builds (or adopts) the ray-cast table and the erfc lookup."""
        self.grid = grid
        self.max_range = float(max_range)
        if self.raycast == "table":
            if table is not None and (table.grid is not grid or table.max_range != self.max_range):
                raise ValidationError("the ray-cast table was built for another map or max_range")
            self.table = table or RayCastTable(
                grid, self.max_range, self.theta_bins, unknown_blocks=self.unknown_blocks
            )
            unit = self.table.unit
            # erfc on the integer range difference (units of the table): exact up to 1 unit
            self._dmax = int(math.ceil(8.0 * self.sigma / unit))
            k = np.arange(-self._dmax, self._dmax + 1) * unit
            arg = (np.abs(k) if self.two_sided else k) / (self.sigma * math.sqrt(2.0))
            self._erfc_lut = erfc(arg).astype(np.float32)

    def log_likelihood(self, laser_grid_poses: Array, z: Array, angles: Array) -> tuple[Array, int]:
        """``(log L per particle, 1)`` for grid-frame laser poses, ranges ``z`` and angles."""
        if self.grid is None:
            raise NotInitializedError("BeamErfcModel.prepare was not called")
        zc = np.minimum(z, self.max_range)
        if self.raycast == "table":
            t = self.table
            zq = np.rint(zc / t.unit).astype(np.intp) + self._dmax
            zhat = t.lookup_quantized(laser_grid_poses, angles)
            d = np.subtract(zq[None, :], zhat, dtype=np.intp)  # z - zhat + dmax
            np.clip(d, 0, 2 * self._dmax, out=d)
            L = self._erfc_lut[d].sum(axis=1).astype(np.float64) / z.size
        else:
            world = self.grid.grid_to_world(laser_grid_poses[:, :2])
            poses = np.column_stack([world, laser_grid_poses[:, 2] + self.grid.origin[2]])
            zhat = cast_rays(self.grid, poses, angles, self.max_range, unknown_blocks=self.unknown_blocks)
            diff = zc[None, :] - zhat
            if self.two_sided:
                diff = np.abs(diff)
            L = erfc(diff / (self.sigma * math.sqrt(2.0))).mean(axis=1)
        with np.errstate(divide="ignore"):
            return self.exponent * np.log(np.maximum(L, 1e-300)), 1


class LikelihoodFieldModel:
    """Likelihood field (Thrun et al. 2005, table 6.3) with a precomputed log table.

    Parameters
    ----------
    sigma_hit : float
        Standard deviation (m) of the end-point distance.
    z_hit, z_rand : float
        Mixture weights of the Gaussian and the uniform term (``z_rand / max_range``).
    max_distance : float
        Distances are capped here (m); end points off the map count as this far (as ROS
        AMCL's ``laser_likelihood_max_dist``, default 2 m).
    exponent : float
        The likelihood is raised to this power.
    surface : bool
        Measure distances to the obstacle surface
        (:meth:`~dfusion.maps.OccupancyGrid.surface_distance_field`, default) instead of to
        the nearest occupied cell centre (Thrun et al., ROS AMCL). With the latter, end
        points anywhere inside a thick wall score as well as end points on its surface,
        which pulls the estimate into walls (measured: 9 cm mean error on a map with
        15 cm walls, against 2 cm with ``surface=True``; ``docs/localization.md``).
    beam_skip : bool
        Leave out the beams that the particle set as a whole does not explain (ROS AMCL's
        ``do_beamskip``, ``amcl_laser.cpp``): a beam whose end point lies within
        ``beam_skip_distance`` of an obstacle for at most a fraction ``beam_skip_threshold``
        of the particles most likely hit something the map does not hold (a parked car, a
        person, vegetation that changed), and scoring it would pull every particle towards
        the nearest mapped obstacle that happens to lie near its end point. Such beams are
        left out of every particle's product, unless more than ``beam_skip_error_threshold``
        of the beams would be (then the particles, not the map, are wrong: all beams are
        used, as in AMCL; also from a uniform prior). The fraction is over the particles
        given (unweighted, as AMCL; after resampling the particles are equally weighted).
    beam_skip_distance, beam_skip_threshold, beam_skip_error_threshold : float
        AMCL's defaults: 0.5 m, 0.3, 0.9.
    short_skip : bool
        Leave out the beams that are *short* against the map: the reading ends in free
        space well before the surface the map puts on that ray, i.e. something the map does
        not hold stands in front of it (the ``z_short`` cause of the beam model, Thrun et
        al. 2005, sec. 6.3). The test is made once per scan at the mean pose of the
        particles given ``x_bar`` (unweighted, circular mean heading): beam ``j`` is short if

            z_j < zhat_j(x_bar)   and   dist(e_j(x_bar)) > r

        with ``zhat_j`` the exact ray-cast range (:func:`~dfusion.maps.raycast.cast_rays`,
        unknown cells block), ``dist(e_j)`` the end point's distance to the nearest surface
        and ``r`` the distance where the two terms of the mixture are equal,
        ``z_hit N(r; 0, sigma_hit^2) = z_rand / z_max``, i.e.
        ``r = sigma_hit sqrt(2 ln(z_hit z_max / (z_rand sigma_hit sqrt(2 pi))))`` (0.75 m for
        the defaults and a 30 m laser): beyond it the end point is more likely a random
        reading than a hit of the map. (The surface the ray meets at ``zhat_j`` is at most
        ``zhat_j - z_j`` from the end point, so a short beam ends at least ``r`` in front of
        it.) A short beam gets the same likelihood for every particle, i.e. it leaves the
        product; unlike ``beam_skip`` the test does not ask whether the particles agree, so
        a beam ending near (or behind) a mapped surface is kept even when the cloud is off.
        If more than ``beam_skip_error_threshold`` of the beams would be left out, all are
        used.
    """

    def __init__(
        self,
        sigma_hit: float = 0.2,
        z_hit: float = 0.95,
        z_rand: float = 0.05,
        *,
        max_distance: float = 2.0,
        exponent: float = 1.0,
        surface: bool = True,
        beam_skip: bool = False,
        beam_skip_distance: float = 0.5,
        beam_skip_threshold: float = 0.3,
        beam_skip_error_threshold: float = 0.9,
        short_skip: bool = False,
    ) -> None:
        self.surface = bool(surface)
        self.short_skip = bool(short_skip)
        self.beam_skip = bool(beam_skip)
        self.beam_skip_distance = float(beam_skip_distance)
        self.beam_skip_threshold = float(beam_skip_threshold)
        self.beam_skip_error_threshold = float(beam_skip_error_threshold)
        if not (self.beam_skip_distance > 0 and 0 <= self.beam_skip_threshold < 1
                and 0 < self.beam_skip_error_threshold <= 1):
            raise ValidationError("need beam_skip_distance > 0, 0 <= beam_skip_threshold < 1, "
                                  "0 < beam_skip_error_threshold <= 1")
        #: beams left out by the beam skipping of the latest scan, and scans where it gave up
        #: (``short_skip``: ``short_beams`` of the latest scan, ``short_beams_total`` of all)
        self.skipped_beams = 0
        self.short_beams = 0
        self.short_beams_total = 0
        self.beam_skip_errors = 0
        self.sigma_hit = float(sigma_hit)
        self.z_hit = float(z_hit)
        self.z_rand = float(z_rand)
        if not (self.sigma_hit > 0 and self.z_hit >= 0 and self.z_rand >= 0 and self.z_hit + self.z_rand > 0):
            raise ValidationError("need sigma_hit > 0, z_hit >= 0, z_rand >= 0, z_hit + z_rand > 0")
        self.max_distance = float(max_distance)
        self.exponent = float(exponent)
        self.grid: OccupancyGrid | None = None

    def point_log_likelihood(self, d: ArrayLike, max_range: float) -> Array:
        """``log(z_hit N(d; 0, sigma_hit^2) + z_rand / max_range)``."""
        d = np.minimum(np.asarray(d, dtype=float), self.max_distance)
        s = self.sigma_hit
        p = self.z_hit * np.exp(-0.5 * (d / s) ** 2) / (math.sqrt(2 * math.pi) * s) + self.z_rand / max_range
        return np.log(p)

    def prepare(self, grid: OccupancyGrid, max_range: float, table: RayCastTable | None = None) -> None:
        self.grid = grid
        self.max_range = float(max_range)
        H, W = grid.shape
        lf = np.empty((H + 2, W + 2), dtype=np.float32)  # one border cell: "off the map"
        lf[:] = self.point_log_likelihood(self.max_distance, self.max_range)
        dist = grid.surface_distance_field() if self.surface else grid.distance_field()
        lf[1:-1, 1:-1] = self.point_log_likelihood(dist, self.max_range)
        self._table = lf.reshape(-1)
        self._Wp, self._Hp = W + 2, H + 2
        # an end point within beam_skip_distance of an obstacle scores above this
        self._explained = float(self.point_log_likelihood(self.beam_skip_distance, self.max_range))
        # short_skip: end points farther than r from every surface score below this
        self._far = float(self.point_log_likelihood(self.random_distance(self.max_range), self.max_range))

    def random_distance(self, max_range: float) -> float:
        """``r = sigma_hit sqrt(2 ln(z_hit max_range / (z_rand sigma_hit sqrt(2 pi))))`` (m), the
        root of ``z_hit N(r; 0, sigma_hit^2) = z_rand / max_range``: beyond it an end point is
        more likely a random reading than a hit (Thrun et al. 2005, table 6.3 mixture). 0 if
        the hit term never exceeds the random one; at most ``max_distance``."""
        s = self.sigma_hit
        if self.z_rand <= 0:
            return self.max_distance
        q = self.z_hit * max_range / (self.z_rand * s * math.sqrt(2 * math.pi))
        return min(s * math.sqrt(2 * math.log(q)), self.max_distance) if q > 1 else 0.0

    def _cell_index(self, laser_grid_poses: Array, z: Array, angles: Array) -> np.ndarray:
        """Flat index into the padded log-likelihood table of every end point, ``(N, B)``."""
        inv = 1.0 / self.grid.resolution
        lx = (z * np.cos(angles) * inv).astype(np.float32)[None, :]
        ly = (z * np.sin(angles) * inv).astype(np.float32)[None, :]
        th = laser_grid_poses[:, 2]
        c = np.cos(th).astype(np.float32)[:, None]
        s = np.sin(th).astype(np.float32)[:, None]
        x = (laser_grid_poses[:, 0] * inv + 1.0).astype(np.float32)[:, None]  # +1: border
        y = (laser_grid_poses[:, 1] * inv + 1.0).astype(np.float32)[:, None]
        ex = c * lx - s * ly
        ex += x
        ey = s * lx + c * ly
        ey += y
        # truncation toward zero is floor for the non-negative values; anything left of
        # column 1 / below row 1 lands in the border (off the map), as do clipped ones
        j = ex.astype(np.int32)
        np.clip(j, 0, self._Wp - 1, out=j)
        i = ey.astype(np.int32)
        np.clip(i, 0, self._Hp - 1, out=i)
        i *= self._Wp
        i += j
        return i

    def short_beams_at(self, laser_grid_pose: ArrayLike, z: ArrayLike, angles: ArrayLike) -> np.ndarray:
        """Boolean mask of the beams that are short against the map seen from one grid-frame
        laser pose (the test of ``short_skip``); ``z`` below ``max_range``."""
        if self.grid is None:
            raise NotInitializedError("LikelihoodFieldModel.prepare was not called")
        p = np.asarray(laser_grid_pose, dtype=float).reshape(1, 3)
        z = np.asarray(z, dtype=float).reshape(-1)
        angles = np.asarray(angles, dtype=float).reshape(-1)
        world = np.concatenate([self.grid.grid_to_world(p[:, :2])[0], [p[0, 2] + self.grid.origin[2]]])
        zhat = cast_rays(self.grid, world, angles, self.max_range)[0]
        far = self._table.take(self._cell_index(p, z, angles))[0] < self._far
        return (z < zhat) & far

    def log_likelihood(self, laser_grid_poses: Array, z: Array, angles: Array) -> tuple[Array, int]:
        """``(sum over beams of log p, number of beams used)``; max-range beams are skipped."""
        if self.grid is None:
            raise NotInitializedError("LikelihoodFieldModel.prepare was not called")
        use = z < self.max_range
        z, angles = z[use], angles[use]
        n = laser_grid_poses.shape[0]
        if z.size == 0:
            return np.zeros(n), 0
        vals = self._table.take(self._cell_index(laser_grid_poses, z, angles))
        if self.short_skip and n > 0:
            th = laser_grid_poses[:, 2]
            mean = np.array([laser_grid_poses[:, 0].mean(), laser_grid_poses[:, 1].mean(),
                             math.atan2(np.sin(th).mean(), np.cos(th).mean())])
            short = self.short_beams_at(mean, z, angles)
            n_short = int(np.count_nonzero(short))
            if 0 < n_short < self.beam_skip_error_threshold * z.size:
                self.short_beams = n_short
                self.short_beams_total += n_short
                keep = ~short
                z, angles, vals = z[keep], angles[keep], vals[:, keep]
            else:
                self.short_beams = 0
        if self.beam_skip and n > 0:
            explained = (vals >= self._explained).mean(axis=0)
            keep = explained > self.beam_skip_threshold
            skipped = int(z.size - np.count_nonzero(keep))
            if skipped >= self.beam_skip_error_threshold * z.size:
                self.beam_skip_errors += 1
                self.skipped_beams = 0
            elif skipped:
                self.skipped_beams = skipped
                return self.exponent * vals[:, keep].sum(axis=1, dtype=np.float64), int(z.size - skipped)
            else:
                self.skipped_beams = 0
        ll = vals.sum(axis=1, dtype=np.float64)
        return self.exponent * ll, int(z.size)


class LaserScanSensor(MeasurementModel):
    """Simulated planar laser on a robot with state ``(x, y, vx, vy)`` (heading = direction of motion).

    ``h(x)`` = exact ray-cast ranges (:func:`~dfusion.maps.cast_rays`) from the pose
    ``(x, y, atan2(vy, vx))`` for the beams of ``laser``; ``R = range_std^2 I``. A
    simulated reading above ``max_range`` means "no return".

    ``H`` (only for the centralized reference EKF, which fuses raw ranges): central
    differences with a step of half a cell in ``x, y`` and ``0.01 rad`` in the heading
    (chained through ``d heading / d v = (-vy, vx) / |v|^2``); a beam whose two
    one-sided differences disagree by more than ``jump`` (it crosses a range
    discontinuity, e.g. a door frame) gets a zero row. It is a crude linearization:
    docs/robots.md.
    """

    is_linear = False

    def __init__(self, grid: OccupancyGrid, laser: LaserConfig, range_std: float = 0.05, *,
                 jump: float = 0.2) -> None:
        if not isinstance(grid, OccupancyGrid):
            raise ValidationError("LaserScanSensor needs a dfusion.maps.OccupancyGrid")
        self.grid = grid
        self.laser = laser
        self.range_std = as_positive(range_std, "range_std")
        self.jump = float(jump)
        self.dim_z = int(laser.angles.size)
        self._R = self.range_std**2 * np.eye(self.dim_z)

    def __repr__(self) -> str:
        return f"LaserScanSensor(beams={self.dim_z}, max_range={self.laser.max_range}, range_std={self.range_std})"

    def pose(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        return np.array([x[0], x[1], heading_of(x)])

    def ranges(self, poses: Array) -> Array:
        lp = se2_compose(np.atleast_2d(poses), self.laser.offset)
        return cast_rays(self.grid, lp, self.laser.angles, self.laser.max_range)

    def h(self, x: Array) -> Array:
        return self.ranges(self.pose(x))[0]

    def H(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        p = self.pose(x)
        d = 0.5 * self.grid.resolution
        da = 0.01
        steps = np.array([[d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0], [0, 0, da], [0, 0, -da]])
        r0 = self.ranges(p)[0]
        r = self.ranges(p + steps)
        H = np.zeros((self.dim_z, x.shape[0]))
        for k, (h_step) in enumerate((d, d, da)):
            fwd, bwd = r[2 * k] - r0, r0 - r[2 * k + 1]
            g = (fwd + bwd) / (2.0 * h_step)
            bad = np.abs(fwd - bwd) > self.jump
            g[bad] = 0.0
            if k < 2:
                H[:, k] = g
            else:
                sp2 = float(x[2] ** 2 + x[3] ** 2)
                if sp2 > 1e-6:
                    H[:, 2] = g * (-x[3] / sp2)
                    H[:, 3] = g * (x[2] / sp2)
        return H

    @property
    def R(self) -> Array:
        return self._R
