r"""Track-to-track association: which two tracks of a node are one target.

In a network every node may start a track for a person its own sensors see first, so one
person can hold several identities for a while: node ``a``'s track and node ``b``'s reach
every node. :class:`TrackToTrackAssociator` finds such pairs among a node's fused tracks.

**Test.** Two tracks ``i, j`` with position estimates ``(p_i, P_i)``, ``(p_j, P_j)`` at
the same time are compared by

.. math:: d^2 = (p_i - p_j)^T (P_i + P_j)^{-1} (p_i - p_j)

the test statistic of the hypothesis that both estimate one position (Bar-Shalom, Willett &
Tian, *Tracking and Data Fusion*, 2011, sec. 9.2 "track-to-track association"; with the
cross-covariance of the two estimates taken as zero: the tracks of one person hold disjoint
measurements and share only the broad common prior, so ``P_i + P_j`` slightly overstates
the covariance of the difference and the test is conservative). Over ``N = confirm``
consecutive checks at which the positions are within ``max_distance`` metres, the pair is
one target when

.. math:: \sum_{k=1}^{N} d_k^2 \le \chi^2_{gate}(N \cdot dim)

the same test on the stacked differences of ``N`` checks (taken as independent: a
sequential test over a window, sec. 9.2's "track history"), which one unlucky check does not
break as a test of every check alone would.

**Rule.** A pair is declared one target when the windowed test above passes and it was never
seen *distinct* in that time: two tracks that both took
a detection of one scan of one sensor are two targets (a sensor sees a target once per
scan), and such a pair is not merged for ``distinct_for`` seconds. The pairs found are
returned in a deterministic order; which of the two survives is the node's rule
(:mod:`dfusion.fusion.tracking_node`: the one born first, then the smaller identity).
"""
from __future__ import annotations

import math
from typing import Iterable, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array, chi2_isf
from dfusion.tracking.track import TrackId

__all__ = ["TrackToTrackAssociator"]


class TrackToTrackAssociator:
    """Finds pairs of tracks that are one target (module docstring).

    Parameters
    ----------
    gate : probability of the chi-square gate on ``d^2`` (position axes).
    confirm : consecutive checks (within ``max_distance``) of the windowed test.
    max_distance : largest distance (m) between the two position estimates of a pair.
    distinct_for : seconds a pair seen distinct (both detected in one scan) is not merged.
    axes : position axes of the state (the first ``axes`` components).
    """

    def __init__(self, gate: float = 0.99, confirm: int = 5, max_distance: float = 1.5, distinct_for: float = 3.0,
                 axes: int = 2) -> None:
        if not 0.0 < gate < 1.0:
            raise ValidationError(f"gate must be in (0, 1), got {gate!r}")
        if not (isinstance(confirm, int) and confirm >= 1):
            raise ValidationError(f"confirm must be an integer >= 1, got {confirm!r}")
        for name, v in (("max_distance", max_distance), ("distinct_for", distinct_for)):
            if not (math.isfinite(v) and v >= 0):
                raise ValidationError(f"{name} must be finite and >= 0, got {v!r}")
        self.gate, self.confirm = float(gate), confirm
        self.max_distance, self.distinct_for, self.axes = float(max_distance), float(distinct_for), int(axes)
        self.threshold = chi2_isf(1.0 - self.gate, self.axes * self.confirm)
        self._close: dict[tuple[TrackId, TrackId], list[float]] = {}
        self._distinct: dict[tuple[TrackId, TrackId], float] = {}

    def distinct(self, tracks: Iterable[TrackId], t: float) -> None:
        """These tracks took detections of one scan at time ``t``: every pair of them is two targets."""
        ids = sorted(set(tracks))
        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                pair = (ids[a], ids[b])
                self._distinct[pair] = float(t)
                self._close.pop(pair, None)

    def forget(self, track: TrackId) -> None:
        """``track`` ended: its pairs are forgotten."""
        for book in (self._close, self._distinct):
            for pair in [p for p in book if track in p]:
                del book[pair]

    def check(self, estimates: Mapping[TrackId, tuple[Array, Array]], t: float) -> list[tuple[TrackId, TrackId]]:
        """One check of every pair of ``estimates`` (``{track: (mean, cov)}`` at time ``t``);
        returns the pairs declared one target now, each ``(smaller id, larger id)``, sorted."""
        ids = sorted(estimates)
        k = self.axes
        self._distinct = {p: s for p, s in self._distinct.items() if t - s < self.distinct_for}
        if len(ids) < 2:
            self._close.clear()
            return []
        pos = np.array([np.asarray(estimates[i][0], dtype=float)[:k] for i in ids])
        cov = np.array([np.asarray(estimates[i][1], dtype=float)[:k, :k] for i in ids])
        diff = pos[:, None, :] - pos[None, :, :]
        S = cov[:, None] + cov[None, :]
        iu = np.triu_indices(len(ids), 1)
        near = np.linalg.norm(diff[iu], axis=1) <= self.max_distance
        d2 = np.full(near.shape, np.inf)
        if near.any():
            sel = np.flatnonzero(near)
            a, b = iu[0][sel], iu[1][sel]
            d2[sel] = np.einsum("ki,ki->k", diff[a, b], np.linalg.solve(S[a, b], diff[a, b][..., None])[..., 0])
        recent: dict[tuple[TrackId, TrackId], list[float]] = {}
        for a, b, value in zip(iu[0], iu[1], d2):
            pair = (ids[a], ids[b])
            if np.isfinite(value) and pair not in self._distinct:
                recent[pair] = (self._close.get(pair, []) + [float(value)])[-self.confirm:]
        self._close = recent
        found = sorted(p for p, v in recent.items() if len(v) == self.confirm and sum(v) <= self.threshold)
        for p in found:
            del self._close[p]
        return found
