r"""Radio fingerprint localization (WiFi or iBeacon RSSI) by weighted k nearest neighbours, with an honest covariance.

**Fingerprints.** Each training scan is a vector of RSSI [dBm] over every transmitter seen in
training, ``missing`` (default -100 dBm) where it was not heard, at a known position ``p_i``.

**Distance.** A query scan ``q`` over the transmitters it heard (and that training knows), ``J``:
``d_i = mean_{j in J} |q_j - F_ij|`` (unheard entries of the fingerprint count as ``missing``).

**Estimate.** The ``k`` nearest fingerprints ``i_1..i_k`` with weights ``w = 1 / (d + eps)``
normalized: ``p_hat = sum w_l p_{i_l}``.

**Covariance (honest).** ``C = c^2 (S + s0^2 I)``, ``S`` the weighted spread of the ``k`` neighbours
around ``p_hat``; the scale ``c`` is calibrated on the training data itself by leave-one-walk-out
(each training scan located from the other walks' fingerprints) so that the average normalized
squared error ``(p - p_hat)^T C^-1 (p - p_hat)`` is 2, its expectation for a consistent 2-D Gaussian
(:meth:`FingerprintLocalizer.calibrate`). A query with no known transmitter returns ``None``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ValidationError
from dfusion.linalg import Array

__all__ = ["FingerprintLocalizer", "FingerprintFix"]


@dataclass
class FingerprintFix:
    """A fingerprint position: mean ``(2,)``, covariance ``(2, 2)``, transmitters used."""

    mean: Array
    cov: Array
    n_used: int


class FingerprintLocalizer:
    """Weighted k-NN fingerprint localizer (module docstring).

    Parameters
    ----------
    scans : list of dict
        Training scans, transmitter id -> RSSI [dBm].
    positions : (N, 2) array
        Where each training scan was taken.
    groups : (N,) array, optional
        Walk index of each scan (for :meth:`calibrate`).
    k, missing, s0, eps : settings
    """

    def __init__(self, scans: list[dict[str, float]], positions: ArrayLike, groups: ArrayLike | None = None, *,
                 k: int = 4, missing: float = -100.0, s0: float = 1.0, eps: float = 1e-3,
                 min_common: int = 1) -> None:
        p = np.asarray(positions, dtype=float)
        if len(scans) == 0 or p.shape != (len(scans), 2):
            raise ValidationError(f"need one (x, y) per training scan, got {len(scans)} scans and {p.shape}")
        if k < 1:
            raise ValidationError(f"k must be >= 1, got {k}")
        ids = sorted({a for s in scans for a in s})
        self.index = {a: j for j, a in enumerate(ids)}
        F = np.full((len(scans), len(ids)), float(missing))
        for i, s in enumerate(scans):
            for a, r in s.items():
                F[i, self.index[a]] = r
        self.F = F
        self.positions = p
        self.groups = None if groups is None else np.asarray(groups)
        self.k, self.missing, self.s0, self.eps = int(k), float(missing), float(s0), float(eps)
        self.min_common = int(min_common)
        self.scale = 1.0

    def _query(self, scan: dict[str, float], exclude: Array | None = None) -> FingerprintFix | None:
        js, zs = [], []
        for a, r in scan.items():
            j = self.index.get(a)
            if j is not None:
                js.append(j)
                zs.append(r)
        if len(js) < self.min_common:
            return None
        d = np.mean(np.abs(self.F[:, js] - np.asarray(zs)), axis=1)
        if exclude is not None:
            d = np.where(exclude, np.inf, d)
        k = min(self.k, int(np.isfinite(d).sum()))
        if k == 0:
            return None
        nn = np.argpartition(d, k - 1)[:k]
        w = 1.0 / (d[nn] + self.eps)
        w /= w.sum()
        pts = self.positions[nn]
        m = w @ pts
        r = pts - m
        S = (r * w[:, None]).T @ r + self.s0 ** 2 * np.eye(2)
        return FingerprintFix(m, self.scale ** 2 * 0.5 * (S + S.T), len(js))

    def locate(self, scan: dict[str, float]) -> FingerprintFix | None:
        """The fix of one scan (None if no transmitter of it is known)."""
        return self._query(scan)

    def calibrate(self, target: float = 2.0) -> float:
        """Set :attr:`scale` so that the leave-one-walk-out mean NEES of the training scans is ``target``
        (needs ``groups``); returns the scale. Each training scan is located from the scans of the
        other walks only (its own walk's scans are excluded: they were taken at nearly the same place)."""
        if self.groups is None:
            raise ValidationError("calibrate() needs the walk index of each training scan (groups)")
        self.scale = 1.0
        ids = np.array(sorted(self.index, key=self.index.get))  # transmitter id of each column
        nees = []
        for i in range(self.F.shape[0]):
            heard = self.F[i] > self.missing
            scan = dict(zip(ids[heard], self.F[i, heard]))
            fix = self._query(scan, exclude=self.groups == self.groups[i])
            if fix is None:
                continue
            e = self.positions[i] - fix.mean
            nees.append(float(e @ np.linalg.solve(fix.cov, e)))
        if not nees:
            raise ValidationError("no training scan could be located from the other walks")
        self.scale = float(np.sqrt(np.mean(nees) / target))
        return self.scale
