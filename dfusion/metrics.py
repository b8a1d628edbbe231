"""Accuracy and consistency metrics.

* RMSE of the position: ``sqrt(mean_k ||p_k - p^true_k||^2)``.
* NEES: ``e_k^T P_k^-1 e_k`` with ``e_k = x_k - x^true_k`` (Bar-Shalom, Li &
  Kirubarajan 2001, sec. 5.4.2); a consistent filter has ``E[NEES] = n``.
* The chi-square interval of an average of ``M`` independent NEES values:
  ``[chi2.ppf(a/2, n M), chi2.ppf(1 - a/2, n M)] / M``.

Multi-target: GOSPA and its parts (:func:`gospa`), CLEAR MOT and IDF1 (:func:`identity_metrics`),
network label agreement (:func:`label_agreement`); see ``docs/multi-target.md``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Hashable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from dfusion.assignment import gated_assignment
from dfusion.linalg import Array

__all__ = ["rmse", "nees", "chi2_interval", "error_stats", "GOSPA", "gospa", "TrackingFrame", "IdentityMetrics",
           "identity_metrics", "FrameMatch", "clear_mot_matches", "LabelAgreement", "label_agreement"]


def rmse(est: Array, truth: Array, axes: int) -> float:
    """Position RMSE over time (first ``axes`` components)."""
    d = np.asarray(est)[:, :axes] - np.asarray(truth)[:, :axes]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def nees(est: Array, cov: Array, truth: Array, residual=None) -> Array:
    """NEES of every time step, through Cholesky solves."""
    e = np.asarray(est) - np.asarray(truth)
    if residual is not None:
        e = residual(np.asarray(est), np.asarray(truth))
    L = np.linalg.cholesky(cov)
    w = np.linalg.solve(L, e[..., None])[..., 0]
    return np.sum(w * w, axis=-1)


def chi2_interval(dof: int, samples: int, level: float = 0.95) -> tuple[float, float]:
    """Interval containing the average of ``samples`` chi-square(``dof``) values with probability ``level``."""
    a = 1.0 - level
    return (chi2.ppf(a / 2, dof * samples) / samples, chi2.ppf(1 - a / 2, dof * samples) / samples)


def error_stats(errors: Array) -> dict[str, float]:
    """RMSE, median, mean and 90th percentile of horizontal errors (m)."""
    e = np.asarray(errors, dtype=float)
    return {"rmse": float(np.sqrt(np.mean(e * e))), "median_error": float(np.median(e)),
            "mean_error": float(np.mean(e)), "p90_error": float(np.percentile(e, 90)), "n": int(e.size)}


# --- multi-target metrics -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GOSPA:
    r"""The GOSPA distance of one frame and its parts (``alpha = 2``).

    Rahmathullah, García-Fernández & Svensson, "Generalized optimal sub-pattern assignment
    metric", FUSION 2017, eq. (1) and Proposition 1: for truth ``X = {x_1..x_n}``, estimates
    ``Y = {y_1..y_m}``, cut-off ``c > 0``, order ``p >= 1`` and ``alpha = 2``::

        d(X, Y) = min_gamma ( sum_{(i,j) in gamma} d(x_i, y_j)^p + c^p / 2 (|X| + |Y| - 2 |gamma|) )^(1/p)

    over partial assignments ``gamma`` of pairs with ``d(x_i, y_j) < c``: the localization
    error of assigned pairs, ``c^p / 2`` per missed target and per false estimate.
    ``localization``, ``missed`` and ``false`` are the three sums (in units of ``m^p``);
    ``distance`` is ``(localization + missed + false)^(1/p)``.
    """

    distance: float
    localization: float
    missed: float
    false: float
    n_missed: int
    n_false: int


def gospa(truth: Array, estimates: Array, c: float = 2.0, p: float = 1.0) -> GOSPA:
    """GOSPA (``alpha = 2``) of positions ``truth`` (n, d) and ``estimates`` (m, d); see :class:`GOSPA`.

    The optimal ``gamma`` is a ``linear_sum_assignment`` on ``min(d, c)^p``: a pair at ``d >= c``
    costs ``c^p``, the same as leaving both unassigned, so it is counted as one missed and one false.
    """
    if not (np.isfinite(c) and c > 0 and np.isfinite(p) and p >= 1):
        raise ValueError(f"GOSPA needs c > 0 and p >= 1, got c={c!r}, p={p!r}")
    X = np.asarray(truth, dtype=float)
    Y = np.asarray(estimates, dtype=float)
    X = X.reshape(len(X), -1) if X.size else np.zeros((0, 1))
    Y = Y.reshape(len(Y), -1) if Y.size else np.zeros((0, X.shape[1]))
    n, m = len(X), len(Y)
    half = c**p / 2.0
    matched = 0
    loc = 0.0
    if n and m:
        D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=2)
        r, k = linear_sum_assignment(np.minimum(D, c) ** p)
        close = D[r, k] < c
        matched = int(close.sum())
        loc = float(np.sum(D[r, k][close] ** p))
    missed, false = half * (n - matched), half * (m - matched)
    return GOSPA(float((loc + missed + false) ** (1.0 / p)), loc, missed, false, n - matched, m - matched)


@dataclass(frozen=True)
class TrackingFrame:
    """One frame of truth and estimates for the identity metrics: ids and (n, d) positions of each."""

    truth_ids: Sequence[Hashable]
    truth: Array
    track_ids: Sequence[Hashable]
    tracks: Array


@dataclass(frozen=True)
class IdentityMetrics:
    r"""CLEAR MOT and identity scores of a tracking run.

    * CLEAR MOT (Bernardin & Stiefelhagen, "Evaluating multiple object tracking performance:
      the CLEAR MOT metrics", EURASIP J. Image Video Process. 2008): per frame, a truth
      keeps the track it was matched to in its previous match if they are still within the
      threshold; the others are matched by a minimum-distance assignment among pairs within
      the threshold. A truth matched to a track other than its previous match is an
      identity switch. ``MOTA = 1 - (misses + false positives + switches) / truth count``;
      ``MOTP`` is the mean distance of matched pairs.
    * IDF1 (Ristani, Solera, Zou, Cucchiara & Tomasi, "Performance measures and a data set
      for multi-target, multi-camera tracking", ECCV Workshops 2016): each truth identity
      is assigned to at most one track identity for the whole run so as to maximize ``IDTP``,
      the number of frames in which they are within the threshold;
      ``IDF1 = 2 IDTP / (truth count + track count)``.

    Counts are over (object, frame) pairs; ``switches_by_truth`` gives the switches of each
    truth identity (those with none are absent).
    """

    mota: float
    motp: float
    idf1: float
    switches: int
    misses: int
    false_positives: int
    matches: int
    truth_count: int
    track_count: int
    switches_by_truth: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FrameMatch:
    """One (truth, track) pair matched in a frame by the CLEAR MOT rule (:func:`clear_mot_matches`)."""

    truth_id: Hashable
    track_id: Hashable
    distance: float
    switched: bool


def clear_mot_matches(frames: Sequence[TrackingFrame], threshold: float = 1.0) -> list[list[FrameMatch]]:
    """The CLEAR MOT matching of every frame (see :class:`IdentityMetrics`): per frame, a truth
    keeps its previous match while they are within ``threshold``; the other truths and tracks
    are paired by a minimum-distance assignment among pairs within ``threshold``. A truth
    matched to another track than its previous match is a switch (``FrameMatch.switched``).
    The one home of this rule: :func:`identity_metrics` counts from it, the identity timeline
    (``dfusion.viz.tracks``) draws it."""
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be positive, got {threshold!r}")
    last: dict[Hashable, Hashable] = {}
    out: list[list[FrameMatch]] = []
    for f in frames:
        gids, hids = list(f.truth_ids), list(f.track_ids)
        X, Y = _points(f.truth, len(gids)), _points(f.tracks, len(hids))
        D = (np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=2) if len(gids) and len(hids)
             else np.zeros((len(gids), len(hids))))
        ok = D <= threshold
        pairs = []
        free_g, free_h = set(range(len(gids))), set(range(len(hids)))
        hindex = {h: j for j, h in enumerate(hids)}
        for i, g in enumerate(gids):
            j = hindex.get(last.get(g, _NONE), -1)
            if j >= 0 and ok[i, j] and j in free_h:
                pairs.append((i, j, False))
                free_g.discard(i)
                free_h.discard(j)
        gi, hj = sorted(free_g), sorted(free_h)
        if gi and hj:
            sub = D[np.ix_(gi, hj)]
            for a, b in zip(*gated_assignment(sub, sub <= threshold)):
                g = gids[gi[a]]
                pairs.append((gi[a], hj[b], g in last and last[g] != hids[hj[b]]))
        for i, j, _ in pairs:
            last[gids[i]] = hids[j]
        out.append([FrameMatch(gids[i], hids[j], float(D[i, j]), bool(sw)) for i, j, sw in pairs])
    return out


def identity_metrics(frames: Sequence[TrackingFrame], threshold: float = 1.0) -> IdentityMetrics:
    """CLEAR MOT (MOTA, MOTP, switches) and IDF1 of ``frames``; pairs match within ``threshold`` (see :class:`IdentityMetrics`)."""
    matched = clear_mot_matches(frames, threshold)
    by_truth: dict[Hashable, int] = {}
    switches = misses = fps = matches = n_truth = n_tracks = 0
    dist_sum = 0.0
    co: dict[tuple[Hashable, Hashable], int] = {}
    truth_frames: dict[Hashable, int] = {}
    track_frames: dict[Hashable, int] = {}
    for f, pairs in zip(frames, matched):
        gids, hids = list(f.truth_ids), list(f.track_ids)
        X, Y = _points(f.truth, len(gids)), _points(f.tracks, len(hids))
        n_truth += len(gids)
        n_tracks += len(hids)
        for g in gids:
            truth_frames[g] = truth_frames.get(g, 0) + 1
        for h in hids:
            track_frames[h] = track_frames.get(h, 0) + 1
        if len(gids) and len(hids):
            D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=2)
            for i, j in zip(*np.nonzero(D <= threshold)):
                key = (gids[i], hids[j])
                co[key] = co.get(key, 0) + 1
        switches += sum(p.switched for p in pairs)
        for p in pairs:
            if p.switched:
                by_truth[p.truth_id] = by_truth.get(p.truth_id, 0) + 1
        dist_sum += sum(p.distance for p in pairs)
        matches += len(pairs)
        misses += len(gids) - len(pairs)
        fps += len(hids) - len(pairs)
    idtp = 0
    if co:
        g_list = sorted(truth_frames, key=repr)
        h_list = sorted(track_frames, key=repr)
        gpos = {g: i for i, g in enumerate(g_list)}
        hpos = {h: j for j, h in enumerate(h_list)}
        C = np.zeros((len(g_list), len(h_list)))
        for (g, h), v in co.items():
            C[gpos[g], hpos[h]] = v
        r, k = linear_sum_assignment(C, maximize=True)
        idtp = int(C[r, k].sum())
    total = n_truth + n_tracks
    return IdentityMetrics(
        mota=float(1.0 - (misses + fps + switches) / n_truth) if n_truth else float("nan"),
        motp=dist_sum / matches if matches else float("nan"),
        idf1=2.0 * idtp / total if total else 1.0,
        switches=int(switches), misses=int(misses), false_positives=int(fps), matches=int(matches),
        truth_count=int(n_truth), track_count=int(n_tracks), switches_by_truth=by_truth)


_NONE = object()


def _points(a: Array, n: int) -> Array:
    """``a`` as ``n`` rows of coordinates (an empty array for ``n = 0``)."""
    a = np.asarray(a, dtype=float)
    return a.reshape(n, -1) if n else a.reshape(0, a.shape[-1] if a.ndim == 2 else 0)


@dataclass(frozen=True)
class LabelAgreement:
    """Network label agreement (:func:`label_agreement`)."""

    agreement: float
    agreeing: int
    compared: int
    seen: int
    #: per frame: (agreeing, compared) (the agreement over time: ``agreeing / compared`` where ``compared > 0``)
    per_frame: tuple[tuple[int, int], ...] = ()


def label_agreement(truth_ids: Sequence[Sequence[Hashable]], truth: Sequence[Array],
                    nodes: Sequence[Sequence[tuple[Sequence[Hashable], Array]]], threshold: float = 1.0) -> LabelAgreement:
    """Share of the time all nodes give a truth the same identity.

    ``truth_ids[k]``, ``truth[k]``: the truths of frame ``k``; ``nodes[a][k] = (track_ids, positions)``
    of node ``a`` at frame ``k``. In each frame each node's tracks are assigned to the truths
    (minimum total distance, pairs within ``threshold``). A (truth, frame) pair is *compared*
    when every node has a track assigned to that truth, and *agrees* when these tracks
    all carry the same identity; ``agreement = agreeing / compared`` (1 when nothing is
    compared). ``seen`` counts the pairs where at least one node has a track on the truth.
    """
    if not nodes:
        raise ValueError("label_agreement needs at least one node")
    agreeing = compared = seen = 0
    per_frame = []
    for k, (gids, X) in enumerate(zip(truth_ids, truth)):
        agreeing_k = compared_k = 0
        X = _points(X, len(gids))
        labels: list[dict[int, Hashable]] = []
        for node in nodes:
            hids, Y = node[k]
            Y = _points(Y, len(hids))
            got: dict[int, Hashable] = {}
            if len(gids) and len(hids):
                D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=2)
                got = {int(i): hids[j] for i, j in zip(*gated_assignment(D, D <= threshold))}
            labels.append(got)
        for i in range(len(gids)):
            have = [lab[i] for lab in labels if i in lab]
            seen += bool(have)
            if len(have) == len(nodes):
                compared_k += 1
                agreeing_k += all(h == have[0] for h in have)
        per_frame.append((agreeing_k, compared_k))
        agreeing += agreeing_k
        compared += compared_k
    return LabelAgreement(agreeing / compared if compared else 1.0, agreeing, compared, seen, tuple(per_frame))
