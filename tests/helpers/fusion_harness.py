"""A hand-driven message schedule for fusion tests (drops, duplicates,
reordering, crossing messages, one-way outages, node restarts), independent of
dfusion.sim, the filterpy reference that every node must match, and a digest of
a node's whole state (to check that a rejected message changes nothing)."""
from __future__ import annotations

import hashlib
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import networkx as nx
import numpy as np
from filterpy.kalman import KalmanFilter

from dfusion.errors import MessageError, OutsideWindowError
from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.topology import settling_rounds

Q_PSD = 0.3
P0 = 4.0
PRIOR = (0.0, np.zeros(4), np.eye(4) * P0)


def cv_F(dt: float) -> np.ndarray:
    F = np.eye(4)
    F[:2, 2:] = dt * np.eye(2)
    return F


def cv_Q(dt: float, q: float = Q_PSD) -> np.ndarray:
    I = np.eye(2)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def central_kalman(measurements, t_end, prior=None):
    """filterpy KalmanFilter on all (t, z, std) measurements in time order, from ``prior``
    ``(t0, x0, P0)`` (default: the harness's ``(0, 0, P0 I)``)."""
    t0, x0, Pp = prior if prior is not None else (0.0, np.zeros(4), np.eye(4) * P0)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x = np.asarray(x0, float).reshape(4, 1)
    kf.P = np.array(Pp, dtype=float)
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    t_prev = t0
    for t, z, std in sorted(measurements, key=lambda m: m[0]):
        if t > t_prev:
            kf.F, kf.Q = cv_F(t - t_prev), cv_Q(t - t_prev)
            kf.predict()
            t_prev = t
        kf.R = std**2 * np.eye(2)
        kf.update(np.asarray(z, float).reshape(2, 1))
    if t_end > t_prev:
        kf.F, kf.Q = cv_F(t_end - t_prev), cv_Q(t_end - t_prev)
        kf.predict()
    return kf.x.ravel(), kf.P


@dataclass
class Schedule:
    """Randomness of one run."""

    seed: int
    steps: int = 30
    dt: float = 0.1
    meas_prob: float = 0.6
    max_meas_delay: float = 0.3
    irregular: bool = True
    send_every: int = 2            # steps between messages on every link
    max_latency: float = 0.3
    drop: float = 0.3
    max_consecutive_drops: int = 2
    duplicate: float = 0.1
    window: int = 400
    fusion: str = "channel"
    stds: dict = field(default_factory=dict)
    # one-way outages: per step and directed link, the chance that every message in that
    # direction is lost for the next ``outage_steps`` steps (the other direction works:
    # the acknowledgements of the messages it carries are what is lost)
    outage: float = 0.0
    outage_steps: int = 6
    # (step, node): the node is replaced by a fresh FusionNode with a larger epoch that
    # replays the measurements it had been given
    restarts: tuple = ()
    # called after every step as on_step(nodes, measurements so far, t)
    on_step: Callable | None = None
    #: Measurements of a simulated constant-velocity truth (the filters' model) instead of
    #: arbitrary values: a healthy network, for consistency tests.
    truth: bool = False
    #: ``FusionNode(guard=...)`` of every node (None: no consistency test); a callable is called
    #: with the node's sorted neighbours and returns that node's guard.
    guard: object = None
    #: ``{node: (dx, dy)}``: with ``truth``, these nodes' measurements are off by this much (a
    #: hostile or broken sensor whose claimed noise does not cover it).
    bias: dict = field(default_factory=dict)


class CVTruth:
    """A constant-velocity trajectory drawn from the filters' own model (prior ``N(0, P0 I)``,
    process noise ``cv_Q``), sampled at increasing times on demand."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.t = 0.0
        self.x = rng.normal(0.0, np.sqrt(P0), size=4)

    def at(self, t: float) -> np.ndarray:
        if t > self.t:
            dt = t - self.t
            self.x = cv_F(dt) @ self.x + np.linalg.cholesky(cv_Q(dt)) @ self.rng.standard_normal(4)
            self.t = t
        return self.x


@dataclass
class Trace:
    """What happened during :func:`run_network` besides the nodes' own state."""

    rejections: Counter = field(default_factory=Counter)
    restarted: list = field(default_factory=list)
    outages: int = 0
    delivered: int = 0


def random_tree(n: int, seed: int) -> nx.Graph:
    if n == 2:
        g = nx.Graph()
        g.add_edge("n0", "n1")
        return g
    g = nx.random_labeled_tree(n, seed=seed)
    return nx.relabel_nodes(g, {i: f"n{i}" for i in g.nodes})


def deliver_measurement(node, t, z, sensor) -> bool:
    """Update a node; a measurement older than its window is refused and dropped."""
    try:
        node.update(t, z, sensor)
        return True
    except OutsideWindowError:
        return False


