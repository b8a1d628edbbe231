r"""Sensor kind ``wsn_rssi``: a wireless sensor network tracking a radio tag with a particle filter.

The world measures the RSSI of the tag's packets at every receiver with the
log-distance model of :class:`~dfusion.models.RSSISensor` (one reading per
receiver per measurement time). The node does not fuse them with the EIF:
its front end (:class:`WSNFrontEnd`) runs a :class:`~dfusion.pf.WSNTracker`
(URUS sec. 8.3) and joins the information network as DESIGN.md sec. 4 says.
On each RSSI measurement taken at ``t``:

1. the particles are predicted from the tracker's time to ``t``;
2. they are weighted by the readings (the "annulus" likelihood);
3. :meth:`WSNTracker.information_contribution` gives what these readings
   added on the position, ``Omega = P_post^-1 - P_pred^-1``,
   ``eta = P_post^-1 mu_post - P_pred^-1 mu_pred`` (Gaussian fits of the same
   particles before and after weighting), projected to positive semi-definite;
4. the 2 x 2 pair is embedded in the node's state (position block; zeros for
   the velocities) and fused with ``node.add_local_information(t, Lam, y)``.

Only the information of the node's own readings enters the network, exactly
like a measurement: it is sent once to the neighbours through the channel
filters and never double counted. The particle filter is an independent
filter of the WSN's own readings, started from the network's common prior:
fused information is *not* fed back into the particles (a particle set
sharpened by the cameras would make ``P_post^-1 - P_pred^-1`` a small
difference of two large, noisy matrices).

**Late measurements.** Measurements are processed in arrival order. The
particles cannot be predicted backwards: a measurement older than the
tracker's time is skipped and counted (``stats.late``); one older than the
node's window raises :class:`~dfusion.errors.OutsideWindowError` before the
particles are touched (the runner counts it as refused).

Scenario keys (``docs/scenarios.md``): ``receivers``, ``p0``, ``exponent``,
``std``, ``d0``, ``tag_height``, ``particles``, ``pf_motion``, ``pf_q``,
``max_speed``, ``std_scale``, ``outlier_prob``, ``roughening``, and an
optional map: ``map`` (a ``.occ`` grid file of the BLE RSSI dataset's format)
or ``obstacles`` (rectangles) with ``map_bounds`` and ``map_cell``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import OutsideWindowError, ValidationError
from ..fusion.node import FusionNode
from ..linalg import Array
from ..models.measurement import RSSISensor
from ..pf import OccupancyGrid, WSNTracker
from ..pf.wsn import MOTIONS
from ..sim.scenario import _NODE_KEYS, register_sensor

__all__ = ["WSNFrontEnd", "WSNStats", "WSN_KEYS", "rssi_sensor_from_table", "grid_from_table", "obstacle_grid"]

#: Keys of a ``sensor = "wsn_rssi"`` node table, besides the common node keys (``std`` is common).
WSN_KEYS = {"receivers", "p0", "exponent", "d0", "tag_height", "particles", "pf_motion", "pf_q", "max_speed",
            "std_scale", "outlier_prob", "roughening", "map", "map_occupied_value", "obstacles", "map_bounds",
            "map_cell"}


def _num(table: Mapping[str, Any], key: str, default: Any, *, positive: bool = False, nonneg: bool = False) -> float:
    v = table.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValidationError(f"{key} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise ValidationError(f"{key} must be positive, got {v!r}")
    if nonneg and v < 0:
        raise ValidationError(f"{key} must be non-negative, got {v!r}")
    return float(v)


def rssi_sensor_from_table(table: Mapping[str, Any]) -> RSSISensor:
    """The :class:`RSSISensor` of a ``sensor = "wsn_rssi"`` node table."""
    unknown = set(table) - _NODE_KEYS - WSN_KEYS
    if unknown:
        raise ValidationError(f"unknown keys {sorted(unknown)} for a wsn_rssi node (known: {sorted(WSN_KEYS)})")
    rec = table.get("receivers")
    if not (isinstance(rec, list) and rec and all(isinstance(r, list) and len(r) in (2, 3) for r in rec)):
        raise ValidationError("receivers must be a non-empty list of [x, y] or [x, y, z] positions")
    if len({len(r) for r in rec}) != 1:
        raise ValidationError("receivers must all be [x, y] or all be [x, y, z]")
    std = table.get("std", 4.0)
    if isinstance(std, list) and len(std) != len(rec):
        raise ValidationError(f"std must be one value or one per receiver ({len(rec)}), got {len(std)}")
    return RSSISensor(rec, _num(table, "p0", -45.0), _num(table, "exponent", 2.0, positive=True), std,
                      d0=_num(table, "d0", 1.0, positive=True), height=_num(table, "tag_height", 0.0))


def obstacle_grid(obstacles: list, bounds: Array, cell: float) -> OccupancyGrid:
    """An :class:`OccupancyGrid` over ``bounds = (x_min, y_min, x_max, y_max)`` with square cells.

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
    return OccupancyGrid(occ, cell, (x0, y0))


