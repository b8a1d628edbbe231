"""Run a scenario in one process: fusion nodes on a simulated network, and the
centralized EKF on the union of all measurements as the reference.

Every step ``t = k dt``:

1. every node predicts to ``t``;
2. measurements that have reached their node by ``t`` are fused (late ones at
   their own time stamp; one older than the window is refused and counted);
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
"""
from __future__ import annotations

import json
import logging
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
    node_mean, node_cov : dict name -> (K, n), (K, n, n)
    outputs : dict name -> NodeOutput
        The policy output of the nodes whose policy is not plain fusion.
    metrics : dict
        The figures printed and written to JSON (see :meth:`to_json`).
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

    def to_json(self) -> str:
        return json.dumps(self.metrics, indent=2, sort_keys=True)

    def table(self) -> str:
        """The summary table printed by ``dfusion simulate``."""
        m = self.metrics
        rows = [("node", "RMSE [m]", "ANEES", "final gap", "mean gap", "sent", "bytes")]
        for name, v in m["nodes"].items():
            rows.append((name, f"{v['rmse']:.4f}", f"{v['anees']:.3f}", f"{v['final_gap']:.2e}",
                         f"{v['mean_gap']:.2e}", str(v["messages"]), str(v["bytes"])))
        c = m["centralized"]
        rows.append(("centralized", f"{c['rmse']:.4f}", f"{c['anees']:.3f}", "-", "-", "-", "-"))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths))) for r in rows]
        lines.insert(1, "-" * len(lines[0]))
        lo, hi = m["nees_interval"]
        lines.append("")
        lines.append(f"fusion={m['fusion']} seed={m['seed']} steps={m['steps']} state dim={m['state_dim']}: "
                     f"ANEES 95% interval for one run [{lo:.3f}, {hi:.3f}] (time-correlated: indicative)")
        lines.append(f"messages {m['messages']} ({m['messages_delivered']} delivered, {m['messages_dropped']} lost), "
                     f"bytes {m['bytes']}, measurements {m['measurements']} ({m['measurements_refused']} refused: older than the window)")
        outs = {name: v["output"] for name, v in m["nodes"].items() if "output" in v}
        if outs:
            lines.append("")
            lines.append("policy outputs (node.output(): the source each node's policy chose)")
            for name, o in outs.items():
                share = ", ".join(f"{src} {frac:.0%}" for src, frac in o["sources"].items())
                lines.append(f"  {name}: policy {o['policy']}, RMSE {o['rmse']:.4f}, ANEES {o['anees']:.3f}, "
                             f"switches {o['switches']}; {share}")
        return "\n".join(lines)


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
    central = CentralizedEKF(motion, 0.0, sc.target.initial_mean, sc.target.initial_cov)
    sensors = {name: spec.sensor for name, spec in sc.nodes.items()}
    front = build_front_ends(sc)
    names = sorted(nodes)
    K = sc.steps + 1
    n = motion.dim
    times = np.round(sc.dt * np.arange(K), 9)
    truth = np.array([world.truth(t) for t in times])
    node_mean = {nm: np.empty((K, n)) for nm in names}
    node_cov = {nm: np.empty((K, n, n)) for nm in names}
    c_mean, c_cov = np.empty((K, n)), np.empty((K, n, n))
    outputs = {nm: NodeOutput(nodes[nm].policy.name, np.empty((K, n)), np.empty((K, n, n)), [""] * K)
               for nm in names if records_output(nodes[nm])}
    by_arrival = sorted(world.measurements, key=lambda m: (m.arrival, m.t, m.node))
    by_time = world.measurements  # already in time order
    next_send = {nm: sc.nodes[nm].send_period for nm in names}
    ia = ic = 0
    refused = 0

    def record(k: int) -> None:
        for nm in names:
            node_mean[nm][k], node_cov[nm][k] = nodes[nm].estimate()
        for nm, o in outputs.items():
            chosen = nodes[nm].output()
            o.mean[k], o.cov[k], o.source[k] = chosen.mean, chosen.cov, chosen.name
        c_mean[k], c_cov[k] = central.estimate(times[k])

    record(0)
    for k in _progress(range(1, K), progress, K - 1):
        t = float(times[k])
        for nm in names:
            nodes[nm].predict(t)
        while ia < len(by_arrival) and by_arrival[ia].arrival <= t + 1e-9:
            m = by_arrival[ia]
            try:
                front[m.node].process(nodes[m.node], m.t, m.z)
            except OutsideWindowError:
                refused += 1
                log.info("%s: measurement at t=%.3f arrived after it left the window", m.node, m.t)
            ia += 1
        while ic < len(by_time) and by_time[ic].t <= t + 1e-9:
            m = by_time[ic]
            if not m.clutter:   # the reference knows which detections are false
                central.add(m.t, m.z, sensors[m.node], seq=ic)
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
    for m in by_arrival[ia:]:
        try:
            front[m.node].process(nodes[m.node], m.t, m.z)
        except OutsideWindowError:
            refused += 1
    for m in by_time[ic:]:
        if not m.clutter:
            central.add(m.t, m.z, sensors[m.node], seq=ic)
        ic += 1
    final_rounds(nodes, sc.graph)
    T = float(times[-1])
    c_final, _ = central.estimate(T)

    result = SimulationResult(sc, world, times, truth, c_mean, c_cov, node_mean, node_cov, outputs=outputs)
    result.metrics = compute_metrics(sc, result, nodes, c_final, net, len(world.measurements), refused)
    return result


def final_rounds(nodes: dict[str, FusionNode], graph: nx.Graph) -> None:
    """:func:`dfusion.topology.settling_rounds` rounds in which every node sends to every
    neighbour, losslessly."""
    for _ in range(settling_rounds(graph)):
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in sorted(nodes) for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)


def compute_metrics(sc, res: SimulationResult, nodes, c_final, net, n_meas, refused) -> dict[str, Any]:
    """The figures of a run (the JSON keys of docs/scenarios.md).

    ``nodes`` maps names to objects with ``estimate()`` and ``stats``; ``c_final`` is the
    centralized mean at the end; ``net`` has ``stats.total`` (delivered, dropped).
    Shared by ``dfusion simulate`` and ``dfusion run``.
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
    for nm, node in nodes.items():
        final_mean, _ = node.estimate()
        gap = np.abs(res.node_mean[nm] - res.central_mean).max(axis=1)
        out["nodes"][nm] = {
            "rmse": rmse(res.node_mean[nm], res.truth, axes),
            "anees": float(np.mean(nees(res.node_mean[nm], res.node_cov[nm], res.truth, resid))),
            "final_gap": float(np.max(np.abs(final_mean - c_final))),
            "mean_gap": float(np.mean(gap)),
            "messages": node.stats.messages_sent,
            "bytes": node.stats.bytes_sent,
            "rejected": node.stats.messages_rejected,
        }
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
