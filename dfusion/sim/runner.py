"""Run a scenario in one process: fusion nodes on a simulated network, and the
centralized EKF on the union of all measurements as the reference.

Every step ``t = k dt``:

1. every node predicts to ``t``;
2. measurements that have reached their node by ``t`` are fused (late ones at
   their own time stamp; one older than the window is refused and counted);
   the measurements of one frame (same node, time and arrival: a camera's
   detections) go to the front end together (:meth:`dfusion.frontends.base.FrontEnd.process_frame`:
   data association);
3. messages that have arrived by ``t`` are received;
4. a node whose send period has elapsed sends a message to each neighbour;
5. node estimates and the centralized estimate (all measurements taken by
   ``t``, no delay) are recorded; for a node whose policy is not plain fusion
   (a switching policy, ``docs/policies.md``) its output (:meth:`FusionNode.output`,
   the source the policy chose) is recorded too.

At the end every message in flight is delivered, late measurements are fused,
and ``diameter + 2`` lossless rounds are exchanged (:func:`dfusion.topology.settling_rounds`) ("once the last messages are
delivered"); ``final_gap`` compares each node's newest mean then with the
centralized one.

Two centralized references run on the world's measurements, in time order and
without delay (:class:`References`): the *fair* one (``centralized``) gets every
detection, false ones included, through the same gate and clutter model as the
camera nodes (:meth:`dfusion.frontends.base.FrontEnd.reference_frame`), and is what the gaps are
measured against; the *oracle* (``centralized_oracle``) skips the false
detections (it knows which they are) and gates nothing.

Per node the run also reports the diagnostics of ``docs/clutter.md``: the
consistency test of the neighbours' information (:mod:`dfusion.fusion.guard`),
a camera's gated detections, NIS and track losses, and the health state per
step (``ok``, ``degraded``, ``lost``), with ``WARNING`` lines in the table for
nodes that were lost at some step or are inconsistent.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np

from dfusion.errors import MessageError, OutsideWindowError
from dfusion.estimation.centralized import CentralizedEKF
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array
from dfusion.metrics import chi2_interval, nees, rmse
from dfusion.policies.base import InformationFusionPolicy
from dfusion.scenario.build import build_front_ends, build_nodes
from dfusion.scenario.spec import Scenario
from dfusion.sim.world import World, simulate_world
from dfusion.transport.simulated import SimulatedNetwork
from dfusion.topology import settling_rounds

log = logging.getLogger(__name__)


@dataclass
class NodeOutput:
    """What a node's policy output over a run (:meth:`FusionNode.output` per step).

    Attributes
    ----------
    policy : str
        The policy's name.
    mean, cov : (K, n), (K, n, n)
        The chosen estimate per step.
    source : list of str
        The name of the chosen source per step (``"fused"``: the node's own fusion).
    """

    policy: str
    mean: Array
    cov: Array
    source: list[str]


def records_output(node: FusionNode) -> bool:
    """Whether a node's output is recorded: its policy is not plain information fusion."""
    return type(node.policy) is not InformationFusionPolicy


@dataclass
class SimulationResult:
    """Time series and metrics of one run.

    Attributes
    ----------
    times : (K,) filter grid
    truth : (K, n)
    central_mean, central_cov : (K, n), (K, n, n)
        The fair centralized reference (same detections, gate and clutter model as the nodes).
    node_mean, node_cov : dict name -> (K, n), (K, n, n)
    outputs : dict name -> NodeOutput
        The policy output of the nodes whose policy is not plain fusion.
    metrics : dict
        The figures printed and written to JSON (see :meth:`to_json`).
    oracle_mean, oracle_cov, oracle_final : arrays or None
        The oracle reference (false detections skipped) per step and at the end.
    health : dict name -> list of str
        Each node's health per step (``"ok"``, ``"degraded"``, ``"lost"``; :func:`node_health`).
    """

    scenario: Scenario
    world: World
    times: Array
    truth: Array
    central_mean: Array
    central_cov: Array
    node_mean: dict[str, Array]
    node_cov: dict[str, Array]
    metrics: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, NodeOutput] = field(default_factory=dict)
    oracle_mean: Array | None = None
    oracle_cov: Array | None = None
    oracle_final: Array | None = None
    health: dict[str, list[str]] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(self.metrics, indent=2, sort_keys=True)

    def table(self) -> str:
        """The summary table printed by ``dfusion simulate``."""
        m = self.metrics
        diag = all(v.get("health") is not None for v in m["nodes"].values())
        rows = [("node", "RMSE [m]", "ANEES", "final gap", "mean gap", "sent", "bytes")
                + (("NIS", "gated", "quar.", "health") if diag else ())]
        for name, v in m["nodes"].items():
            row = (name, f"{v['rmse']:.4f}", f"{v['anees']:.3f}", f"{v['final_gap']:.2e}",
                   f"{v['mean_gap']:.2e}", str(v["messages"]), str(v["bytes"]))
            if diag:
                nis, gated = v.get("nis_mean"), v.get("gated")
                row += ("-" if nis is None else f"{nis:.2f}", "-" if gated is None else str(gated),
                        ",".join(v.get("quarantined") or []) or "-", v["health"])
            rows.append(row)
        for key, label in (("centralized", "centralized"), ("centralized_oracle", "central oracle")):
            c = m.get(key)
            if c is not None:
                rows.append((label, f"{c['rmse']:.4f}", f"{c['anees']:.3f}", "-", "-", "-", "-")
                            + (("-",) * 4 if diag else ()))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths))) for r in rows]
        lines.insert(1, "-" * len(lines[0]))
        lo, hi = m["nees_interval"]
        lines.append("")
        lines.append(f"fusion={m['fusion']} seed={m['seed']} steps={m['steps']} state dim={m['state_dim']}: "
                     f"ANEES 95% interval for one run [{lo:.3f}, {hi:.3f}] (time-correlated: indicative)")
        lines.append(f"messages {m['messages']} ({m['messages_delivered']} delivered, {m['messages_dropped']} lost), "
                     f"bytes {m['bytes']}, measurements {m['measurements']} ({m['measurements_refused']} refused: older than the window)")
        if diag:
            lines.append("NIS: mean consistency statistic per degree of freedom of the neighbours' information "
                         "(expected 1); gated: own detections outside the gate; quar.: quarantined neighbours "
                         f"at the end; protection: {m.get('protection', '-')}")
        lines.extend(warning_lines(m))
        outs = {name: v["output"] for name, v in m["nodes"].items() if "output" in v}
        if outs:
            lines.append("")
            lines.append("policy outputs (node.output(): the source each node's policy chose)")
            for name, o in outs.items():
                share = ", ".join(f"{src} {frac:.0%}" for src, frac in o["sources"].items())
                lines.append(f"  {name}: policy {o['policy']}, RMSE {o['rmse']:.4f}, ANEES {o['anees']:.3f}, "
                             f"switches {o['switches']}; {share}")
        return "\n".join(lines)


