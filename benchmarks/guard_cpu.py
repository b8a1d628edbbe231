"""CPU of the consistency test of neighbours' messages (``dfusion.fusion.guard``), per received message.

Copies of the same network (a chain of ``--nodes`` nodes, or a random tree with ``--tree``;
position sensors at 10 Hz, sends every 0.5 s, window ``--window`` states) are run in lockstep on
the same data: one with the current test; one with the implementation before 2026-11-25
(reproduced below: a smoothing pass without cached gains before and after the message, one
eigendecomposition per block in ``split_blocks`` and in the statistic); one with the test of
2026-11-28 before its covariance bounds (``exact``: the smoothed covariances of the whole pass
before the message, ``add_information_moments(exact_covariances=True)``, and the means computed
afresh before every message); one without a test. Each step the order of the copies
alternates, so the load of a shared machine hits all alike. Printed: median and mean CPU
(``process_time``) of ``FusionNode.receive`` per message for each, the test's own part and
the ratios, and the largest difference between the copies' statistics (they must agree to
rounding, and make the same decisions).

Usage: python benchmarks/guard_cpu.py [--nodes 2] [--tree] [--window 60] [--steps 600]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from dfusion.fusion import FusionNode
from dfusion.fusion.guard import (EIG_RTOL, NEGLIGIBLE, RANGE_TOL, GuardConfig, NeighbourGuard, block_eigen,
                                  information_statistic, split_blocks)
from dfusion.linalg import chi2_isf
from dfusion.models import ConstantVelocity, PositionSensor


# ------------------------------------------------------------------ the implementation before
def _old_smoothed(tr, k_from: int, covs: bool):
    m = len(tr.L)
    tr._forward(m)
    mu, P = tr.latest()
    means, cs = [mu], [P]
    for k in range(m - 2, k_from - 1, -1):
        ck, nxt = tr._cache[k], tr._cache[k + 1]
        F = tr.factors[k].F
        Cp = getattr(nxt, "_old_chol", None)     # cached with the forward terms, as it was
        if Cp is None:
            Cp = nxt._old_chol = np.linalg.cholesky(nxt.pred_cov)
        if covs:
            G = np.linalg.solve(Cp.T, np.linalg.solve(Cp, F @ ck.cov)).T
            mu = ck.mean + G @ (mu - nxt.pred_mean)
            P = 0.5 * (ck.cov + G @ (P - nxt.pred_cov) @ G.T)
            P = 0.5 * (P + P.T)
            cs.append(P)
        else:
            r = np.linalg.solve(Cp.T, np.linalg.solve(Cp, mu - nxt.pred_mean))
            mu = ck.mean + ck.cov @ (F.T @ r)
        means.append(mu)
    means.reverse()
    cs.reverse()
    return means, cs


def _old_moments(f, entries):
    with f._transaction():
        for t, _, _ in entries:
            if f.index_of(t) is None:
                f._insert(t)
        idx = [f.index_of(t) for t, _, _ in entries]
        k0 = min(idx)
        means0, covs0 = _old_smoothed(f._traj, k0, True)
        for k, (_, Lam, y) in zip(idx, entries):
            f._traj.add_information(k, Lam, y)
        means1, _ = _old_smoothed(f._traj, k0, False)
        out = ([means0[k - k0] for k in idx], [covs0[k - k0] for k in idx], [means1[k - k0] for k in idx])
        f._enforce_window()
    return out


def _old_split(entries):
    add, other = [], []
    for e in entries:
        w = np.linalg.eigvalsh(e[1])
        scale = float(np.max(np.abs(w))) if w.size else 0.0
        if scale > 0.0 and w[0] >= -EIG_RTOL * scale:
            add.append(e)
        elif scale > 0.0:
            other.append(e)
        elif np.any(e[2]):
            add.append(e)
    return add, other


def _old_statistic(entries, mu0, P0, mu1):
    stat, dof = 0.0, 0
    for (t, L, y), m0, C0, m1 in zip(entries, mu0, P0, mu1):
        w, V = np.linalg.eigh(0.5 * (L + L.T))
        scale = float(np.max(np.abs(w))) if w.size else 0.0
        pos = w > EIG_RTOL * scale if scale > 0 else np.zeros(w.shape, dtype=bool)
        Vp = V[:, pos]
        out = y - Vp @ (Vp.T @ y)
        if float(out @ C0 @ out) > RANGE_TOL:
            return math.inf, dof + int(pos.sum())
        if not pos.any():
            continue
        lam = w[pos]
        signal = lam * np.einsum("ij,jk,ki->i", Vp.T, C0, Vp)
        use = signal > NEGLIGIBLE
        if not use.any():
            continue
        Vu, lu = Vp[:, use], lam[use]
        zc = (Vu.T @ y) / lu
        stat += float(np.sum((zc - Vu.T @ m0) * lu * (zc - Vu.T @ m1)))
        dof += int(use.sum())
    return stat, dof


def _old_add_tested(node, entries):
    f = node.filter
    add, other = _old_split(entries)
    if other:
        f.add_information_batch(other, validate=False)
    if not add:
        return 0.0, 0, 0
    mu0, P0, mu1 = _old_moments(f, add)
    stat, dof = _old_statistic(add, mu0, P0, mu1)
    return stat, dof, len(add)


def _exact_add_tested(node, entries):
    """The test of 2026-11-28 before the covariance bounds: the exact smoothed covariances."""
    f = node.filter
    eigen = block_eigen(entries[0][1]) if len(entries) == 1 else None
    add, other = split_blocks(entries, eigen)
    if other:
        f.add_information_batch(other, validate=False)
    if not add:
        return 0.0, 0, 0
    f._traj._means = None   # (no means kept from the message before)
    mu0, P0, mu1 = f.add_information_moments(add, exact_covariances=True)
    stat, dof = information_statistic(add, mu0, P0, mu1, eigen)
    return stat, dof, len(add)


# ------------------------------------------------------------------ the run
class _Recording(NeighbourGuard):
    def __init__(self, nbrs, log):
        super().__init__(nbrs, GuardConfig())
        self.log = log

    def judge(self, j, stat, dof):
        if dof > 0:
            self.log.append((stat, dof))
        return super().judge(j, stat, dof)


def _network(n: int, window: int, log: list, lane: str, tree: bool) -> list[FusionNode]:
    """A chain, or a random tree (each node's parent drawn among the nodes before it, seed 1)."""
    motion = ConstantVelocity(2, 0.05)
    prior = (0.0, np.zeros(4), np.eye(4))
    names = [f"n{i}" for i in range(n)]
    rng = np.random.default_rng(1)
    parent = [None] + [int(rng.integers(i)) if tree else i - 1 for i in range(1, n)]
    nbrs = {i: [names[j] for j in range(n) if parent[j] == i] + ([names[parent[i]]] if i else []) for i in range(n)}
    nodes = []
    for i, name in enumerate(names):
        node = FusionNode(name, nbrs[i], motion, window=window, prior=prior, epoch=i + 1,
                          guard=_Recording(nbrs[i], log) if lane != "off" else None)
        if lane in ("old", "exact"):
            fn = _old_add_tested if lane == "old" else _exact_add_tested
            node._add_tested = (lambda nd, fn: (lambda entries: fn(nd, entries)))(node, fn)
        nodes.append(node)
    return nodes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, default=2)
    ap.add_argument("--tree", action="store_true", help="a random tree instead of a chain")
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--steps", type=int, default=600)
    args = ap.parse_args(argv)
    sensor = PositionSensor(2, 0.5)
    lanes = ("old", "exact", "new", "off")
    logs = {k: [] for k in lanes}
    nets = {k: _network(args.nodes, args.window, logs[k], k, args.tree) for k in lanes}
    cpu = {k: [] for k in lanes}
    rng = np.random.default_rng(0)
    warm = 2 * args.window
    for k in range(1, warm + args.steps + 1):
        t = round(0.1 * k, 9)
        z = [rng.normal(size=2) * 0.5 + [0.1 * t, 0.0] for _ in range(args.nodes)]
        order = lanes if k % 2 else lanes[::-1]
        for key in order:
            nodes = nets[key]
            for node, zi in zip(nodes, z):
                node.predict(t)
                node.update(t, zi, sensor)
            if k % 5:
                continue
            msgs = [(b, a.message_to(b.name)) for a in nodes for b in nodes if b.name in a.channels]
            for b, data in msgs:
                t0 = time.process_time()
                b.receive(data)
                dt = time.process_time() - t0
                if k > warm:
                    cpu[key].append(dt)
    stats = {k: np.array(logs[k]) for k in ("old", "exact", "new")}
    ref = stats["exact"]
    for k in ("old", "new"):
        assert stats[k].shape == ref.shape and np.array_equal(stats[k][:, 1], ref[:, 1]), \
            f"different tests or degrees of freedom ({k} against exact)"
    fin = np.isfinite(ref[:, 0])

    def rel(a):
        return np.max(np.abs(a[fin, 0] - ref[fin, 0]) / np.maximum(1.0, np.abs(ref[fin, 0])))

    ms = {k: np.array(cpu[k]) * 1e3 for k in lanes}
    own = {k: ms[k].mean() - ms["off"].mean() for k in ("old", "exact", "new")}
    shape = f"random tree of {args.nodes} nodes" if args.tree else f"chain of {args.nodes} nodes"
    print(f"{shape}, window {args.window}, {len(ms['new'])} messages received per copy, {len(ref)} tested")
    print("receive CPU ms per message (process_time):")
    print(f"{'copy':<34} {'median':>8} {'mean':>8} {'test':>8} {'test / now':>11}")
    label = {"old": "before 2026-11-25", "exact": "2026-11-28, exact covariances", "new": "now", "off": "no test"}
    for k in lanes:
        t = f"{own[k]:8.3f} {own[k] / max(own['new'], 1e-9):11.2f}" if k != "off" else f"{'-':>8} {'-':>11}"
        print(f"{label[k]:<34} {np.median(ms[k]):8.3f} {ms[k].mean():8.3f} {t}")
    dof = ref[:, 1].astype(int)
    c = np.array([chi2_isf(1e-3, int(d)) for d in dof])
    fails = {k: stats[k][:, 0] > c for k in stats}
    print(f"largest difference of the statistics from the exact copy's (relative, >= 1 absolute): "
          f"before 2026-11-25 {rel(stats['old']):.1e}, now {rel(stats['new']):.1e}; failures "
          f"{int(fails['old'].sum())} / {int(fails['exact'].sum())} / {int(fails['new'].sum())}, same messages: "
          f"{np.array_equal(fails['old'], fails['exact']) and np.array_equal(fails['new'], fails['exact'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
