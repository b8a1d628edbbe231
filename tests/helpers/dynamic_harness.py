"""A hand-driven network whose links change: random link changes over a radio graph with
cycles, joins, leaves, drops, duplicates and delays, independent of dfusion.sim; the
reference is filterpy's Kalman filter (tests/helpers/fusion_harness.py)."""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from dfusion.fusion import FusionNode
from dfusion.fusion.sending import SendSchedule
from dfusion.fusion.tree import SpanningTree, forest_settled, initial_parents, tree_components
from dfusion.models import ConstantVelocity, PositionSensor
from tests.helpers.fusion_harness import P0, Q_PSD, central_kalman, cv_F, cv_Q, deliver_measurement

PRIOR = (0.0, np.zeros(4), np.eye(4) * P0)


@dataclass
class DynamicSchedule:
    """Randomness of one run of a network whose links change."""

    seed: int
    n: int = 6
    steps: int = 40
    dt: float = 0.1
    link_prob: float = 0.5          # chance that a pair is linked at the start
    change_prob: float = 0.3        # chance per step that one pair's link flips
    joiners: int = 1                # nodes that join after the start
    leavers: int = 1                # nodes that leave for good
    meas_prob: float = 0.5
    max_meas_delay: float = 0.2
    send_every: int = 2
    max_latency: float = 0.25
    drop: float = 0.2
    duplicate: float = 0.1
    window: int = 5000
    check_every_step: bool = True
    stds: dict = field(default_factory=dict)
    #: "periodic": every node sends over every link every ``send_every`` steps; "event": by
    #: :class:`dfusion.fusion.sending.SendSchedule` (news at once, at least ``min_interval`` apart
    #: per link, the heartbeat every ``send_every`` steps)
    sends: str = "periodic"
    min_interval: float = 0.0
    #: chance per step of a link *flicker*: a link that exists goes down and up again within the
    #: step at one end only (the other end notices nothing: a lapse of a liveliness token), or,
    #: with chance ``flicker_both``, at both ends. A one-sided flicker is at the parent's end of a
    #: tree link with chance ``flicker_parent`` (the child notices nothing and stays in its tree
    #: epoch), else at a random end (at the child's end it starts a new tree epoch). Drawn from a
    #: random stream of its own, so the other draws (and the schedules without flickers) stay the same.
    flicker: float = 0.0
    flicker_both: float = 0.0
    flicker_parent: float = 0.5


@dataclass
class DynamicRun:
    nodes: dict[str, FusionNode]           # every node that was ever present
    present: set[str]                       # present at the end
    measurements: list[tuple[float, np.ndarray, float, str]]   # (t, z, std, node)
    t_end: float
    worst_overconfidence: float             # most negative relative eigenvalue of P_node - P_central seen
    worst_block: float                      # most negative eigenvalue of (all measurements at t) - (node's at t),
    #                                         relative to the size of the filter's block at t
    link_changes: int
    epochs: int
    settle_rounds: int
    flickers: int = 0


def single_state_information(node: FusionNode) -> tuple[np.ndarray, np.ndarray]:
    """Per state time, the single-state information in the node's filter: its diagonal blocks
    minus those of the prior and the constant-velocity motion chain, computed here in closed
    form (D_0 = P0^-1 + F_0' Q_0^-1 F_0, D_k = Q_{k-1}^-1 + F_k' Q_k^-1 F_k, D_m = Q_{m-1}^-1),
    and the size of each diagonal block (the difference is exact to rounding relative to it:
    states a millisecond apart have motion information of order 1e9)."""
    times, D, _, _ = node.filter.information()
    assert times[0] == 0.0 and node.filter.marginalized == 0
    motion = np.zeros_like(D)
    motion[0] += np.linalg.inv(np.eye(4) * P0)
    for k in range(len(times) - 1):
        dt = times[k + 1] - times[k]
        F, Qi = cv_F(dt), np.linalg.inv(cv_Q(dt))
        motion[k] += F.T @ Qi @ F
        motion[k + 1] += Qi
    return np.asarray(times), D - motion, np.abs(D).max(axis=(1, 2))


def measurement_information(measurements, times: np.ndarray) -> np.ndarray:
    """Per time of ``times``: the information of every measurement taken then, ``sum H' R^-1 H``."""
    out = np.zeros((len(times), 4, 4))
    index = {round(float(t), 9): i for i, t in enumerate(times)}
    for t, _, std, _ in measurements:
        i = index.get(round(float(t), 9))
        if i is not None:
            out[i, :2, :2] += np.eye(2) / std**2
    return out