def warning_lines(m: dict[str, Any]) -> list[str]:
    """``WARNING`` lines of a run's metrics: nodes that were lost at some step, and nodes whose
    ANEES is outside the 95 % interval of one run (inconsistent)."""
    lo, hi = m["nees_interval"]
    out = []
    for name, v in m["nodes"].items():
        steps = v.get("health_steps") or {}
        if steps.get("lost", 0):
            out.append(f"WARNING {name}: lost during {steps['lost']} steps (every neighbour quarantined, or its "
                       f"camera's track lost); health at the end: {v.get('health', '?')}")
        if not lo <= v["anees"] <= hi:
            side = "over-confident" if v["anees"] > hi else "conservative"
            out.append(f"WARNING {name}: inconsistent, ANEES {v['anees']:.3g} outside [{lo:.3f}, {hi:.3f}] ({side})")
    return out


def _progress(iterable, enabled: bool, total: int):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, unit="step", leave=False)


def run_scenario(sc: Scenario, *, progress: bool = False) -> SimulationResult:
    """Simulate ``sc`` with every node in this process; see the module docstring."""
    world = simulate_world(sc)
    nodes = build_nodes(sc)
    net = SimulatedNetwork(((a, b, spec) for (a, b), spec in sc.links.items()), seed=sc.seed)
    motion = sc.target.motion
    front = build_front_ends(sc)
    refs = References(sc, front)
    names = sorted(nodes)
    K = sc.steps + 1
    n = motion.dim
    times = np.round(sc.dt * np.arange(K), 9)
    truth = np.array([world.truth(t) for t in times])
    node_mean = {nm: np.empty((K, n)) for nm in names}
    node_cov = {nm: np.empty((K, n, n)) for nm in names}
    c_mean, c_cov = np.empty((K, n)), np.empty((K, n, n))
    o_mean, o_cov = np.empty((K, n)), np.empty((K, n, n))
    health = {nm: [""] * K for nm in names}
    outputs = {nm: NodeOutput(nodes[nm].policy.name, np.empty((K, n)), np.empty((K, n, n)), [""] * K)
               for nm in names if records_output(nodes[nm])}
    by_arrival = frames(sorted(world.measurements, key=lambda m: (m.arrival, m.t, m.node)))
    by_time = frames(world.measurements)  # already in time order
    next_send = {nm: sc.nodes[nm].send_period for nm in names}
    ia = ic = 0
    refused = 0

    def fuse(frame: list) -> int:
        """Fuse one frame at its node; the number of measurements refused (older than the window)."""
        m0 = frame[0]
        try:
            front[m0.node].process_frame(nodes[m0.node], m0.t, np.array([m.z for m in frame]))
        except OutsideWindowError:
            log.info("%s: measurement at t=%.3f arrived after it left the window", m0.node, m0.t)
            return len(frame)
        return 0

    def record(k: int) -> None:
        for nm in names:
            node_mean[nm][k], node_cov[nm][k] = nodes[nm].estimate()
        for nm, o in outputs.items():
            chosen = nodes[nm].output()
            o.mean[k], o.cov[k], o.source[k] = chosen.mean, chosen.cov, chosen.name
        for nm in names:
            health[nm][k] = node_health(nodes[nm], front.get(nm))
        (c_mean[k], c_cov[k]), (o_mean[k], o_cov[k]) = refs.estimate(times[k])

    record(0)
    for k in _progress(range(1, K), progress, K - 1):
        t = float(times[k])
        for nm in names:
            nodes[nm].predict(t)
        while ia < len(by_arrival) and by_arrival[ia][0].arrival <= t + 1e-9:
            refused += fuse(by_arrival[ia])
            ia += 1
        while ic < len(by_time) and by_time[ic][0].t <= t + 1e-9:
            refs.add(by_time[ic], seq=ic)
            ic += 1
        for nm in names:
            for d in net.receive(nm, t + 1e-9):
                try:
                    nodes[nm].receive(d.data)
                except MessageError as exc:  # a simulated network never corrupts; log anyway
                    log.warning("%s: %s", nm, exc)
        for nm in names:
            if t + 1e-9 >= next_send[nm]:
                for nb in nodes[nm].neighbors:
                    net.send(nm, nb, nodes[nm].message_to(nb, sent_at=t), t)
                while next_send[nm] <= t + 1e-9:
                    next_send[nm] += sc.nodes[nm].send_period
        record(k)

    # the end: every message in flight, every late measurement, then lossless rounds
    for d in net.flush():
        nodes[d.dst].receive(d.data)
    for frame in by_arrival[ia:]:
        refused += fuse(frame)
    for frame in by_time[ic:]:
        refs.add(frame, seq=ic)
        ic += 1
    for nm, fe in front.items():
        fe.finish(nodes[nm])
    final_rounds(nodes, sc.graph)
    T = float(times[-1])
    (c_final, _), (o_final, _) = refs.estimate(T)

    result = SimulationResult(sc, world, times, truth, c_mean, c_cov, node_mean, node_cov, outputs=outputs,
                              oracle_mean=o_mean, oracle_cov=o_cov, oracle_final=o_final, health=health)
    result.metrics = compute_metrics(sc, result, nodes, c_final, net, len(world.measurements), refused,
                                     front_ends=front)
    return result


