r"""Hypothesisers: every track against every detection of a scan, gated, with likelihood ratios.

For track ``t`` with prediction ``(x^_t, P^_t)`` and detection ``z_j`` of a scan
(Bar-Shalom, Daum & Huang, "The probabilistic data association filter", IEEE Control
Systems Magazine 29(6), 2009, sec. "JPDAF"; Bar-Shalom & Li 1995, sec. 6.2)::

    nu_tj = z_j (-) h(x^_t),   S_t = H_t P^_t H_t^T + R,   d_tj^2 = nu_tj^T S_t^-1 nu_tj
    gated:  d_tj^2 <= gamma = chi2_m^-1(P_G)
    detection weight   g_tj = P_D,t N(nu_tj; 0, S_t)          (gated pairs only)
    miss weight        g_t0 = lambda (1 - P_D,t P_G)

A joint hypothesis (each track takes at most one detection, each detection at most one
track, the others are clutter) has probability proportional to the product of its tracks'
weights (the ``lambda`` of each clutter detection is common to all hypotheses of a scan
after dividing by ``lambda^k``). ``P_D,t`` is the scan's detection probability times the
probability that the track is in the scan's view (:meth:`~dfusion.tracking.track.Scan.visibility`;
a track with ``P_D,t = 0`` takes no part). These are the single-target
PDA's terms (:mod:`dfusion.estimation.pda`: ``b / e_i`` is ``g_t0 / g_tj``), computed by the
PDA's own :func:`~dfusion.estimation.pda.frame_innovations`. ``lambda = 0``
is floored at ``1e-300`` (then a gated detection is always taken).

**Per-detection noise.** When the scan gives each detection its own covariance ``R_j``
(:attr:`~dfusion.tracking.track.Scan.noise`), the innovation covariance is per pair,
``S_tj = H_t P^_t H_t^T + R_j``, and ``d_tj^2`` and ``g_tj`` use it (the same Gaussian
likelihood, with the pair's own ``S``); :attr:`Hypotheses.pair_S` holds them.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dfusion.estimation.pda import frame_innovations, gate_threshold
from dfusion.linalg import Array, cholesky, symmetrize
from dfusion.tracking.track import Scan, Track

__all__ = ["Hypotheses", "Hypothesiser", "GaussianHypothesiser"]

_TINY_DENSITY = 1e-300


@dataclass(frozen=True)
class Hypotheses:
    """Single-target hypotheses of ``T`` tracks with the ``k`` detections of one scan.

    Attributes
    ----------
    means, covs : per track, the prediction ``(x^_t, P^_t)`` at the scan's time.
    H, S : per track, the measurement Jacobian at ``x^_t`` and the innovation covariance.
    innovations : (T, k, m) ``nu_tj``.
    d2 : (T, k) squared Mahalanobis distances.
    gated : (T, k) bool, ``d2 <= gamma`` and the track in view.
    log_weight : (T, k) ``log g_tj`` where gated, ``-inf`` elsewhere.
    log_miss : (T,) ``log g_t0``.
    detection : (T,) ``P_D,t`` (0 for a track out of view).
    visibility : (T,) probability that each track is in the scan's view.
    gamma : the gate.
    pair_S : (T, k, m, m) ``S_tj = H_t P^_t H_t^T + R_j`` when the scan gives per-detection noise
             (``S`` then holds ``H_t P^_t H_t^T + sensor.R``, unused); ``None`` otherwise.
    noise : (k, m, m) the scan's per-detection ``R_j``, or ``None``.
    """

    means: list[Array]
    covs: list[Array]
    H: list[Array]
    S: list[Array]
    innovations: Array
    d2: Array
    gated: Array
    log_weight: Array
    log_miss: Array
    detection: Array
    visibility: Array
    gamma: float
    pair_S: Array | None = None
    noise: Array | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.d2.shape


class Hypothesiser(ABC):
    """Component kind: forms and gates every (track, detection) pair of a scan."""

    @abstractmethod
    def hypothesise(self, tracks: Sequence[Track], scan: Scan) -> Hypotheses:
        """The hypotheses of ``tracks`` (already predicted to ``scan.time``) with ``scan``."""


class GaussianHypothesiser(Hypothesiser):
    """Gaussian likelihoods and a chi-square gate of probability ``gate`` (module docstring).

    ``detections_in_view=True``: the detection weight is ``g_tj = P_D N(nu_tj; 0, S_tj)`` for
    every track with a non-zero view probability ``v_t``, and ``v_t`` enters only the miss
    weight ``lambda (1 - P_D v_t P_G)``. With a view-limited detection probability
    ``P_D(x) = P_D 1_view(x)``, the likelihood of a detection at ``z`` is
    ``int P_D 1_view(x) N(z; Hx, R) N(x; x^, P^) dx``, which is ``P_D N(z; Hx^, S)`` when the
    noise is small against the view (``1_view(x) = 1_view(z) = 1`` where the integrand
    matters), whereas the default ``P_D v_t N(...)`` underweights a track whose estimate is
    wide against the view (a robot not seen for a long time, ``v_t << 1``) below clutter.
    Default ``False`` (``P_D v_t`` in both weights: the plaza benchmark's setting).
    """

    def __init__(self, gate: float = 0.99, *, detections_in_view: bool = False) -> None:
        gate_threshold(gate)
        self.gate = float(gate)
        self.detections_in_view = bool(detections_in_view)

    def hypothesise(self, tracks: Sequence[Track], scan: Scan) -> Hypotheses:
        sensor = scan.sensor
        m = int(sensor.dim_z)
        Z = scan.detections
        k, T = Z.shape[0], len(tracks)
        gamma = gate_threshold(self.gate, m)
        log_density = math.log(max(scan.clutter_density, _TINY_DENSITY))
        means, covs, Hs, Ss = [], [], [], []
        nus = np.zeros((T, k, m))
        d2 = np.full((T, k), np.inf)
        logw = np.full((T, k), -np.inf)
        log_miss = np.zeros(T)
        pd = np.zeros(T)
        vis = np.zeros(T)
        pair_S = None if scan.noise is None else np.zeros((T, k, m, m))
        for t, track in enumerate(tracks):
            x, P = track.estimate()
            fi = frame_innovations(x, P, Z, sensor)   # H, S, nu_tj, d_tj^2: the PDA's
            means.append(x)
            covs.append(P)
            Hs.append(fi.H)
            Ss.append(fi.S)
            vis[t] = scan.visibility(x, P)
            pd[t] = scan.detection_probability * vis[t]
            miss = 1.0 - pd[t] * self.gate
            log_miss[t] = log_density + math.log(miss) if miss > 0 else -np.inf
            if k == 0:
                continue
            nus[t] = fi.innovations
            if pair_S is None:
                d2[t] = fi.d2
                log_norm = np.full(k, fi.log_norm)
            else:                                      # S_tj = H P^ H^T + R_j per detection
                HPH = fi.S - np.asarray(sensor.R, dtype=float)
                log_norm = np.empty(k)
                for j in range(k):
                    Sj = symmetrize(HPH + scan.noise[j])
                    pair_S[t, j] = Sj
                    C = cholesky(Sj, "innovation covariance S")
                    w = np.linalg.solve(C, fi.innovations[j])
                    d2[t, j] = float(w @ w)
                    log_norm[j] = -0.5 * m * math.log(2.0 * math.pi) - float(np.sum(np.log(np.diag(C))))
            if pd[t] > 0:
                p_det = scan.detection_probability if self.detections_in_view else pd[t]
                logw[t] = np.where(d2[t] <= gamma, math.log(p_det) + log_norm - 0.5 * d2[t], -np.inf)
        gated = np.isfinite(logw)
        return Hypotheses(means, covs, Hs, Ss, nus, d2, gated, logw, log_miss, pd, vis, gamma, pair_S, scan.noise)