def _pair(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a < b else (b, a)


def build_node(name: str, links: set[tuple[str, str]], start: dict | None, incarnation: int,
               window: int) -> FusionNode:
    """A node with the links it has now; ``start``: the configured start (else it joins)."""
    nbrs = sorted({x for l in links if name in l for x in l} - {name})
    motion = ConstantVelocity(2, Q_PSD)
    if start is None:
        tree = SpanningTree(name, nbrs)
    else:
        tree = SpanningTree(name, nbrs, epoch=start[name][0], parent=start[name][1],
                            known={j: start[j] for j in nbrs})
    return FusionNode(name, nbrs, motion, window=window, prior=PRIOR, tree=tree, epoch=incarnation)


def settle(nodes: dict[str, FusionNode], links: set[tuple[str, str]], max_rounds: int = 200) -> int:
    """Lossless rounds (every node sends over every link, all delivered) until the tree rule
    has settled, then until no estimate moves any more; returns the rounds."""
    rounds = 0

    def one_round() -> None:
        out = [(j, d) for n in sorted(nodes) for j, d in nodes[n].outgoing()]
        for j, d in out:
            nodes[j].receive(d)

    while not forest_settled({n: x.tree.state() for n, x in nodes.items()}, links)[0]:
        one_round()
        rounds += 1
        assert rounds < max_rounds, forest_settled({n: x.tree.state() for n, x in nodes.items()}, links)
    # then until the estimates stop moving (at most the tree's diameter + 2 rounds are needed)
    last = None
    for _ in range(len(nodes) + 3):
        one_round()
        rounds += 1
        now = np.concatenate([np.concatenate([x.estimate()[0], x.estimate()[1].ravel()]) for _, x in
                              sorted(nodes.items())])
        if last is not None and np.array_equal(now, last):
            break
        last = now
    return rounds


def run_dynamic(s: DynamicSchedule, reference_every_step: bool = True) -> DynamicRun:
    rng = np.random.default_rng(s.seed)
    names = [f"n{i}" for i in range(s.n)]
    order = list(rng.permutation(names))
    joiners = set(order[:s.joiners])
    leavers = set(order[s.joiners:s.joiners + s.leavers])
    join_step = {j: int(rng.integers(1, s.steps)) for j in joiners}
    leave_step = {j: int(rng.integers(1, s.steps)) for j in leavers}
    stds = {n: s.stds.get(n, float(rng.uniform(0.3, 1.5))) for n in names}
    sensors = {n: PositionSensor(2, stds[n]) for n in names}
    present = set(names) - joiners
    links = {_pair(a, b) for a, b in itertools.combinations(sorted(present), 2) if rng.random() < s.link_prob}
    start = initial_parents(sorted(present), links)
    incarnations = itertools.count(1)
    nodes = {n: build_node(n, links, start, next(incarnations), s.window) for n in sorted(present)}
    gone: set[str] = set()
    in_flight: list[tuple[float, int, str, bytes]] = []
    waiting: list[tuple[float, str, float, np.ndarray]] = []
    measurements: list[tuple[float, np.ndarray, float, str]] = []
    counter = itertools.count()
    worst = np.inf
    worst_block = np.inf
    changes = 0
    t = 0.0
    schedules: dict[tuple[str, int], SendSchedule] = {}
    flicker_rng = np.random.default_rng([s.seed, 7])
    flickers = 0

    def drop_link(a: str, b: str) -> None:
        links.discard(_pair(a, b))
        nodes[a].link_down(b)
        nodes[b].link_down(a)

    def add_link(a: str, b: str) -> None:
        links.add(_pair(a, b))
        nodes[a].link_up(b)
        nodes[b].link_up(a)

    for k in range(1, s.steps + 1):
        t = round(k * s.dt, 12)
        # joins and leaves
        for j in sorted(joiners):
            if join_step[j] == k:
                node = build_node(j, set(), None, next(incarnations), s.window)
                node.predict(t)
                nodes[j] = node
                present.add(j)
                for other in sorted(present - {j}):
                    if rng.random() < s.link_prob:
                        add_link(j, other)
                        changes += 1
        for j in sorted(leavers):
            if leave_step[j] == k and j in present:
                for a, b in sorted(links):
                    if j in (a, b):
                        drop_link(a, b)
                        changes += 1
                present.discard(j)
                gone.add(j)
        # one random link flips (among present nodes)
        if rng.random() < s.change_prob and len(present) >= 2:
            a, b = sorted(rng.choice(sorted(present), size=2, replace=False))
            if (a, b) in links:
                drop_link(a, b)
            else:
                add_link(a, b)
            changes += 1
        if links and flicker_rng.random() < s.flicker:
            pair = sorted(links)[int(flicker_rng.integers(len(links)))]
            parents = [x for x, y in (pair, pair[::-1]) if nodes[y].tree.parent == x]
            if flicker_rng.random() < s.flicker_both:
                ends = pair
            elif parents and flicker_rng.random() < s.flicker_parent:
                ends = (parents[0],)
            else:
                ends = (pair[int(flicker_rng.integers(2))],)
            for x in ends:
                y = pair[1] if x == pair[0] else pair[0]
                nodes[x].link_down(y)
                nodes[x].link_up(y)
            flickers += 1
        for n in sorted(present):
            nodes[n].predict(t)
        for n in sorted(present):
            if rng.random() < s.meas_prob:
                tm = round(max(t - rng.uniform(0, s.dt), 0.0), 9)
                z = rng.normal(0.0, 3.0, size=2)
                measurements.append((tm, z, stds[n], n))
                waiting.append((tm + rng.uniform(0, s.max_meas_delay), n, tm, z))
        for item in sorted([w for w in waiting if w[0] <= t], key=lambda w: w[0]):
            if item[1] in present:
                deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]])
        waiting = [w for w in waiting if w[0] > t]
        arrived = sorted(m for m in in_flight if m[0] <= t)
        in_flight = [m for m in in_flight if m[0] > t]
        for _, _, dst, data in arrived:
            if dst in present:   # also over a link that went down meanwhile: the node ignores it
                nodes[dst].receive(data)
        if s.sends == "event":
            for n in sorted(present):
                key = (n, nodes[n].epoch)   # a new schedule per incarnation
                if key not in schedules:
                    period = s.send_every * s.dt
                    schedules[key] = SendSchedule(period, s.min_interval, "event", first=period)
                for dst, data in schedules[key].due(nodes[n], t):
                    if rng.random() < s.drop:
                        continue
                    for _ in range(2 if rng.random() < s.duplicate else 1):
                        in_flight.append((t + rng.uniform(0, s.max_latency), next(counter), dst, data))
        elif k % s.send_every == 0:
            for n in sorted(present):
                for dst, data in nodes[n].outgoing():
                    if rng.random() < s.drop:
                        continue
                    for _ in range(2 if rng.random() < s.duplicate else 1):
                        in_flight.append((t + rng.uniform(0, s.max_latency), next(counter), dst, data))
        if reference_every_step:
            # never over-confident: P_node - P_central >= 0 (the central EKF has every measurement taken so far)
            _, Pc = central_kalman([(m[0], m[1], m[2]) for m in measurements], t)
            scale = np.abs(Pc).max()
            for n in sorted(present):
                _, P = nodes[n].estimate()
                worst = min(worst, float(np.linalg.eigvalsh(P - Pc)[0] / scale))
                # and per state time: no measurement counted twice in the node's filter
                times, single, size = single_state_information(nodes[n])
                allinfo = measurement_information(measurements, times)
                gap = np.linalg.eigvalsh(allinfo - single)[:, 0]
                worst_block = min(worst_block, float((gap / size).min()))
    # the end: late measurements, every message in flight, then a connected graph and lossless rounds
    for item in waiting:
        if item[1] in present:
            deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]])
    for _, _, dst, data in sorted(in_flight):
        if dst in present:
            nodes[dst].receive(data)
    alive = sorted(present)
    comps = tree_components(links, alive)
    for first, other in zip(comps, comps[1:]):   # connect the components (cycles may remain)
        add_link(min(first), min(other))
        changes += 1
    live = {n: nodes[n] for n in alive}
    rounds = settle(live, links)
    # information a change of the tree took is held in a node's own estimate for at most `hold`
    # seconds (FusionNode(hold=...)): once that has passed, nothing but the current tree counts
    t_end = round(t + max(x.hold for x in live.values()) + s.dt, 9)
    for x in live.values():
        x.predict(t_end)
    rounds += settle(live, links)
    epochs = sum(x.stats.new_epochs for x in nodes.values())
    return DynamicRun(nodes, present, measurements, t_end, worst, worst_block, changes, epochs, rounds, flickers)


def rel(a, b) -> float:
    """Largest entry of ``a - b`` relative to the largest of ``b``."""
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


def assert_exact(run: DynamicRun) -> None:
    """Every node still present equals the Kalman filter on every measurement of those nodes (1e-9)."""
    meas = [(t, z, std) for t, z, std, node in run.measurements if node in run.present]
    mean, cov = central_kalman(meas, run.t_end)
    for name in sorted(run.present):
        m, P = run.nodes[name].estimate()
        assert rel(m, mean) < 1e-9, (name, rel(m, mean))
        assert rel(P, cov) < 1e-9, (name, rel(P, cov))
