"""A hand-driven network of TrackingNodes with known association (identities given), lossy,
delaying, duplicating and reordering links, late measurements, track births at any node and
time, merges and deletions decided by random nodes; the reference is filterpy's Kalman filter
per track (prior: the common TrackPrior at the track's birth), independent of dfusion."""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from dfusion.fusion.tracking_node import TrackingNode, TrackPrior
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.tracking import TrackId
from tests.helpers.fusion_harness import Q_PSD, central_kalman

PRIOR = TrackPrior(position_std=50.0, velocity_std=10.0)


def track_kalman(measurements, born: float, t_end: float, prior: TrackPrior = PRIOR):
    """filterpy KalmanFilter from the common prior at ``born`` over ``(t, z, std)`` in time order, to ``t_end``."""
    return central_kalman(measurements, t_end, prior.at(born, 4))


@dataclass
class TrackSchedule:
    seed: int
    n: int = 4
    targets: int = 3
    steps: int = 25
    dt: float = 0.1
    meas_prob: float = 0.5
    max_meas_delay: float = 0.2
    send_every: int = 2
    drop: float = 0.2
    duplicate: float = 0.1
    max_latency: float = 0.25
    aliases: int = 0            # targets also observed under a second identity (by other nodes), merged later
    deletions: int = 0          # tracks deleted by a random node at a random step
    link_changes: float = 0.0   # chance per step that one link of a radio graph flips (links_change)
    key: bytes | None = None


@dataclass
class TrackRun:
    nodes: dict[str, TrackingNode]
    measurements: dict[TrackId, list]          # (t, z, std) per identity
    born: dict[TrackId, float]
    merged: dict[TrackId, TrackId]             # gone -> keep
    deleted: set[TrackId]
    t_end: float
    worst: float = np.inf                      # min over steps, nodes, tracks of eig(P_node - P_ref) / scale
    checks: int = 0
    stats: dict = field(default_factory=dict)

    def survivor(self, tid: TrackId) -> TrackId | None:
        while tid in self.merged:
            tid = self.merged[tid]
        return None if tid in self.deleted else tid

    def closure(self, keep: TrackId) -> list[TrackId]:
        return [tid for tid in self.born if self._root(tid) == keep]

    def _root(self, tid: TrackId) -> TrackId:
        while tid in self.merged:
            tid = self.merged[tid]
        return tid

    def reference(self, keep: TrackId, t: float, taken_before: float = np.inf):
        ms = [m for tid in self.closure(keep) for m in self.measurements[tid] if m[0] <= taken_before]
        return track_kalman(ms, self.born[keep], t)


def _node(name: str, nbrs, s: TrackSchedule, epoch: int) -> TrackingNode:
    return TrackingNode(name, sorted(nbrs), ConstantVelocity(2, Q_PSD), prior=PRIOR, window=5000, deleter=False,
                        merger=False, epoch=epoch, links_change=s.link_changes > 0, network_key=s.key, run="t",
                        hold=0.0)


def lossless_rounds(nodes: dict[str, TrackingNode], k: int, t: float | None = None) -> None:
    for _ in range(k):
        out = [(j, d) for n in sorted(nodes) for j, d in nodes[n].outgoing(t)]
        for j, d in out:
            nodes[j].receive(d)