def receive(node, data: bytes, trace: Trace | None) -> None:
    """Deliver a message; a rejected one is recorded in ``trace`` (and raises without one)."""
    try:
        node.receive(data)
        if trace is not None:
            trace.delivered += 1
    except MessageError as exc:
        if trace is None:
            raise
        trace.rejections[exc.reason] += 1


def node_guard(s: Schedule, neighbors) -> object:
    """The ``guard`` of a node with these neighbours under schedule ``s`` (:attr:`Schedule.guard`)."""
    return s.guard(sorted(neighbors)) if callable(s.guard) else s.guard


def restart(old: FusionNode, t: float, own: list, sensor, s: Schedule) -> FusionNode:
    """A fresh incarnation of ``old`` (epoch + 1) at time ``t`` that replays ``own`` (t, z)."""
    new = FusionNode(old.name, old.neighbors, old.motion, window=s.window, prior=PRIOR, fusion=s.fusion,
                     epoch=old.epoch + 1, guard=node_guard(s, old.neighbors))
    new.predict(t)
    for tm, z in sorted(own, key=lambda m: m[0]):
        deliver_measurement(new, tm, z, sensor)
    return new


def run_network(graph: nx.Graph, s: Schedule, final_rounds: bool = True, trace: Trace | None = None):
    """Run every node on the schedule; return (nodes, all measurements, t_end).

    Without ``trace`` a rejected message raises; with one, rejections are counted there.
    """
    rng = np.random.default_rng(s.seed)
    motion = ConstantVelocity(2, Q_PSD)
    names = sorted(graph.nodes)
    nodes = {
        n: FusionNode(n, sorted(graph.neighbors(n)), motion, window=s.window, prior=PRIOR, fusion=s.fusion,
                      epoch=1000 * (i + 1), guard=node_guard(s, graph.neighbors(n)))
        for i, n in enumerate(names)
    }
    truth = CVTruth(np.random.default_rng(s.seed + 7919)) if s.truth else None
    stds = {n: s.stds.get(n, float(rng.uniform(0.3, 1.5))) for n in names}
    sensors = {n: PositionSensor(2, stds[n]) for n in names}
    links = [(a, b) for a, b in graph.edges] + [(b, a) for a, b in graph.edges]
    consecutive = {l: 0 for l in links}
    down_until = {l: 0 for l in links}
    in_flight: list[tuple[float, int, str, bytes]] = []
    waiting: list[tuple[float, str, float, np.ndarray]] = []   # measurements not yet arrived
    measurements = []
    own: dict[str, list] = {n: [] for n in names}             # what each node was given
    counter = 0
    t = 0.0
    for k in range(1, s.steps + 1):
        t = round(k * s.dt, 12)
        for n in names:
            nodes[n].predict(t)
        for step, n in s.restarts:
            if step == k:
                nodes[n] = restart(nodes[n], t, own[n], sensors[n], s)
                if trace is not None:
                    trace.restarted.append((k, n))
        batch = []
        for n in names:   # new measurements, delivered to their node after a random delay
            if rng.random() < s.meas_prob:
                tm = t - (rng.uniform(0, s.dt) if s.irregular else 0.0)
                tm = round(max(tm, 0.0), 9)
                z = rng.normal(0.0, 3.0, size=2)
                batch.append((tm, n, z, rng.uniform(0, s.max_meas_delay)))
        if truth is not None:   # the truth at the measurement times, in time order
            batch = [(tm, n, truth.at(tm)[:2] + stds[n] * z / 3.0 + np.asarray(s.bias.get(n, 0.0)), d) for tm, n, z, d in sorted(batch, key=lambda e: e[0])]
        for tm, n, z, d in batch:
            measurements.append((tm, z, stds[n]))
            waiting.append((tm + d, n, tm, z))
        for item in sorted([w for w in waiting if w[0] <= t], key=lambda w: w[0]):
            if deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]]):
                own[item[1]].append((item[2], item[3]))
        waiting = [w for w in waiting if w[0] > t]
        arrived = sorted([m for m in in_flight if m[0] <= t])
        in_flight = [m for m in in_flight if m[0] > t]
        for _, _, dst, data in arrived:
            receive(nodes[dst], data, trace)
        if s.outage:
            for l in links:
                if down_until[l] < k and rng.random() < s.outage:
                    down_until[l] = k + s.outage_steps
                    if trace is not None:
                        trace.outages += 1
        if k % s.send_every == 0:
            for a, b in links:
                data = nodes[a].message_to(b)
                if down_until[(a, b)] >= k:
                    continue
                if rng.random() < s.drop and consecutive[(a, b)] < s.max_consecutive_drops:
                    consecutive[(a, b)] += 1
                    continue
                consecutive[(a, b)] = 0
                copies = 2 if rng.random() < s.duplicate else 1
                for _ in range(copies):
                    counter += 1
                    in_flight.append((t + rng.uniform(0, s.max_latency), counter, b, data))
        if s.on_step is not None:
            s.on_step(nodes, measurements, t)
    for item in waiting:   # remaining late measurements
        deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]])
    for _, _, dst, data in sorted(in_flight):
        receive(nodes[dst], data, trace)
    if final_rounds:
        for _ in range(settling_rounds(graph)):
            lossless_round(nodes, links)
    return nodes, measurements, t


