"""A hand-driven message schedule for fusion tests (drops, duplicates,
reordering, crossing messages), independent of dfusion.sim, and the filterpy
reference that every node must match."""
from __future__ import annotations

from dataclasses import dataclass, field

import networkx as nx
import numpy as np
from filterpy.kalman import KalmanFilter

from dfusion.errors import OutsideWindowError
from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.topology import settling_rounds

Q_PSD = 0.3
P0 = 4.0


def cv_F(dt: float) -> np.ndarray:
    F = np.eye(4)
    F[:2, 2:] = dt * np.eye(2)
    return F


def cv_Q(dt: float, q: float = Q_PSD) -> np.ndarray:
    I = np.eye(2)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def central_kalman(measurements, t_end):
    """filterpy KalmanFilter on all (t, z, std) measurements in time order."""
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x = np.zeros((4, 1))
    kf.P = np.eye(4) * P0
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    t_prev = 0.0
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
    #: Measurements of a simulated constant-velocity truth (the filters' model) instead of
    #: arbitrary values: a healthy network, for consistency tests.
    truth: bool = False
    #: ``FusionNode(guard=...)`` of every node (None: no consistency test); a callable is called
    #: with the node's sorted neighbours and returns that node's guard.
    guard: object = None


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


def run_network(graph: nx.Graph, s: Schedule, final_rounds: bool = True):
    """Run every node on the schedule; return (nodes, all measurements, t_end)."""
    rng = np.random.default_rng(s.seed)
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    names = sorted(graph.nodes)
    nodes = {
        n: FusionNode(n, sorted(graph.neighbors(n)), motion, window=s.window, prior=prior, fusion=s.fusion,
                      guard=s.guard(sorted(graph.neighbors(n))) if callable(s.guard) else s.guard)
        for n in names
    }
    truth = CVTruth(np.random.default_rng(s.seed + 7919)) if s.truth else None
    stds = {n: s.stds.get(n, float(rng.uniform(0.3, 1.5))) for n in names}
    sensors = {n: PositionSensor(2, stds[n]) for n in names}
    links = [(a, b) for a, b in graph.edges] + [(b, a) for a, b in graph.edges]
    consecutive = {l: 0 for l in links}
    in_flight: list[tuple[float, int, str, bytes]] = []
    waiting: list[tuple[float, str, float, np.ndarray]] = []   # measurements not yet arrived
    measurements = []
    counter = 0
    t = 0.0
    for k in range(1, s.steps + 1):
        t = round(k * s.dt, 12)
        for n in names:
            nodes[n].predict(t)
        step = []
        for n in names:   # new measurements, delivered to their node after a random delay
            if rng.random() < s.meas_prob:
                tm = t - (rng.uniform(0, s.dt) if s.irregular else 0.0)
                tm = round(max(tm, 0.0), 9)
                z = rng.normal(0.0, 3.0, size=2)
                step.append((tm, n, z, rng.uniform(0, s.max_meas_delay)))
        if truth is not None:   # the truth at the measurement times, in time order
            step = [(tm, n, truth.at(tm)[:2] + stds[n] * z / 3.0, d) for tm, n, z, d in sorted(step, key=lambda e: e[0])]
        for tm, n, z, d in step:
            measurements.append((tm, z, stds[n]))
            waiting.append((tm + d, n, tm, z))
        for item in sorted([w for w in waiting if w[0] <= t], key=lambda w: w[0]):
            deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]])
        waiting = [w for w in waiting if w[0] > t]
        arrived = sorted([m for m in in_flight if m[0] <= t])
        in_flight = [m for m in in_flight if m[0] > t]
        for _, _, dst, data in arrived:
            nodes[dst].receive(data)
        if k % s.send_every == 0:
            for a, b in links:
                data = nodes[a].message_to(b)
                if rng.random() < s.drop and consecutive[(a, b)] < s.max_consecutive_drops:
                    consecutive[(a, b)] += 1
                    continue
                consecutive[(a, b)] = 0
                copies = 2 if rng.random() < s.duplicate else 1
                for _ in range(copies):
                    counter += 1
                    in_flight.append((t + rng.uniform(0, s.max_latency), counter, b, data))
    for item in waiting:   # remaining late measurements
        deliver_measurement(nodes[item[1]], item[2], item[3], sensors[item[1]])
    for _, _, dst, data in sorted(in_flight):
        nodes[dst].receive(data)
    if final_rounds:
        for _ in range(settling_rounds(graph)):
            msgs = [(b, nodes[a].message_to(b)) for a, b in links]
            for b, data in msgs:
                nodes[b].receive(data)
    return nodes, measurements, t