def run_tracks(s: TrackSchedule) -> TrackRun:
    rng = np.random.default_rng(s.seed)
    names = [f"n{i}" for i in range(s.n)]
    if s.link_changes > 0:
        g = nx.gnp_random_graph(s.n, 0.6, seed=s.seed)
        links = {(f"n{a}", f"n{b}") for a, b in g.edges}
    else:
        tree = nx.random_labeled_tree(s.n, seed=s.seed) if s.n > 2 else nx.path_graph(2)
        links = {(f"n{a}", f"n{b}") if a < b else (f"n{b}", f"n{a}") for a, b in tree.edges}
    nbrs = {n: {x for l in links if n in l for x in l} - {n} for n in names}
    nodes = {n: _node(n, nbrs[n], s, i + 1) for i, n in enumerate(names)}
    stds = {n: float(rng.uniform(0.3, 1.5)) for n in names}
    sensors = {n: PositionSensor(2, stds[n]) for n in names}
    # identities: target k is TrackId(origin, k) started by a random node at a random step; an alias
    # of it is TrackId(other origin, 100 + k), born later, observed by another group of nodes
    targets = []
    for k in range(s.targets):
        origin = names[int(rng.integers(s.n))]
        targets.append((TrackId(origin, k), int(rng.integers(1, s.steps // 2))))
    aliases = {}
    for k in range(min(s.aliases, s.targets)):
        origin = names[int(rng.integers(s.n))]
        aliases[TrackId(origin, 100 + k)] = (targets[k][0], int(rng.integers(1, s.steps // 2)))
    born_step = {tid: st for tid, st in targets} | {a: st for a, (_, st) in aliases.items()}
    born = {tid: round(st * s.dt, 9) for tid, st in born_step.items()}
    merge_step = {a: int(rng.integers(max(born_step[a], born_step[orig]) + 1, s.steps))
                  for a, (orig, _) in aliases.items()}
    delete_step = {}
    # a track that is part of a merge is not deleted: a deletion and a merge of one track decided at
    # once by two nodes are resolved by what each node hears first (consistent, never double
    # counted, but with no one reference to compare with)
    paired = set(aliases) | {orig for orig, _ in aliases.values()}
    ids = sorted(set(born) - paired)
    for i in rng.permutation(len(ids))[:s.deletions]:
        tid = ids[int(i)]
        delete_step[tid] = int(rng.integers(born_step[tid] + 2, s.steps + 1))
    run = TrackRun(nodes, {tid: [] for tid in born}, born, {}, set(), 0.0)
    in_flight: list = []
    waiting: list = []
    counter = itertools.count()
    truth = {tid: rng.normal(0, 20, size=2) for tid, _ in targets}
    t = 0.0

    def flip_link() -> None:
        a, b = sorted(rng.choice(names, size=2, replace=False))
        if (a, b) in links:
            links.discard((a, b))
            nodes[a].link_down(b)
            nodes[b].link_down(a)
        else:
            links.add((a, b))
            nodes[a].link_up(b)
            nodes[b].link_up(a)

    for k in range(1, s.steps + 1):
        t = round(k * s.dt, 9)
        if s.link_changes and rng.random() < s.link_changes:
            flip_link()
        for n in names:
            nodes[n].predict(t)
        # measurements of live identities (an identity: its own origin's group measures it first)
        for tid in sorted(born):
            if born_step[tid] > k or run.survivor(tid) is None or tid in run.merged:
                continue
            for n in names:
                first = n == tid.origin and born_step[tid] == k
                if not first and (rng.random() >= s.meas_prob or born_step[tid] == k):
                    continue
                base = truth[aliases[tid][0]] if tid in aliases else truth[tid]
                tm = t if first else round(max(t - rng.uniform(0, s.max_meas_delay), born[tid]), 9)
                z = base + rng.normal(0, stds[n], size=2)
                run.measurements[tid].append((tm, z, stds[n]))
                waiting.append((tm if first else tm + rng.uniform(0, s.max_meas_delay), n, tid, tm, z))
        for item in sorted([w for w in waiting if w[0] <= t], key=lambda w: (w[0], w[1], w[2])):
            _, n, tid, tm, z = item
            if tid in nodes[n].ended:   # the node heard this identity ended (merged or deleted): not used
                run.measurements[tid] = [m for m in run.measurements[tid] if not (m[0] == tm and m[1] is z)]
                continue
            nodes[n].observe(tid, tm, z, sensors[n], born=born[tid])
            run.stats["observed"] = run.stats.get("observed", 0) + 1
        waiting = [w for w in waiting if w[0] > t]
        # merges and deletions decided by a random node that has the track(s)
        for a, (orig, _) in aliases.items():
            if merge_step[a] == k:
                holders = [n for n in names if a in nodes[n].tracks and orig in nodes[n].tracks]
                if holders:
                    x = nodes[holders[int(rng.integers(len(holders)))]]
                    keep, gone = x.survivor(a, orig)
                    x.merge(gone, keep)
                    run.merged[gone] = keep
        for tid, st in delete_step.items():
            if st == k and run.survivor(tid) == tid:
                holders = [n for n in names if tid in nodes[n].tracks]
                if holders:
                    nodes[holders[int(rng.integers(len(holders)))]].delete(tid)
                    run.deleted.add(tid)
        arrived = sorted(m for m in in_flight if m[0] <= t)
        in_flight = [m for m in in_flight if m[0] > t]
        for _, _, dst, data in arrived:
            nodes[dst].receive(data)
        if k % s.send_every == 0:
            for n in names:
                for dst, data in nodes[n].outgoing(t):
                    if rng.random() < s.drop:
                        continue
                    for _ in range(2 if rng.random() < s.duplicate else 1):
                        in_flight.append((t + rng.uniform(0, s.max_latency), next(counter), dst, data))
        _check_not_over_confident(run, t)
    # the end: late measurements, messages in flight, a connected graph, lossless rounds
    for _, n, tid, tm, z in sorted(waiting, key=lambda w: (w[0], w[1], w[2])):
        if tid not in nodes[n].ended:
            nodes[n].observe(tid, tm, z, sensors[n], born=born[tid])
        else:
            run.measurements[tid] = [m for m in run.measurements[tid] if not (m[0] == tm and m[1] is z)]
    for _, _, dst, data in sorted(in_flight):
        nodes[dst].receive(data)
    if s.link_changes:
        g = nx.Graph(list(links))
        g.add_nodes_from(names)
        comps = [sorted(c) for c in nx.connected_components(g)]
        for first, other in zip(comps, comps[1:]):
            links.add(tuple(sorted((first[0], other[0]))))
            nodes[first[0]].link_up(other[0])
            nodes[other[0]].link_up(first[0])
    lossless_rounds(nodes, 3 * s.n + 6, t)
    run.t_end = t
    return run


def _check_not_over_confident(run: TrackRun, t: float) -> None:
    for node in run.nodes.values():
        for tid, mean, P in node.estimates():
            root = run._root(tid)
            _, Pc = run.reference(root, t, taken_before=t)
            scale = np.abs(Pc).max()
            run.worst = min(run.worst, float(np.linalg.eigvalsh(P - Pc)[0] / scale))
            run.checks += 1