def lossless_round(nodes: dict, links: list) -> None:
    """Every node sends one message to every neighbour, and every message is delivered."""
    msgs = [(b, nodes[a].message_to(b)) for a, b in links]
    for b, data in msgs:
        nodes[b].receive(data)


# ---------------------------------------------------------------- a node's whole state
def node_state(node: FusionNode) -> dict:
    """Everything a received message may change, except the rejection counters.

    The filter (:meth:`DelayedStateEIF.checkpoint`: its base, the single-state information
    of every state, the state times, the marginalized count), every channel filter
    (:meth:`ChannelFilter.state`: stored entries, incarnation, sequence numbers,
    acknowledgements, dirty and resend sets, records of sent messages, counters), the
    stores messages are made from (own and total information per state time) and the
    statistics but ``messages_rejected`` and ``rejections``.
    """
    f = node.filter
    (base, L, y, _factors, _cache, _kept), times, marginalized = f.checkpoint()
    stats = {k: v for k, v in vars(node.stats).items() if k not in ("messages_rejected", "rejections")}
    return {
        "filter": (base, L, y, times, marginalized, f.latest_time, f.oldest_time),
        "channels": {j: ch.state() for j, ch in sorted(node.channels.items())},
        "own": getattr(node, "_own").checkpoint(),
        "total": getattr(node, "_total").checkpoint(),
        "pruned_at": getattr(node, "_pruned_at"),
        "stats": stats,
    }


def _flatten(x, arrays: list, scalars: list) -> None:
    """Split ``x`` into its arrays (in order) and everything else (with the shapes, dtypes
    and lengths, so that the two lists determine ``x``)."""
    t = type(x)
    if t is np.ndarray:
        arrays.append(x)
        scalars.append((x.dtype.char, x.shape))
    elif t is dict:
        scalars.append(("dict", len(x)))
        for k in sorted(x):
            scalars.append(k)
            _flatten(x[k], arrays, scalars)
    elif t is list or t is tuple:
        types = {type(v) for v in x}
        if types == {np.ndarray}:          # fast paths: a list of arrays, a list of plain values
            arrays.extend(x)
            scalars.append((t.__name__, tuple((v.dtype.char, v.shape) for v in x)))
        elif types <= {bool, int, float, str, type(None)}:
            scalars.append((t.__name__, tuple(x)))
        else:
            scalars.append((t.__name__, len(x)))
            for v in x:
                _flatten(v, arrays, scalars)
    elif t is set:
        scalars.append(("set", tuple(sorted(x))))
    elif t in (bool, int, float, str, type(None)) or isinstance(x, np.generic):
        scalars.append(x)
    else:
        raise TypeError(f"cannot digest {t.__name__}")


def state_digest(node: FusionNode) -> str:
    """A digest of :func:`node_state`, to compare states within one process: SHA-256 of
    every array's bytes (bit for bit) and Python's hash of everything else (integers,
    names, flags, shapes; fast, and equal for equal values)."""
    arrays: list = []
    scalars: list = []
    _flatten(node_state(node), arrays, scalars)
    h = hashlib.sha256(b"".join([a.tobytes() for a in arrays]))
    return f"{hash(tuple(scalars)) & (2**64 - 1):016x}-{h.hexdigest()}"


# ---------------------------------------------------------------- a chain a - b - c
KEY = b"network-key-of-the-tests"


def make_node(name: str, neighbors, *, epoch: int, window: int = 50, key: bytes | None = None, network: str = "",
              run: str = "", **kw) -> FusionNode:
    """A node of the constant-velocity test network (the common prior :data:`PRIOR`)."""
    return FusionNode(name, neighbors, ConstantVelocity(2, Q_PSD), window=window, prior=PRIOR, network_key=key,
                      network=network, run=run, epoch=epoch, **kw)