def frames(measurements: list) -> list[list]:
    """Group consecutive measurements of the same node, time and arrival: the measurements of one
    frame (a camera's true detection and its false ones share them)."""
    out: list[list] = []
    for m in measurements:
        if out and (out[-1][0].node, out[-1][0].t, out[-1][0].arrival) == (m.node, m.t, m.arrival):
            out[-1].append(m)
        else:
            out.append([m])
    return out


class References:
    """The two centralized references of a run (see the module docstring).

    ``fair``: every measurement of a frame through its node's front end as the reference
    applies it (:meth:`dfusion.frontends.base.FrontEnd.reference_frame`: a camera's gate and clutter model), or as
    EKF updates with the sensor's model. ``oracle``: every true measurement as an EKF update,
    false detections skipped.
    """

    def __init__(self, sc: Scenario, front: dict[str, Any]) -> None:
        motion = sc.target.motion
        self.fair = CentralizedEKF(motion, 0.0, sc.target.initial_mean, sc.target.initial_cov)
        self.oracle = CentralizedEKF(motion, 0.0, sc.target.initial_mean, sc.target.initial_cov)
        self.sensors = {name: spec.sensor for name, spec in sc.nodes.items()}
        self.front = front

    def add(self, frame: list, seq: int) -> None:
        """Add one frame (measurements of one node at one time; ``seq`` orders equal times)."""
        m0 = frame[0]
        sensor = self.sensors[m0.node]
        for m in frame:
            if not m.clutter:   # the oracle knows which detections are false
                self.oracle.add(m.t, m.z, sensor, seq=seq)
        fe = self.front.get(m0.node)
        update = fe.reference_frame(m0.t, np.array([m.z for m in frame])) if fe is not None else None
        if update is not None:
            self.fair.add_frame(m0.t, update, seq=seq)
        else:
            for m in frame:
                self.fair.add(m.t, m.z, sensor, seq=seq)

    def estimate(self, t: float) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
        """``((fair mean, cov), (oracle mean, cov))`` at ``t``."""
        return self.fair.estimate(t), self.oracle.estimate(t)