def grid_from_table(table: Mapping[str, Any], base: Path | None = None) -> OccupancyGrid | None:
    """The optional map of a ``wsn_rssi`` node: ``map`` (an ``.occ`` file) or ``obstacles``; None without."""
    if "map" in table and "obstacles" in table:
        raise ValidationError("give either map (an .occ file) or obstacles, not both")
    if "map" in table:
        path = table["map"]
        if not isinstance(path, str) or not path:
            raise ValidationError(f"map must be a path to an .occ grid file, got {path!r}")
        p = Path(path)
        if not p.is_absolute() and base is not None:
            p = base / p
        value = table.get("map_occupied_value", 1)
        if value not in (0, 1) or isinstance(value, bool):
            raise ValidationError(f"map_occupied_value must be 0 or 1, got {value!r}")
        try:
            return OccupancyGrid.from_occ_file(p, occupied_value=value)
        except OSError as exc:
            raise ValidationError(f"map: cannot read {p}: {exc}") from None
    if "obstacles" in table:
        obs = table["obstacles"]
        ok = isinstance(obs, list) and all(
            isinstance(r, list) and len(r) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                       and math.isfinite(v) for v in r) and r[2] > r[0] and r[3] > r[1]
            for r in obs)
        if not ok:
            raise ValidationError("obstacles must be a list of [x_min, y_min, x_max, y_max] rectangles")
        b = table.get("map_bounds")
        if not (isinstance(b, list) and len(b) == 4 and all(isinstance(v, (int, float)) for v in b)
                and b[2] > b[0] and b[3] > b[1]):
            raise ValidationError("obstacles need map_bounds = [x_min, y_min, x_max, y_max]")
        cell = _num(table, "map_cell", 0.25, positive=True)
        return obstacle_grid(obs, np.asarray(b, dtype=float), cell)
    for key in ("map_bounds", "map_cell", "map_occupied_value"):
        if key in table:
            raise ValidationError(f"{key} given without map or obstacles")
    return None


@dataclass
class WSNStats:
    """Counters of a WSN front end."""

    measurements: int = 0         # RSSI measurements (one reading per receiver each) processed
    readings: int = 0             # individual receiver readings used
    contributions: int = 0        # information contributions fused into the node
    empty: int = 0                # measurements that contributed no information (no reading, or all clipped)
    late: int = 0                 # skipped: older than the particles' time
    refused: int = 0              # older than the node's window


