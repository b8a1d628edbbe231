r"""Data associators: which detection of a scan is which track's.

Both take the :class:`~dfusion.tracking.gating.Hypotheses` of a scan and return an
:class:`Association`: for every track ``t`` the weight ``beta_tj`` of each detection ``j``
and ``beta_t0`` of none. The per-track update is then the PDA update with these weights
(:func:`dfusion.estimation.pda_moments`); for GNN they are 0 or 1 (a Kalman update).

**GNN** (global nearest neighbour; Blackman & Popoli, *Design and Analysis of Modern
Tracking Systems*, 1999, sec. 6.4): the single joint hypothesis of largest probability,
``max prod_t g_t a(t)``, i.e. the assignment minimizing ``sum_t -log g_t a(t)``, solved with
:func:`dfusion.assignment.gated_assignment` (``linear_sum_assignment`` through allowed pairs
only) on the ``T x (k + T)`` matrix whose first ``k``
columns are ``-log g_tj`` (``inf`` outside the gate) and whose last ``T`` columns hold
``-log g_t0`` on the diagonal (track ``t`` missed) and ``inf`` elsewhere.

**JPDA** (Bar-Shalom, Daum & Huang 2009, eq. 42-47; Fortmann, Bar-Shalom & Scheffe,
IEEE J. Oceanic Eng. 8(3), 1983): the marginal probabilities over every feasible joint
hypothesis ``theta``::

    beta_tj = sum_{theta: theta(t) = j} p(theta),   p(theta) = prod_t g_t theta(t) / Z

computed exactly by the *efficient hypothesis management* net of Maskell, Briers & Wright
("Fast mutual exclusion", Proc. SPIE 5428, 2004; Horridge & Maskell, "Real-time tracking
of hundreds of targets with efficient exact JPDAF implementation", FUSION 2006) on each
cluster of tracks that share gated detections (clusters are independent: ``Z`` factorizes).
Tracks are taken in order; the net's nodes of layer ``i`` are the sets of detections used
by tracks ``< i`` *that tracks ``>= i`` can still use* (other used detections no longer
constrain anything, so hypotheses that differ only there are merged). A forward pass sums
``F`` over the paths into a node, a backward pass ``B`` over the paths out of it, and
``beta_tj = sum_nodes F(node) g_tj B(child) / Z``. The cost grows with the number of
distinct nodes, not of joint hypotheses (exponential only in how many detections a
cluster's tracks share at once).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from dfusion.assignment import gated_assignment

from dfusion.linalg import Array
from dfusion.tracking.gating import Hypotheses

__all__ = ["Association", "DataAssociator", "GNN", "JPDA", "gated_clusters", "ehm_marginals"]


@dataclass(frozen=True)
class Association:
    """Weights of one scan: ``weights[t, j] = beta_tj``, ``miss[t] = beta_t0`` (each row sums to 1).

    A track that takes no part (out of view) has ``miss = 1`` and ``active = False``.
    """

    weights: Array
    miss: Array
    active: Array

    @classmethod
    def none(cls, hyp: Hypotheses) -> "Association":
        """Every track missed (``beta_t0 = 1``), to be filled in by an associator; ``active``: tracks in view."""
        T, k = hyp.shape
        return cls(np.zeros((T, k)), np.ones(T), hyp.detection > 0)

    def hit(self, t: int) -> bool:
        """Whether track ``t`` counts as detected in this scan: ``beta_t0 < 1/2``."""
        return bool(self.active[t] and self.miss[t] < 0.5)


class DataAssociator(ABC):
    """Component kind: association weights of every track with every detection of a scan."""

    @abstractmethod
    def associate(self, hyp: Hypotheses) -> Association:
        """The association of one scan's hypotheses."""