def final_rounds(nodes: dict[str, FusionNode], graph: nx.Graph) -> None:
    """:func:`dfusion.topology.settling_rounds` rounds in which every node sends to every
    neighbour, losslessly."""
    for _ in range(settling_rounds(graph)):
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in sorted(nodes) for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)


def compute_metrics(sc, res: SimulationResult, nodes, c_final, net, n_meas, refused,
                    front_ends: dict[str, Any] | None = None) -> dict[str, Any]:
    """The figures of a run (the JSON keys of docs/scenarios.md).

    ``nodes`` maps names to objects with ``estimate()`` and ``stats`` (and, for the
    diagnostics, ``guard`` and ``health()``); ``c_final`` is the fair centralized mean at the
    end; ``net`` has ``stats.total`` (delivered, dropped); ``front_ends`` (optional) gives the
    camera counters. Shared by ``dfusion simulate`` and ``dfusion run``.
    """
    axes = sc.target.axes
    motion = sc.target.motion
    resid = motion.residual if motion.angle_indices else None
    out: dict[str, Any] = {
        "scenario": sc.path,
        "seed": sc.seed,
        "fusion": sc.fusion,
        "steps": len(res.times),
        "state_dim": motion.dim,
        "nees_interval": list(chi2_interval(motion.dim, 1)),
        "centralized": {
            "rmse": rmse(res.central_mean, res.truth, axes),
            "anees": float(np.mean(nees(res.central_mean, res.central_cov, res.truth, resid))),
        },
        "nodes": {},
    }
    o_final = getattr(res, "oracle_final", None)
    out["centralized_oracle"] = None   # a result without the oracle reference (dfusion run's, for now)
    if getattr(res, "oracle_mean", None) is not None:
        out["centralized_oracle"] = {
            "rmse": rmse(res.oracle_mean, res.truth, axes),
            "anees": float(np.mean(nees(res.oracle_mean, res.oracle_cov, res.truth, resid))),
        }
    prot = getattr(sc, "protection", None)
    if prot is not None:
        out["protection"] = prot.describe()
    health = getattr(res, "health", None) or {}
    for nm, node in nodes.items():
        final_mean, _ = node.estimate()
        gap = np.abs(res.node_mean[nm] - res.central_mean).max(axis=1)
        out["nodes"][nm] = {
            "rmse": rmse(res.node_mean[nm], res.truth, axes),
            "anees": float(np.mean(nees(res.node_mean[nm], res.node_cov[nm], res.truth, resid))),
            "final_gap": float(np.max(np.abs(final_mean - c_final))),
            "final_gap_oracle": float(np.max(np.abs(final_mean - o_final))) if o_final is not None else None,
            "mean_gap": float(np.mean(gap)),
            "messages": node.stats.messages_sent,
            "bytes": node.stats.bytes_sent,
            "rejected": node.stats.messages_rejected,
        }
        out["nodes"][nm].update(node_diagnostics(node, (front_ends or {}).get(nm), health.get(nm)))
        o = res.outputs.get(nm)
        if o is not None:
            out["nodes"][nm]["output"] = output_metrics(o, res.truth, axes, resid)
    total = net.stats.total
    out["messages"] = int(sum(v["messages"] for v in out["nodes"].values()))
    out["bytes"] = int(sum(v["bytes"] for v in out["nodes"].values()))
    out["messages_delivered"] = int(total.delivered)
    out["messages_dropped"] = int(total.dropped)
    out["measurements"] = n_meas
    out["measurements_refused"] = refused
    return out