class WSNFrontEnd:
    """Runs a :class:`WSNTracker` on a node's RSSI measurements and fuses its information contributions.

    Parameters
    ----------
    tracker : WSNTracker
        Not yet initialized; it is initialized from ``prior`` at the first measurement.
    prior : (t0, mean, cov)
        The network's common prior (state ``[x, y, (z,) vx, vy, (vz)]``): particle
        positions (and velocities for a constant-velocity tracker) are drawn from it.
    axes : int
        Position axes of the state (2 or 3); the contribution goes to ``x, y``.
    """

    def __init__(self, tracker: WSNTracker, prior: tuple[float, Array, Array], axes: int = 2) -> None:
        self.tracker = tracker
        self.t0 = float(prior[0])
        self.prior_mean = np.asarray(prior[1], dtype=float)
        self.prior_cov = np.asarray(prior[2], dtype=float)
        self.axes = int(axes)
        #: Time of the particles (None before the first measurement).
        self.time: float | None = None
        self.stats = WSNStats()

    def __repr__(self) -> str:
        return f"WSNFrontEnd({self.tracker!r}, time={self.time}, {self.stats})"

    def _initialize(self) -> None:
        trk = self.tracker
        m, C = self.prior_mean, self.prior_cov
        trk.initialize(mean=m[:2], cov=C[:2, :2])
        if trk.dim == 4:
            # velocities drawn from the prior conditioned on the drawn positions
            iv = [self.axes, self.axes + 1]
            ip = [0, 1]
            Cpp, Cvp, Cvv = C[np.ix_(ip, ip)], C[np.ix_(iv, ip)], C[np.ix_(iv, iv)]
            K = np.linalg.solve(Cpp, Cvp.T).T
            Cc = Cvv - K @ Cvp.T
            x = np.array(trk.particles)
            L = np.linalg.cholesky(0.5 * (Cc + Cc.T) + 1e-12 * np.eye(2))
            x[:, 2:] = m[iv] + (x[:, :2] - m[ip]) @ K.T + trk.pf.rng.standard_normal((x.shape[0], 2)) @ L.T
            trk.pf.set_particles(x)
        self.time = self.t0

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        """Predict the particles to ``t``, weight them by the readings ``z``, fuse the contribution.

        Returns whether information was fused. See the module docstring for late measurements.
        """
        f = node.filter
        if t < f.oldest_time - f.time_tol:
            self.stats.refused += 1
            raise OutsideWindowError(f"RSSI measurement at t={t} is older than the window start {f.oldest_time}")
        if self.time is None:
            self._initialize()
        if t < self.time - f.time_tol:
            self.stats.late += 1
            return False
        self.stats.measurements += 1
        self.tracker.predict(max(t - self.time, 0.0))
        self.time = max(self.time, float(t))
        used = self.tracker.update(z)
        self.stats.readings += used
        info = self.tracker.information_contribution()
        if used == 0 or not np.any(info.Omega):
            self.stats.empty += 1
            return False
        n = f.n
        Lam = np.zeros((n, n))
        y = np.zeros(n)
        Lam[:2, :2] = info.Omega
        y[:2] = info.eta
        node.add_local_information(t, Lam, y)
        self.stats.contributions += 1
        return True

    def estimate(self) -> tuple[Array, Array]:
        """The particle filter's own Gaussian fit of ``(x, y)`` (its readings only)."""
        return self.tracker.gaussian_summary()


def _wsn_sensor(table: Mapping[str, Any], sc) -> RSSISensor:
    sensor = rssi_sensor_from_table(table)
    # validate the tracker's keys now, so that errors name the scenario file
    _tracker_options(table, sc)
    base = None if sc.path.startswith("<") else Path(sc.path).parent
    grid_from_table(table, base)
    return sensor


def _tracker_options(table: Mapping[str, Any], sc) -> dict[str, Any]:
    motion = table.get("pf_motion", "constant_velocity")
    if motion not in MOTIONS:
        raise ValidationError(f"pf_motion must be one of {MOTIONS}, got {motion!r}")
    q_default = getattr(sc.target.motion, "q", 0.1) if motion == "constant_velocity" else 0.5
    particles = table.get("particles", 5000)
    if isinstance(particles, bool) or not isinstance(particles, int) or particles < 2:
        raise ValidationError(f"particles must be an integer >= 2, got {particles!r}")
    max_speed = table.get("max_speed")
    if max_speed is not None:
        max_speed = _num(table, "max_speed", None, positive=True)
    outlier = _num(table, "outlier_prob", 0.0, nonneg=True)
    if outlier >= 1:
        raise ValidationError(f"outlier_prob must be in [0, 1), got {outlier}")
    return dict(n_particles=particles, motion=motion, q=_num(table, "pf_q", q_default, positive=True),
                max_speed=max_speed, std_scale=_num(table, "std_scale", 1.0, positive=True),
                outlier_prob=outlier, roughening=_num(table, "roughening", 0.0, nonneg=True))


def _wsn_front_end(spec, sc, seed: int) -> WSNFrontEnd:
    table = {"sensor": "wsn_rssi", **spec.params}
    base = None if sc.path.startswith("<") else Path(sc.path).parent
    grid = grid_from_table(table, base)
    tracker = WSNTracker(spec.sensor, grid=grid, seed=seed, **_tracker_options(table, sc))
    return WSNFrontEnd(tracker, (0.0, sc.target.initial_mean, sc.target.initial_cov), axes=sc.target.axes)


register_sensor("wsn_rssi", _wsn_sensor, _wsn_front_end)