class GNN(DataAssociator):
    """Global nearest neighbour: the most probable joint hypothesis (module docstring)."""

    def associate(self, hyp: Hypotheses) -> Association:
        out = Association.none(hyp)
        W, miss, k = out.weights, out.miss, hyp.shape[1]
        rows = np.flatnonzero(out.active)
        if rows.size:
            cost = np.full((rows.size, k + rows.size), np.inf)
            cost[:, :k] = -hyp.log_weight[rows]
            cost[np.arange(rows.size), k + np.arange(rows.size)] = -hyp.log_miss[rows]
            for i, j in zip(*gated_assignment(cost)):   # gated pairs and misses only
                if j < k:
                    W[rows[i], j] = 1.0
                    miss[rows[i]] = 0.0
        return out


def gated_clusters(gated: Array) -> list[tuple[Array, Array]]:
    """Independent groups ``(tracks, detections)``: connected components of the gate's bipartite graph.

    Every track with at least one gated detection is in exactly one group; detections gated
    by no track are in none.
    """
    T, k = gated.shape
    parent = list(range(T))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for j in range(k):
        ts = np.flatnonzero(gated[:, j])
        for t in ts[1:]:
            ra, rb = find(int(ts[0])), find(int(t))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for t in range(T):
        if gated[t].any():
            groups.setdefault(find(t), []).append(t)
    out = []
    for ts in groups.values():
        tr = np.array(ts)
        out.append((tr, np.flatnonzero(gated[tr].any(axis=0))))
    return out


def ehm_marginals(weight: Array, miss: Array) -> tuple[Array, Array]:
    """Exact JPDA marginals of one cluster by the EHM net (module docstring).

    ``weight`` (T, k): ``g_tj`` (0 outside the gate), ``miss`` (T,): ``g_t0``. Returns
    ``(beta (T, k), beta0 (T,))``. Each track's weights may be scaled by any positive
    constant (the marginals do not change); callers scale each row to a maximum of 1.
    """
    T, k = weight.shape
    options = [[(-1, float(miss[t]))] + [(int(j), float(weight[t, j])) for j in np.flatnonzero(weight[t] > 0)]
               for t in range(T)]
    masks = [sum(1 << j for j, _ in opts if j >= 0) for opts in options]
    future = [0] * (T + 1)                       # detections tracks >= i can use
    for i in range(T - 1, -1, -1):
        future[i] = future[i + 1] | masks[i]

    def moves(i: int, key: int):
        """``(detection, weight, child node)`` of every option of track ``i`` at node ``key``."""
        keep = future[i + 1]
        for j, w in options[i]:
            if j < 0:
                yield j, w, key & keep
            elif not key >> j & 1:
                yield j, w, (key | 1 << j) & keep

    layers: list[dict[int, float]] = [{0: 1.0}]
    for i in range(T):
        nxt: dict[int, float] = {}
        for key, f in layers[i].items():
            for _, w, child in moves(i, key):
                nxt[child] = nxt.get(child, 0.0) + f * w
        layers.append(nxt)
    back: dict[int, float] = {0: 1.0}           # layer T has the one node 0
    beta = np.zeros((T, k))
    beta0 = np.zeros(T)
    for i in range(T - 1, -1, -1):
        here: dict[int, float] = {}
        for key, f in layers[i].items():
            total = 0.0
            for j, w, child in moves(i, key):
                through = w * back[child]
                total += through
                if j >= 0:
                    beta[i, j] += f * through
                else:
                    beta0[i] += f * through
            here[key] = total
        back = here
    Z = back[0]
    return beta / Z, beta0 / Z


class JPDA(DataAssociator):
    """Joint probabilistic data association, exact, by EHM on independent clusters (module docstring)."""

    def associate(self, hyp: Hypotheses) -> Association:
        out = Association.none(hyp)
        W, miss = out.weights, out.miss
        gated = hyp.gated & out.active[:, None]
        for tr, dets in gated_clusters(gated):
            logs = np.concatenate([hyp.log_weight[np.ix_(tr, dets)], hyp.log_miss[tr, None]], axis=1)
            logs = logs - logs.max(axis=1, keepdims=True)      # per-track scaling (marginals unchanged)
            g = np.exp(logs)
            g[:, :-1] *= gated[np.ix_(tr, dets)]
            b, b0 = ehm_marginals(g[:, :-1], g[:, -1])
            W[np.ix_(tr, dets)] = b
            miss[tr] = b0
        return out
