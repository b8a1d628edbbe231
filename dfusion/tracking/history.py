r"""What a multi-target run produced, as plain data: every node's tracks over time, and the truth.

* :class:`TrackHistory`: per node, per time, the tracks as ``(TrackId, mean, cov)``. A
  tracker or a fusion node fills it with :meth:`TrackHistory.record` (for example after each
  frame: ``history.record("cam1", t, tracker.estimates())``); the metrics
  (:mod:`dfusion.metrics`), the figures (:mod:`dfusion.viz.tracks`) and the MCAP recording
  (:func:`dfusion.viz.foxglove.record_tracks_mcap`) read it.
* :class:`TruthPaths`: per target name, the times and positions where it exists (a person
  is born and dies); :meth:`TruthPaths.at` gives the targets present at a time.

The state's first two components are the position (m) and the covariance's first 2 x 2
block its covariance (the constant-velocity state ``[x, y, vx, vy]`` of the trackers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Hashable, Iterable, Sequence

import numpy as np

from dfusion.errors import ShapeError, TimeError, ValidationError
from dfusion.linalg import Array
from dfusion.metrics import IdentityMetrics, LabelAgreement, TrackingFrame, identity_metrics, label_agreement
from dfusion.tracking.track import TrackId

__all__ = ["TrackEstimate", "TrackHistory", "TruthPaths"]

#: One track at one time: its identity, mean and covariance.
TrackEstimate = tuple[TrackId, Array, Array]

_SAME_TIME = 1e-9   # seconds: two records closer than this are at one time


@dataclass
class TruthPaths:
    """The truth of every target: ``paths[name] = (t (K,), xy (K, 2))``, times increasing.

    A target exists from its first time to its last; in between, its position at a time
    between two samples is interpolated linearly (at a sample time it is the sample).
    """

    paths: dict[str, tuple[Array, Array]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, (t, xy) in list(self.paths.items()):
            t, xy = np.asarray(t, float).ravel(), np.asarray(xy, float)
            if xy.ndim != 2 or xy.shape != (len(t), 2) or len(t) == 0:
                raise ShapeError(f"truth of {name!r}: need times (K,) and positions (K, 2), K >= 1, "
                                 f"got {t.shape} and {xy.shape}")
            if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xy))):
                raise ValidationError(f"truth of {name!r} must be finite")
            if np.any(np.diff(t) <= 0):
                raise TimeError(f"truth of {name!r}: times must increase")
            self.paths[name] = (t, xy)

    def at(self, t: float) -> tuple[list[str], Array]:
        """Names and (n, 2) positions of the targets that exist at ``t``."""
        names, pos = [], []
        for name, (ts, xy) in self.paths.items():
            if ts[0] - _SAME_TIME <= t <= ts[-1] + _SAME_TIME:
                names.append(name)
                pos.append([np.interp(t, ts, xy[:, 0]), np.interp(t, ts, xy[:, 1])])
        return names, np.array(pos, float).reshape(-1, 2)


@dataclass
class TrackHistory:
    """Every node's tracks over time: ``nodes[node] = [(t, [(TrackId, mean, cov), ...]), ...]``, times increasing.

    :meth:`record` adds a node's tracks at a time (a second record at the same time replaces
    the first: the node's state after every scan of a frame). A node without a record at a
    time has no tracks then (:meth:`at`); nodes meant to be compared frame by frame (label
    agreement) record at the same frame times.
    """

    nodes: dict[str, list[tuple[float, list[TrackEstimate]]]] = field(default_factory=dict)

    def record(self, node: str, t: float, tracks: Iterable[Any]) -> None:
        """Record ``node``'s tracks at time ``t``: ``(TrackId, mean, cov)`` tuples (e.g.
        :meth:`~dfusion.tracking.MultiTargetTracker.estimates`) or objects with ``id`` and
        ``estimate()`` (:class:`~dfusion.tracking.Track`). Arrays are copied."""
        if not isinstance(node, str) or not node:
            raise ValidationError(f"node name must be a non-empty string, got {node!r}")
        t = float(t)
        if not math.isfinite(t):
            raise TimeError(f"record time must be finite, got {t!r}")
        rows: list[TrackEstimate] = []
        for tr in tracks:
            tid, mean, cov = (tr.id, *tr.estimate()) if hasattr(tr, "estimate") else tr
            mean, cov = np.array(mean, float).ravel(), np.array(cov, float)
            if mean.size < 2 or cov.shape != (mean.size, mean.size):
                raise ShapeError(f"track {tid}: need a mean (n >= 2) and an (n, n) covariance, "
                                 f"got {mean.shape}, {cov.shape}")
            rows.append((tid, mean, cov))
        if len({tid for tid, _, _ in rows}) != len(rows):
            raise ValidationError(f"{node} at t={t}: one identity recorded twice")
        series = self.nodes.setdefault(node, [])
        if series and t < series[-1][0] - _SAME_TIME:
            raise TimeError(f"{node}: record at t={t} is older than its last, t={series[-1][0]}")
        if series and abs(t - series[-1][0]) <= _SAME_TIME:
            series[-1] = (series[-1][0], rows)
        else:
            series.append((t, rows))

    def times(self, node: str | None = None) -> Array:
        """The record times of ``node`` (``None``: of every node, merged)."""
        if node is not None:
            return np.array([t for t, _ in self.nodes[node]], float)
        ts = sorted({t for series in self.nodes.values() for t, _ in series})
        merged: list[float] = []
        for t in ts:
            if not merged or t - merged[-1] > _SAME_TIME:
                merged.append(t)
        return np.array(merged, float)

    def at(self, node: str, t: float) -> list[TrackEstimate]:
        """``node``'s tracks recorded at ``t`` (empty when it has no record then)."""
        series = self.nodes.get(node, [])
        k = int(np.searchsorted([s for s, _ in series], t - _SAME_TIME))
        return series[k][1] if k < len(series) and abs(series[k][0] - t) <= _SAME_TIME else []

    def positions(self, node: str, t: float) -> tuple[list[TrackId], Array]:
        """Identities and (n, 2) positions of ``node``'s tracks at ``t``."""
        rows = self.at(node, t)
        return [tid for tid, _, _ in rows], np.array([m[:2] for _, m, _ in rows], float).reshape(-1, 2)

    def paths(self, node: str) -> dict[TrackId, tuple[Array, Array, Array]]:
        """``node``'s tracks one by one: identity -> (times (K,), means (K, n), covariances (K, n, n))."""
        got: dict[TrackId, tuple[list, list, list]] = {}
        for t, rows in self.nodes[node]:
            for tid, m, P in rows:
                ts, ms, Ps = got.setdefault(tid, ([], [], []))
                ts.append(t)
                ms.append(m)
                Ps.append(P)
        return {tid: (np.array(ts), np.array(ms), np.array(Ps)) for tid, (ts, ms, Ps) in got.items()}

    def identities(self) -> list[Hashable]:
        """Every identity any node recorded, sorted."""
        return sorted({tid for series in self.nodes.values() for _, rows in series for tid, _, _ in rows}, key=_order)

    def frames(self, node: str, truth: TruthPaths, times: Sequence[float] | None = None) -> list[TrackingFrame]:
        """The truth and ``node``'s tracks at each time (default: the node's record times), for the metrics."""
        ts = self.times(node) if times is None else times
        return [TrackingFrame(*truth.at(float(t)), *self.positions(node, float(t))) for t in ts]

    def identity_metrics(self, node: str, truth: TruthPaths, threshold: float = 1.0) -> IdentityMetrics:
        """CLEAR MOT and IDF1 of ``node`` (:func:`dfusion.metrics.identity_metrics`)."""
        return identity_metrics(self.frames(node, truth), threshold)

    def label_agreement(self, truth: TruthPaths, threshold: float = 1.0,
                        nodes: Sequence[str] | None = None) -> tuple[Array, LabelAgreement]:
        """The times (every node's record times, merged) and the network label agreement
        over them (:func:`dfusion.metrics.label_agreement`; ``per_frame`` follows the times)."""
        names = list(self.nodes) if nodes is None else list(nodes)
        ts = self.times()
        at = [truth.at(float(t)) for t in ts]
        per_node = [[self.positions(n, float(t)) for t in ts] for n in names]
        return ts, label_agreement([a[0] for a in at], [a[1] for a in at], per_node, threshold)


def _order(tid: Hashable) -> tuple:
    """Sort key of identities of mixed kinds (TrackId first, in their order, then by text)."""
    return (0, tid.origin, tid.serial, "") if isinstance(tid, TrackId) else (1, "", 0, str(tid))