def node_health(node, front=None) -> str:
    """The worse of the node's health (its guard: quarantines) and its front end's status (a
    camera's track loss): ``"ok"`` < ``"degraded"`` < ``"lost"``."""
    order = ("ok", "degraded", "lost")
    states = [node.health() if hasattr(node, "health") else "ok"]
    if front is not None:
        states.append(front.status())
    return max(states, key=order.index)


def node_diagnostics(node, front=None, health_series: list[str] | None = None) -> dict[str, Any]:
    """Per-node diagnostics (``docs/clutter.md``): the consistency test of the neighbours'
    information (``nis_mean``, ``tests``, ``failures``, ``quarantines``, ``quarantined``,
    ``untested_blocks``), a camera's ``detections``, those ``gated``, its ``camera_nis`` and
    ``track_losses``, and the health at the end (``health``) and per step (``health_steps``).
    Every key is present; None where the object does not report it (no guard, not a camera,
    or a ``dfusion run`` node, whose process does not send them)."""
    out: dict[str, Any] = {"tests": None, "failures": None, "nis_mean": None, "quarantines": None,
                           "quarantined": [], "untested_blocks": None, "gated": None, "detections": None,
                           "camera_nis": None, "track_losses": None, "health": None, "health_steps": None}
    guard = getattr(node, "guard", None)
    if guard is not None:
        out.update(guard.summary())
    st = getattr(front, "stats", None)
    if st is not None and hasattr(st, "gated"):
        out["gated"] = int(st.gated)
        out["detections"] = int(st.detections)
        out["camera_nis"] = None if math.isnan(st.nis_mean) else float(st.nis_mean)
        out["track_losses"] = int(getattr(st, "losses", 0))
    if hasattr(node, "health"):
        out["health"] = node_health(node, front)
        series = health_series or []
        out["health_steps"] = {h: int(sum(1 for x in series if x == h)) for h in ("ok", "degraded", "lost")}
    return out


def output_metrics(o: NodeOutput, truth: Array, axes: int, resid=None) -> dict[str, Any]:
    """Figures of a node's policy output: RMSE and ANEES against the truth, the number of
    switches (changes of the chosen source between steps) and each source's share of steps."""
    names, counts = np.unique(np.array(o.source), return_counts=True)
    return {
        "policy": o.policy,
        "rmse": rmse(o.mean, truth, axes),
        "anees": float(np.mean(nees(o.mean, o.cov, truth, resid))),
        "switches": int(sum(a != b for a, b in zip(o.source, o.source[1:]))),
        "sources": {str(nm): float(c / len(o.source)) for nm, c in zip(names, counts)},
    }
