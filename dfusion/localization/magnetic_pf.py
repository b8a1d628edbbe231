r"""Particle-filter localization of a walking phone from pedestrian dead reckoning and a magnetic map.

The survey behind dfusion's localization row (infrastructure-free global localization in
repetitive environments) finds the magnetic-field particle filter the most robust of its sources
but not accurate enough alone; this is that filter, on the one particle-filter engine
(:class:`~dfusion.estimation.particle_filter.ParticleFilter`) the WSN tracker and MCL use.

**State** per particle: position ``(x, y)`` [m], the walk's heading offset ``delta`` [rad] (how the
phone is held; added to the floor's offset from East), its step-length scale ``s`` (multiplies the
Weinberg gain), and a Rao-Blackwellized magnetometer bias per feature: mean ``b_j`` and variance
``P_j`` (phones differ by several uT; measured on site1-F1, per-walk bias std 4-7 uT against 3 uT
within a walk).

**Motion** per step (``w`` = Weinberg factor, ``psi`` = heading from the rotation vector)::

    delta <- delta + N(0, sigma_delta^2)           s <- s exp(N(0, sigma_s^2))
    L = K s w (1 + N(0, sigma_L^2))                 a = psi + theta_floor + delta + N(0, sigma_psi^2)
    (x, y) <- (x, y) + L (cos a, sin a) + N(0, sigma_pos^2 I)

**Magnetic likelihood** of the step's world-frame features ``f_j`` (``docs/indoor.md``), with the
map's mean ``m_j(p)`` and variance ``v_j(p)``::

    f_j ~ N(m_j(p) + b_j, v_j(p) + r + P_j)     (log-likelihood divided by ``temper``)

then the bias is updated by the scalar Kalman step ``k = P_j / (v_j + r + P_j)``,
``b_j <- b_j + k (f_j - m_j - b_j)``, ``P_j <- (1 - k) P_j``; a particle whose position is off the
map's support gets ``log(off_map)`` added (corridors where nobody walked). Successive steps' map
errors are correlated in space (the map is smooth and the walker slow), so the likelihood is
tempered (``temper > 1``) as the WSN tracker's ``std_scale`` does for correlated RSSI.

:meth:`MagneticLocalizer.reweight_information` multiplies the weights by the Gaussian likelihood an
information pair ``(eta, Omega)`` on ``(x, y)`` represents (WiFi's from the network), after
redrawing the worst particles from the radio track when the set's fit to the radio drops (augmented
MCL, :meth:`MagneticLocalizer.recovery_fraction`; the track is :meth:`MagneticLocalizer.radio_track_test`'s);
:meth:`MagneticLocalizer.information_contribution` gives what the magnetic readings since the last call added, as
the WSN tracker's quotient of Gaussian fits (``docs/indoor.md`` says when it is withheld).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import NotInitializedError, ValidationError
from dfusion.estimation.gaussian import InformationGaussian, project_psd_information
from dfusion.estimation.particle_filter import ParticleDepletionError, ParticleFilter, weighted_mean_cov
from dfusion.linalg import Array, spd_inverse
from dfusion.maps.magnetic import MagneticMap

__all__ = ["MagneticLocalizer", "MagneticPFSettings", "build_bias_free_map"]


@dataclass
class MagneticPFSettings:
    """Settings of :class:`MagneticLocalizer` (one set for the whole data family; the defaults are the
    ones ``examples/indoor_localization.py`` evaluates, docs/indoor.md).

    ``n_particles``; per step: ``sigma_delta`` [rad] random walk of the heading offset, ``sigma_s`` of the
    log step scale, ``sigma_len`` relative step-length noise, ``sigma_psi`` [rad] heading noise,
    ``sigma_pos`` [m] isotropic position noise; initial laws ``delta0_std`` [rad], ``s0_std`` (log scale);
    magnetic likelihood: ``sensor_var`` [uT^2], ``bias_var`` [uT^2] (prior of the per-walk bias),
    ``temper`` (divides the log-likelihood), ``off_map`` (likelihood factor off the map's support; 1:
    none), ``features`` (columns of the field features used: 0 = B_z, 1 = B_h, 2 = |B|);
    ``roughening`` (Gordon's K, position only); ``recover_slow``, ``recover_fast`` (augmented MCL's
    ``alpha_slow < alpha_fast``; 0: off; docs/indoor.md): the smoothing rates of the radio fit's averages that set how many
    particles :meth:`MagneticLocalizer.reweight_information` redraws around the radio fix;
    ``recover_alpha`` (0: off): significance level of the test of the particle set against the radio track
    (:meth:`MagneticLocalizer.radio_track_test`) below which particles are redrawn from that track;
    ``redraw_from_track``: every redraw (also augmented MCL's) is from the radio track instead of the latest fix;
    ``init_from_radio``: a set initialized without a prior (global localization) is redrawn, at the first radio
    information it receives, from that information's Gaussian (covariance times ``init_inflate ** 2``)
    restricted to the map's support (:meth:`MagneticLocalizer.reweight_information`)."""

    n_particles: int = 2000
    sigma_delta: float = np.radians(0.5)
    sigma_s: float = 0.01
    sigma_len: float = 0.15
    sigma_psi: float = np.radians(5.0)
    sigma_pos: float = 0.3
    delta0_std: float = np.radians(5.0)
    s0_std: float = 0.05
    sensor_var: float = 1.0
    bias_var: float = 36.0
    temper: float = 2.0
    off_map: float = 0.9
    features: tuple[int, ...] = (0, 1, 2)
    roughening: float = 0.05
    recover_slow: float = 0.1
    recover_fast: float = 0.5
    recover_alpha: float = 0.0
    redraw_from_track: bool = True
    init_from_radio: bool = True
    init_inflate: float = 1.0


class MagneticLocalizer:
    """PDR + magnetic-map particle filter (module docstring).

    Parameters
    ----------
    mag_map : MagneticMap
        The floor's map (features as in :func:`dfusion.models.pdr.world_field`).
    gain, theta_floor : float
        Weinberg ``K`` [m] and the floor frame's rotation from East [rad] (fitted on training walks).
    settings : MagneticPFSettings
    seed : int, Generator or None
    """

    def __init__(self, mag_map: MagneticMap, gain: float, theta_floor: float,
                 settings: MagneticPFSettings | None = None, seed: int | np.random.Generator | None = None) -> None:
        if not (np.isfinite(gain) and gain > 0):
            raise ValidationError(f"gain must be positive, got {gain}")
        self.map = mag_map
        self.gain = float(gain)
        self.theta = float(theta_floor)
        self.cfg = settings or MagneticPFSettings()
        self._seed = seed
        self.pf: ParticleFilter | None = None
        self.time: float | None = None
        self._ref: tuple[Array, Array] | None = None
        self._fj = np.asarray(self.cfg.features, dtype=np.int64)
        self.w_slow: float | None = None
        self.w_fast: float | None = None
        self.injected = 0

    # ---------------------------------------------------------------- set-up
    def initialize(self, t: float, mean: ArrayLike | None = None, cov: ArrayLike | None = None) -> None:
        """Draw the particles at time ``t``: Gaussian ``(mean, cov)`` on ``(x, y)`` or, without a mean,
        uniform over the map's support (global localization)."""
        rng = self._seed if isinstance(self._seed, np.random.Generator) else np.random.default_rng(self._seed)
        c = self.cfg
        x = self._draw(c.n_particles, mean, cov, rng)
        self.pf = ParticleFilter(x, rng=rng, roughening=c.roughening)
        self.pf.roughening_dims = (0, 1)
        self.time = float(t)
        self._ref = self._fit()
        self.w_slow = self.w_fast = None
        self.injected = 0
        self.radio_track: tuple[Array, Array] | None = None
        self.awaiting_radio = mean is None and c.init_from_radio

    def _draw_on_support(self, n: int, mean: Array, cov: Array, rng: np.random.Generator) -> Array:
        """``n`` particles from ``N(mean, cov)`` restricted to the map's support (the walkable-area prior times
        the radio likelihood), by rejection in batches of ``n``; topped up by unrestricted draws if 20 batches
        do not give ``n`` (a fix far from any walked cell)."""
        keep: list[Array] = []
        got = 0
        for _ in range(20):
            x = self._draw(n, mean, cov, rng)
            x = x[self.map.on_support(x[:, :2])]
            keep.append(x)
            got += x.shape[0]
            if got >= n:
                break
        if got < n:
            keep.append(self._draw(n - got, mean, cov, rng))
        return np.vstack(keep)[:n]

    def _draw(self, n: int, mean: ArrayLike | None, cov: ArrayLike | None, rng: np.random.Generator) -> Array:
        """``n`` particles: positions from ``N(mean, cov)`` (uniform over the support without a mean),
        heading offset, scale and bias from their initial laws."""
        c = self.cfg
        if mean is None:
            pos = self.map.sample_support(n, rng)
        else:
            C = np.eye(2) if cov is None else np.asarray(cov, dtype=float)
            pos = np.asarray(mean, dtype=float)[:2] + rng.standard_normal((n, 2)) @ np.linalg.cholesky(C).T
        m = self._fj.size
        x = np.empty((n, 4 + 2 * m))
        x[:, :2] = pos
        x[:, 2] = rng.standard_normal(n) * c.delta0_std
        x[:, 3] = np.exp(rng.standard_normal(n) * c.s0_std)
        x[:, 4:4 + m] = 0.0
        x[:, 4 + m:] = c.bias_var
        return x

    def _require(self) -> ParticleFilter:
        if self.pf is None:
            raise NotInitializedError("MagneticLocalizer used before initialize()")
        return self.pf

    # ------------------------------------------------------------------ step
    def step(self, t: float, w: float, psi: float, field: ArrayLike | None) -> None:
        """One detected step at ``t``: move by it (Weinberg factor ``w``, heading ``psi``), then weight
        by the step's world-frame ``field`` (``None``: no magnetic update)."""
        pf = self._require()
        c = self.cfg
        x = pf.particles.copy()
        n = x.shape[0]
        rng = pf.rng
        x[:, 2] += rng.standard_normal(n) * c.sigma_delta
        x[:, 3] *= np.exp(rng.standard_normal(n) * c.sigma_s)
        L = self.gain * w * x[:, 3] * (1.0 + rng.standard_normal(n) * c.sigma_len)
        a = psi + self.theta + x[:, 2] + rng.standard_normal(n) * c.sigma_psi
        x[:, 0] += L * np.cos(a)
        x[:, 1] += L * np.sin(a)
        if c.sigma_pos > 0:
            x[:, :2] += rng.standard_normal((n, 2)) * c.sigma_pos
        if self.radio_track is not None:  # the radio track moves by the particles' step, mean and spread
            dm, dC = weighted_mean_cov(x[:, :2] - pf.particles[:, :2], pf.weights)
            self.radio_track = (self.radio_track[0] + dm, self.radio_track[1] + dC)
        pf.move(x)
        self.time = float(t)
        if field is not None:
            self._magnetic(np.asarray(field, dtype=float)[self._fj])

    def _magnetic(self, f: Array) -> None:
        pf = self._require()
        c = self.cfg
        x = pf.particles.copy()
        m = self._fj.size
        mu, v = self.map.lookup(x[:, :2])
        mu, v = mu[:, self._fj], v[:, self._fj]
        b, P = x[:, 4:4 + m], x[:, 4 + m:]
        S = v + c.sensor_var + P
        r = f - mu - b
        ll = -0.5 * np.sum(r * r / S + np.log(S), axis=1) / c.temper
        ll += np.where(self.map.on_support(x[:, :2]), 0.0, np.log(c.off_map))
        k = P / S
        x[:, 4:4 + m] = b + k * r
        x[:, 4 + m:] = (1.0 - k) * P
        pf.move(x)
        self._update(ll)

    def _update(self, ll: Array) -> None:
        pf = self._require()
        try:
            pf.update(ll)
        except ParticleDepletionError:
            return
        pf.resample_if_needed()

    def radio_fit(self, mean: ArrayLike, omega: ArrayLike) -> float:
        """The particle set's agreement with a radio fix ``N(mean, Omega^-1)``: the average likelihood of
        augmented MCL scaled by the Gaussian's peak, ``w_avg = sum_i w_i exp(-d_i^T Omega d_i / 2)``,
        ``d_i = p_i - mean``, in ``[0, 1]`` (fixes of different widths compare)."""
        pf = self._require()
        d = pf.particles[:, :2] - np.asarray(mean, dtype=float)
        return float(pf.weights @ np.exp(-0.5 * np.einsum("ij,jk,ik->i", d, np.asarray(omega, dtype=float), d)))

    def recovery_fraction(self, fit: float) -> float:
        """Augmented MCL (Thrun, Burgard and Fox, *Probabilistic Robotics*, 2005, sec. 8.3.5, Table 8.3):
        ``w_slow += alpha_slow (w_avg - w_slow)``, ``w_fast += alpha_fast (w_avg - w_fast)`` (both start at
        the first ``w_avg``); the fraction of particles to redraw is ``max(0, 1 - w_fast / w_slow)``: the
        set's recent fit to the radio fixes against its long-run fit. 0 when the rates are 0 (off)."""
        c = self.cfg
        if c.recover_slow <= 0 or c.recover_fast <= 0:
            return 0.0
        if self.w_slow is None or self.w_fast is None:
            self.w_slow = self.w_fast = float(fit)
        else:
            self.w_slow += c.recover_slow * (fit - self.w_slow)
            self.w_fast += c.recover_fast * (fit - self.w_fast)
        return max(0.0, 1.0 - self.w_fast / self.w_slow) if self.w_slow > 0 else 0.0

    def radio_track_test(self, z: Array, C: Array) -> float:
        """Update the radio track with the fix ``N(z, C)`` and test the particle set against it.

        The radio track ``N(r, R)`` is a Kalman filter of the radio fixes alone, moved between fixes by the
        particles' mean step and its spread (:meth:`step`): PDR + radio, the network's Kalman baseline. A fix
        updates it (``G = R (R + C)^-1``, ``r += G (z - r)``, ``R = (I - G) R``; the first fix starts it).
        The test: with the set's Gaussian fit ``N(m, P)``, ``D^2 = (m - r)^T (P + R)^-1 (m - r)`` is
        chi-square with 2 degrees of freedom when both describe the same position, so its p-value is
        ``exp(-D^2 / 2)``; returned. Shared PDR and radio information make ``D^2`` smaller than
        independent estimates' would be, so the test is conservative."""
        if self.radio_track is None:
            self.radio_track = (z.copy(), C.copy())
        else:
            r, R = self.radio_track
            G = np.linalg.solve(R + C, R).T
            R1 = (np.eye(2) - G) @ R
            self.radio_track = (r + G @ (z - r), 0.5 * (R1 + R1.T))
        r, R = self.radio_track
        m, P = self._fit()
        d = m - r
        return float(np.exp(-0.5 * d @ np.linalg.solve(P + R, d)))

    def reweight_information(self, eta: ArrayLike, omega: ArrayLike, inject: float = 0.0,
                             floor: float = 0.0) -> None:
        """Multiply the weights by ``exp(eta^T p - p^T Omega p / 2)`` (information from the network on
        ``(x, y)``; pass only what this node did not contribute itself), then resample if needed. Like a
        prediction, this resets the reference of :meth:`information_contribution`.

        A set started without a prior with ``init_from_radio`` is, at the first definite information, redrawn
        whole from ``N(Omega^-1 eta, init_inflate^2 Omega^-1)`` restricted to the map's support, at equal
        weights, and the information is not applied again (it is the proposal: uniform prior times the fix).

        Otherwise particles are first redrawn around the fix (when ``Omega`` is positive definite): the fraction
        ``max(inject, recovery_fraction)`` (:meth:`recovery_fraction`, augmented MCL) of the particles
        with the lowest weights is replaced by draws from ``N(Omega^-1 eta, Omega^-1)`` (heading offset,
        scale and bias from their initial laws) at the mean weight of the set: the mixture proposal of
        Monte Carlo localization with sensor resetting (Lenser and Veloso, "Sensor resetting
        localization for poorly modelled mobile robots", ICRA 2000; Thrun, Burgard and Fox,
        *Probabilistic Robotics*, 2005, sec. 8.3.5), so that a set locked onto the wrong corridor can
        recover.

        ``floor > 0`` makes the radio likelihood robust: ``max``-normalized Gaussian plus a uniform
        outlier floor, ``log(exp(-D^2 / 2) + floor)`` with ``D`` the Mahalanobis distance to the fix."""
        pf = self._require()
        e = np.asarray(eta, dtype=float)
        O = np.asarray(omega, dtype=float)
        definite = bool(np.all(np.linalg.eigvalsh(O) > 0))
        k = int(float(inject) * pf.n)
        src = None
        if definite:
            z = np.linalg.solve(O, e)
            C = np.linalg.inv(O)
            C = 0.5 * (C + C.T)
            src = (z, C)
            if self.awaiting_radio:  # global start: the first radio information becomes the proposal
                self.awaiting_radio = False
                pf.set_particles(self._draw_on_support(pf.n, z, self.cfg.init_inflate ** 2 * C, pf.rng))
                if self.cfg.recover_alpha > 0 or self.cfg.redraw_from_track:
                    self.radio_track = (z.copy(), C.copy())
                self._ref = self._fit()
                return
            k = max(k, int(self.recovery_fraction(self.radio_fit(z, O)) * pf.n))
            if self.cfg.recover_alpha > 0 or self.cfg.redraw_from_track:
                pval = self.radio_track_test(z, C)
                if self.cfg.redraw_from_track:
                    src = self.radio_track
                if self.cfg.recover_alpha > 0 and pval < self.cfg.recover_alpha:
                    k = max(k, int((1.0 - pval / self.cfg.recover_alpha) * pf.n))
                    src = self.radio_track
        if k > 0 and src is not None:
            x = pf.particles.copy()
            lw = pf.log_weights.copy()
            worst = np.argsort(lw)[:k]
            x[worst] = self._draw(k, src[0], src[1], pf.rng)
            top = lw.max()
            lw[worst] = top + np.log(np.mean(np.exp(lw - top)))
            pf.set_particles(x, lw)
            self.injected += k
        p = pf.particles[:, :2]
        ll = p @ e - 0.5 * np.einsum("ij,jk,ik->i", p, O, p)
        if floor > 0 and definite:
            d = p - z
            ll = np.logaddexp(-0.5 * np.einsum("ij,jk,ik->i", d, O, d), np.log(floor))
        self._update(ll - ll.max())
        self._ref = self._fit()

    # --------------------------------------------------------------- outputs
    def _fit(self) -> tuple[Array, Array]:
        pf = self._require()
        return weighted_mean_cov(pf.particles[:, :2], pf.weights)

    def estimate(self) -> tuple[Array, Array]:
        """Weighted mean and covariance of ``(x, y)``."""
        return self._fit()

    def mode_estimate(self, radius: float = 5.0, cell: float = 2.0) -> Array:
        """The weighted mean of the particles within ``radius`` of the densest ``cell`` x ``cell`` square
        (weights binned, summed over 3 x 3 squares): the main mode of a multi-modal set, where the
        overall mean may lie between corridors."""
        pf = self._require()
        p = pf.particles[:, :2]
        w = pf.weights
        lo = p.min(axis=0)
        ij = np.floor((p - lo) / cell).astype(np.int64)
        shape = tuple(ij.max(axis=0) + 3)
        H = np.zeros(shape)
        np.add.at(H, (ij[:, 0] + 1, ij[:, 1] + 1), w)
        S = sum(np.roll(np.roll(H, a, 0), b, 1) for a in (-1, 0, 1) for b in (-1, 0, 1))
        i, j = np.unravel_index(np.argmax(S), shape)
        c = lo + (np.array([i, j]) - 0.5) * cell
        near = np.hypot(p[:, 0] - c[0], p[:, 1] - c[1]) <= radius
        return (w[near] @ p[near]) / w[near].sum()

    def information_contribution(self, max_std: float = 3.0) -> InformationGaussian:
        r"""What the magnetic readings since the last call added on ``(x, y)``: ``Omega = P_1^-1 - P_0^-1``,
        ``eta = P_1^-1 m_1 - P_0^-1 m_0`` (Gaussian fits now and at the reference, made PSD), the PDR
        motion in between counted in the reference by moving its mean with the particles' mean motion.
        Zero while the posterior fit is wider than ``max_std`` in some direction (a multi-modal set,
        ``docs/indoor.md``). The reference is reset to now."""
        m1, P1 = self._fit()
        m0, P0 = self._ref
        self._ref = (m1, P1)
        if np.sqrt(np.linalg.eigvalsh(P1).max()) > max_std:
            return InformationGaussian(np.zeros(2), np.zeros((2, 2)))
        reg = 1e-4 * np.eye(2)  # a collapsed set (all copies of one particle) has a singular fit
        O1 = spd_inverse(P1 + reg, "posterior particle covariance")
        O0 = spd_inverse(P0 + reg, "reference particle covariance")
        Om, eta, _ = project_psd_information(O1 - O0, O1 @ m1 - O0 @ m1, 1e-9)
        return InformationGaussian(eta, Om)


def build_bias_free_map(tracks: list[Array], fields: list[Array], *, bounds: ArrayLike, cell: float = 1.0,
                        sigma: float = 1.0, n0: float = 2.0, iterations: int = 3) -> tuple[MagneticMap, list[Array]]:
    """A :class:`MagneticMap` from training walks with each walk's magnetometer bias removed.

    Alternates ``iterations`` times: build the map from ``f - b_w``; set each walk's bias ``b_w`` to the
    mean residual ``f - m(p)`` of its samples. Returns the map and the biases.
    """
    if len(tracks) != len(fields) or not tracks:
        raise ValidationError("tracks and fields must be non-empty lists of the same length")
    bias = [np.zeros(np.asarray(f).shape[1]) for f in fields]
    P = np.vstack(tracks)
    mp = None
    for _ in range(max(1, iterations)):
        F = np.vstack([f - b for f, b in zip(fields, bias)])
        mp = MagneticMap.build(P, F, bounds=bounds, cell=cell, sigma=sigma, n0=n0)
        bias = [np.mean(f - mp.lookup(p)[0], axis=0) for p, f in zip(tracks, fields)]
    return mp, bias