def build_chain(key: bytes | None = None, **kw) -> tuple[FusionNode, FusionNode, FusionNode, bytes, list]:
    """Nodes ``a - b - c`` (epochs 11, 22, 33) after 5 steps of measurements and exchanges,
    some of them late; returns ``(a, b, c, message a -> b, measurements)``.

    The message carries information ``b`` does not have yet (measurements of ``a`` after
    the last exchange, one of them late, at a time that is not a state of ``b`` yet), so accepting it changes ``b``'s filter,
    its channel from ``a``, its stores, what it must send ``c`` and, since ``b`` has
    sent ``a`` messages, what ``b`` knows ``a`` acknowledged. ``measurements`` are
    every ``(t, z, std)`` of the three nodes (for :func:`central_kalman`).
    """
    nodes = {name: make_node(name, nbrs, epoch=epoch, key=key, **kw)
             for name, nbrs, epoch in (("a", ["b"], 11), ("b", ["a", "c"], 22), ("c", ["b"], 33))}
    a, b, c = nodes["a"], nodes["b"], nodes["c"]
    sensor = PositionSensor(2, 0.5)
    rng = np.random.default_rng(7)
    meas = []

    def update(node, t, z):
        node.update(t, z, sensor)
        meas.append((t, np.asarray(z, float), 0.5))

    for k in range(1, 5):
        t = round(0.1 * k, 9)
        for node in nodes.values():
            node.predict(t)
        update(a, t, rng.normal(size=2) + [k, 0.0])
        update(c, round(t - 0.05, 9), rng.normal(size=2) + [0.0, k])    # a late measurement
        if k % 2 == 0:
            for src, dst in (("a", "b"), ("b", "a"), ("b", "c"), ("c", "b")):
                nodes[dst].receive(nodes[src].message_to(dst))
    for node in nodes.values():
        node.predict(0.5)
    update(a, 0.5, [5.0, 0.1])
    update(a, 0.33, [3.3, 0.3])
    update(b, 0.45, [4.5, 0.2])
    return a, b, c, a.message_to("b"), meas


# ---------------------------------------------------------------- every attribute of a node
#: Attributes of a node that a received message never changes (configuration, outputs of other
#: methods) or that a rejection changes on purpose (its log).
NOT_MESSAGE_STATE = frozenset({"policy", "frame_key", "rejection_log", "sources"})


def full_state(node: FusionNode) -> dict:
    """Every attribute of ``node`` (``vars(node)``) but :data:`NOT_MESSAGE_STATE` and the rejection
    counters, each store as its content (the filter as in :func:`node_state`, a store of blocks
    by its checkpoint, a channel filter by its state, the guard by its records), everything
    else as its plain value. An attribute of a type it does not know raises ``TypeError``: a
    store added to the node later is compared, or this fails, but it is never left out."""
    from dfusion.estimation.delayed_state import DelayedStateEIF
    from dfusion.fusion import ChannelFilter, NeighbourGuard
    from dfusion.fusion.incarnation import Incarnations
    from dfusion.fusion.node import NodeStats, _Blocks

    def plain(x):
        if isinstance(x, DelayedStateEIF):
            (base, L, y, _factors, _cache, _kept), times, marginalized = x.checkpoint()
            return ("filter", base, L, y, times, marginalized, x.latest_time, x.oldest_time)
        if isinstance(x, _Blocks):
            return ("blocks",) + x.checkpoint()
        if isinstance(x, ChannelFilter):
            return ("channel", x.local, x.remote, x.ack_lag) + tuple(plain(v) for v in x.state())
        if isinstance(x, NeighbourGuard):
            return ("guard", repr(x.config), {j: plain({k: v for k, v in vars(r).items()})
                                              for j, r in x.links.items()})
        if isinstance(x, Incarnations):
            return ("incarnations", x.keyed, {j: (r.epoch, r.newest_seq, r.sent_at, r.streak, r.mark)
                                              for j, r in x.replaced.items()})
        if isinstance(x, NodeStats):
            return {k: plain(v) for k, v in vars(x).items() if k not in ("messages_rejected", "rejections")}
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return tuple(plain(v) for v in x)
        if isinstance(x, deque):
            return ("deque", x.maxlen, tuple(x))
        if isinstance(x, (set, frozenset)):
            return ("set", tuple(sorted(x)))
        if isinstance(x, np.ndarray) or x is None or isinstance(x, (bool, int, float, str, np.generic)):
            return x
        raise TypeError(f"full_state does not know {type(x).__name__}: add it")

    return {k: plain(v) for k, v in vars(node).items() if k not in NOT_MESSAGE_STATE}


def full_digest(node: FusionNode) -> str:
    """:func:`full_state` as a digest (bit for bit for arrays)."""
    arrays: list = []
    scalars: list = []
    _flatten(full_state(node), arrays, scalars)
    h = hashlib.sha256(b"".join([np.ascontiguousarray(a).tobytes() for a in arrays]))
    return f"{hash(tuple(map(repr, scalars))) & (2**64 - 1):016x}-{h.hexdigest()}"
