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
centralized one (``final_gap_position`` in metres and ``final_gap_velocity`` in
m/s split it by unit).

Two centralized references run on the world's measurements, in time order and
without delay (:class:`References`): the *fair* one (``centralized``) gets every
detection, false ones included, through the same gate and clutter model as the
camera nodes (:meth:`dfusion.frontends.base.FrontEnd.reference_frame`), and is what
the gaps are measured against; the *oracle* (``centralized_oracle``) skips the false
detections (it knows which they are) and gates nothing.

Per node the run also reports the diagnostics of ``docs/clutter.md``: the
consistency test of the neighbours' information (:mod:`dfusion.fusion.guard`),
a camera's gated detections, NIS and track losses, and the health state per
step (``ok``, ``degraded``, ``lost``), with ``WARNING`` lines in the table for
nodes that were lost at some step or are inconsistent.

The world is simulated from the scenario (:func:`dfusion.sim.world.simulate_world`)
unless one is given: :mod:`dfusion.sim.replay` reads it from a ROS bag.

**Links that change** (``Scenario.dynamic``: ``[[events]]``, radio ranges;
:mod:`dfusion.sim.links`): before step 1 of every time step the links that exist then are
applied to the nodes and the network (nodes join and leave); nodes send over every link
(fusion messages on tree links, beacons on the others), and a node whose tree links changed
sends at once instead of waiting for its send period (:attr:`FusionNode.urgent`). The end
runs lossless rounds until the tree rule has settled, then ``diameter + 2`` more. Nodes
absent from the network have no estimate (NaN) for those steps; their figures are over the
steps they were present. ``metrics["links"]`` lists every change of the links with the
send periods the tree and the information took to settle after it.

Message counts add up (``metrics["traffic"]``, checked by the tests): the messages
sent over the network plus the copies the links duplicated equal those delivered
plus those dropped plus those still in flight (none at the end); every delivered
copy is fused or rejected by its receiver; the final lossless rounds are counted
apart.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from dfusion.errors import MessageError, OutsideWindowError
from dfusion.estimation.centralized import CentralizedEKF
from dfusion.fusion.node import FusionNode
from dfusion.fusion.sending import SendSchedule
from dfusion.linalg import Array
from dfusion.metrics import chi2_interval, nees, rmse
from dfusion.models.base import model_at
from dfusion.policies.base import records_output as policy_records_output
from dfusion.scenario.build import build_front_ends, build_nodes
from dfusion.scenario.spec import Scenario
from dfusion.fusion.tree import forest_settled, tree_components
from dfusion.sim.links import DynamicLinks, agreed_edges
from dfusion.sim.world import World, simulate_world
from dfusion.transport.simulated import SimulatedNetwork
from dfusion.topology import Tree, settling_rounds

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)

#: Bound on the rounds of message deliveries and sends between two steps (event sends); a
#: minimum interval of ``m`` allows at most ``dt / m + 1`` sends per link per step.
MAX_EVENTS_PER_STEP = 10_000


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
    return policy_records_output(node.policy)


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
    #: What happened to each measurement a node's front end processed:
    #: ``{"t": step time, "node", "t_meas", "z", "outcome"}`` with ``outcome`` the
    #: front-end counters that moved (``"contributed"``, ``"gated"``, ...) while the
    #: frame it belongs to was processed, or ``"refused"`` (older than the window).
    #: Filled by :func:`run_scenario`.
    events: list[dict[str, Any]] = field(default_factory=list)
    oracle_mean: Array | None = None
    oracle_cov: Array | None = None
    oracle_final: Array | None = None
    health: dict[str, list[str]] = field(default_factory=dict)
    #: Links that change: the :class:`~dfusion.sim.links.DynamicLinks` of the run (its
    #: schedule, its changes, the tree at every step); None for a fixed tree.
    links: DynamicLinks | None = None

    def to_json(self, series: bool = False) -> str:
        """The metrics as JSON; with ``series`` also the per-step time series
        (:func:`dfusion.sim.runner.series_of`) under the key ``"series"``."""
        out = dict(self.metrics, series=series_of(self)) if series else self.metrics
        return json.dumps(out, indent=2, sort_keys=True)

    def table(self) -> str:
        """The summary table printed by ``dfusion simulate``: every number with its unit,
        the ANEES in plain words, message counts that add up."""
        m = self.metrics
        dim = m["state_dim"]
        vel = any("final_gap_velocity" in v for v in m["nodes"].values())
        diag = all(v.get("health") is not None for v in m["nodes"].values())
        head = ["node", "RMSE [m]", "ANEES [-]", "final gap pos [m]"] + (["final gap vel [m/s]"] if vel else []) + \
            ["mean gap pos [m]"] + (["mean gap vel [m/s]"] if vel else []) + ["sent [msgs]", "sent [bytes]"] + \
            (["NIS [-]", "gated", "quar.", "health"] if diag else [])
        rows = [head]
        def gap(x):
            return "left" if x is None else f"{x:.2e}"
        for name, v in m["nodes"].items():
            row = [name, known(v['rmse'], ".4f"), known(v['anees'], ".3f"), gap(v['final_gap_position'])]
            if vel:
                row.append(gap(v['final_gap_velocity']))
            row.append(f"{v['mean_gap_position']:.2e}")
            if vel:
                row.append(f"{v['mean_gap_velocity']:.2e}")
            row += [str(v["messages"]), str(v["bytes"])]
            if diag:
                nis, gated = v.get("nis_mean"), v.get("gated")
                row += ["-" if nis is None else f"{nis:.2f}", "-" if gated is None else str(gated),
                        ",".join(v.get("quarantined") or []) or "-", v["health"]]
            rows.append(row)
        for key, label in (("centralized", "centralized"), ("centralized_oracle", "central oracle")):
            c = m.get(key)
            if c is not None:
                rows.append([label, known(c['rmse'], ".4f"), known(c['anees'], ".3f")] + ["-"] * (len(head) - 3))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths))) for r in rows]
        lines.insert(1, "-" * len(lines[0]))
        lo, hi = m["nees_interval"]
        lines.append("")
        lines.append(f"fusion={m['fusion']} seed={m['seed']} steps={m['steps']} state dim={dim}; "
                     "gap: node minus centralized EKF (pos: distance in m, vel: in m/s)")
        lines.append(f"ANEES = NEES (e' P^-1 e, the error weighted by the filter's covariance) averaged over the run; "
                     f"a consistent filter averages {dim}, the state dimension.")
        a_lo, a_hi = m.get("anees_interval_independent", (lo, hi))
        lines.append(f"  95% ranges for a consistent filter: one step's NEES [{lo:.2f}, {hi:.2f}]; the average of "
                     f"{m['steps']} independent steps [{a_lo:.2f}, {a_hi:.2f}] (successive steps are correlated, so "
                     f"expect more spread). Far above {dim}: overconfident; far below: too cautious.")
        lines.extend(traffic_lines(m))
        lines.extend(send_lines(m))
        if diag:
            lines.append("NIS: mean consistency statistic per degree of freedom of the neighbours' information "
                         "(expected 1); gated: own detections outside the gate; quar.: quarantined neighbours "
                         f"at the end; protection: {m.get('protection', '-')}; centralized: the same detections "
                         "through the same association (fair), central oracle: false detections skipped")
        if "links" in m:
            lines.extend(link_lines(m["links"]))
        lines.extend(warning_lines(m))
        outs = {name: v["output"] for name, v in m["nodes"].items() if "output" in v}
        if outs:
            lines.append("")
            lines.append("policy outputs (node.output(): the source each node's policy chose)")
            for name, o in outs.items():
                share = ", ".join(f"{src} {frac:.0%}" for src, frac in o["sources"].items())
                lines.append(f"  {name}: policy {o['policy']}, RMSE {known(o['rmse'], '.4f')} m, "
                             f"ANEES {known(o['anees'], '.3f')}, "
                             f"switches {o['switches']}; {share}")
        return "\n".join(lines)


def known(x: float, fmt: str) -> str:
    """``x`` formatted, or ``unknown`` when it is NaN (no truth): never a bare ``nan``."""
    return format(x, fmt) if math.isfinite(x) else "unknown"


def link_lines(lk: dict[str, Any]) -> list[str]:
    """The changes of the links and the tree, with their settling times, as table lines."""
    period = lk["send_period"]
    st = lk["settling_tree_changes"]

    def fmt(v):
        return "-" if v is None else f"{v:.1f}"
    lines = ["", f"links that change: {lk['link_changes']} changes of the links, {lk['tree_changes']} of them changed "
             f"the fusion tree ({lk['epochs_started']} new tree epochs started); settling in send periods of "
             f"{period:g} s after a change of the tree: tree median {fmt(st['tree']['median'])}, max "
             f"{fmt(st['tree']['max'])}; information median {fmt(st['information']['median'])}, max "
             f"{fmt(st['information']['max'])} (over {st['count']} changes that settled before the next one)"]
    rows = [["t [s]", "what changed", "tree changed", "tree settled [send periods]", "information settled [send periods]"]]
    for c in lk["changes"]:
        info = fmt(c["info_settled_send_periods"])
        if c["overlapped"]:
            info += " (next change first)" if c["info_settled_send_periods"] is None else " (overlapped)"
        rows.append([f"{c['t']:.1f}", "; ".join(c["what"]), "yes" if c["tree_changed"] else "no",
                     fmt(c["tree_settled_send_periods"]), info])
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines += ["  " + "  ".join(cell.ljust(w) if i == 1 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths)))
              for r in rows]
    lines.append("  (tree settled: one epoch and an agreed spanning tree in every component; information settled: "
                 "every node holds everything its component measured up to the change, once)")
    return lines


def traffic_lines(m: dict[str, Any]) -> list[str]:
    """Message and measurement counts of the metrics, in words (each line adds up)."""
    tr = m.get("traffic")
    lines = []
    if tr is not None:
        net = tr["network"]
        lines.append(f"messages over the network: {net['sent']} sent + {net['duplicated']} duplicated copies = "
                     f"{net['delivered']} delivered + {net['dropped']} dropped + {net['in_flight']} in flight; "
                     f"of the delivered: {tr['fused']} fused + {tr['rejected']} rejected")
        if tr.get("ignored"):
            lines[-1] += f" + {tr['ignored']} ignored (already had)"
        if tr.get("rejected_on_arrival"):
            lines.append(f"not delivered: {tr['rejected_on_arrival']} copies rejected on arrival (garbage, forged or "
                         f"foreign traffic dropped by the checks before the queue)")
        if tr.get("final_rounds_over_network"):
            lines.append(f"(the final rounds went over the network too); {m['messages']} messages "
                         f"({m['bytes']} bytes) built by the nodes in all")
        else:
            lines.append(f"final lossless rounds: {tr['final_rounds']} messages; {m['messages']} messages "
                         f"({m['bytes']} bytes) sent by the nodes in all")
    else:
        lines.append(f"messages {m['messages']} ({m['messages_delivered']} delivered), bytes {m['bytes']}")
    mr = m.get("measurements_detail")
    if mr is not None:
        lines.append(f"measurements: {m['measurements']} taken = {mr['fused']} used + {mr['rejected']} rejected by "
                     f"their front end (gate, unusable) + {m['measurements_refused']} refused (older than the window)")
    else:
        lines.append(f"measurements {m['measurements']} ({m['measurements_refused']} refused: older than the window)")
    return lines


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
        if math.isfinite(v["anees"]) and not lo <= v["anees"] <= hi:
            side = "over-confident" if v["anees"] > hi else "conservative"
            out.append(f"WARNING {name}: inconsistent, ANEES {v['anees']:.3g} outside [{lo:.3f}, {hi:.3f}] ({side})")
    return out


#: Seconds between two progress lines when stderr is not a terminal (a pipe, a log file).
PROGRESS_INTERVAL = 10.0


class Progress:
    """Progress of ``total`` steps on stderr: a tqdm bar on a terminal; elsewhere (piped,
    redirected) one line every :data:`PROGRESS_INTERVAL` seconds and one at the end
    (``progress: 301/600 steps (50 %), 20 s``), so a long run piped into a file or a CI log shows
    it is alive. :meth:`update` takes the number of steps done (and a note for the bar);
    :meth:`close` ends it. ``simulate`` and ``replay`` (:func:`run_scenario`) and ``dfusion run``'s
    launcher use it."""

    def __init__(self, total: int, *, desc: str | None = None, stream=None) -> None:
        import sys
        import time

        self.total, self.stream = total, stream if stream is not None else sys.stderr
        self.n, self._written, self._note, self._clock = 0, None, "", time.monotonic
        self.start = self._last = self._clock()
        self.bar = None
        if self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="step", leave=False, file=self.stream, desc=desc)

    def update(self, n: int, note: str = "") -> None:
        """``n`` steps done of ``total``; ``note`` is shown after the count (e.g. ``alive 3/3``)."""
        if self.bar is not None:
            if note != self._note:
                self.bar.set_postfix_str(note, refresh=n == self.bar.n)
            if n != self.bar.n:
                self.bar.update(n - self.bar.n)   # redrawn at most every tqdm's mininterval
        self.n, self._note = n, note
        if self.bar is None:
            now = self._clock()
            if now - self._last >= PROGRESS_INTERVAL or (n == self.total and self._written != n):
                self._last = now
                self._line(now)

    def _line(self, now: float) -> None:
        self._written = self.n
        note = f", {self._note}" if self._note else ""
        self.stream.write(f"progress: {self.n}/{self.total} steps ({100.0 * self.n / max(self.total, 1):.0f} %), "
                          f"{now - self.start:.0f} s{note}\n")
        self.stream.flush()

    def close(self) -> None:
        """The bar goes; off a terminal, the last count is written unless it was just written."""
        if self.bar is not None:
            self.bar.close()
        elif self._written != self.n:
            self._line(self._clock())


def _progress(iterable, enabled: bool, total: int):
    """``iterable`` with :class:`Progress` of ``total`` steps on stderr (when ``enabled``)."""
    if not enabled:
        yield from iterable
        return
    p = Progress(total)
    try:
        for k, item in enumerate(iterable, 1):
            yield item
            p.update(k)
    finally:
        p.close()


def run_scenario(sc: Scenario, *, progress: bool = False, world: World | None = None,
                 on_step: Callable[..., None] | None = None) -> SimulationResult:
    """Simulate ``sc`` with every node in this process; see the module docstring.

    ``world``: the truth and measurements to use (default: simulated from ``sc``; a
    recording, :func:`dfusion.sim.replay.world_from_bag`). ``on_step(t, estimates,
    truth, events)`` is called after every step with each node's ``(mean, cov)`` (and
    ``"centralized"``) and the events (:attr:`SimulationResult.events`) since the last
    call: a live view (:class:`dfusion.viz.foxglove.LiveView`).
    """
    world = simulate_world(sc) if world is None else world
    dyn = DynamicLinks(sc) if sc.dynamic else None
    if dyn is None:
        nodes = build_nodes(sc)
        net = SimulatedNetwork(((a, b, spec) for (a, b), spec in sc.links.items()), seed=sc.seed)
    else:
        nodes, net = dyn.start()
    motion = sc.target.motion
    front = build_front_ends(sc)
    refs = References(sc, front)
    names = sorted(sc.nodes)
    K = sc.steps + 1
    n = motion.dim
    times = np.round(sc.dt * np.arange(K), 9)
    truth = np.array([world.truth(t) for t in times])
    node_mean = {nm: np.full((K, n), np.nan) for nm in names}
    node_cov = {nm: np.full((K, n, n), np.nan) for nm in names}
    c_mean, c_cov = np.empty((K, n)), np.empty((K, n, n))
    o_mean, o_cov = np.full((K, n), np.nan), np.full((K, n, n), np.nan)
    health = {nm: [""] * K for nm in names}
    outputs: dict[str, NodeOutput] = {}

    def add_output(nm: str) -> None:
        if records_output(nodes[nm]):
            outputs[nm] = NodeOutput(nodes[nm].policy.name, np.full((K, n), np.nan), np.full((K, n, n), np.nan),
                                     [""] * K)

    for nm in names:
        if nm in nodes:
            add_output(nm)
    by_arrival = frames(sorted(world.measurements, key=lambda m: (m.arrival, m.t, m.node)))
    by_time = frames(world.measurements)  # already in time order
    sched = {nm: SendSchedule(sc.nodes[nm].send_period, sc.min_send_interval, sc.sends) for nm in names}
    ia = ic = 0
    refused = 0
    events: list[dict[str, Any]] = []
    counts = {"fused": 0, "rejected": 0, "final_rounds": 0, "used": 0, "dropped_by_front_end": 0}

    def process(frame: list, t_step: float) -> None:
        """Fuse one frame (the measurements of one node at one time) at its node."""
        nonlocal refused
        m0 = frame[0]
        if m0.node not in nodes:   # the node left before the measurement reached it
            refused += len(frame)
            events.extend({"t": t_step, "node": m.node, "t_meas": m.t, "z": m.z, "outcome": ["refused"]}
                          for m in frame)
            return
        fe = front[m0.node]
        before = fe.health()
        try:
            fe.process_frame(nodes[m0.node], m0.t, np.array([m.z for m in frame]))
        except OutsideWindowError:
            refused += len(frame)
            log.info("%s: measurement at t=%.3f arrived after it left the window", m0.node, m0.t)
            events.extend({"t": t_step, "node": m.node, "t_meas": m.t, "z": m.z, "outcome": ["refused"]}
                          for m in frame)
            return
        after = fe.health()
        moved = [k for k, v in after.items() if k != "processed" and v != before.get(k)]
        used = min(max(int(after.get("contributed", 0) - before.get("contributed", 0)), 0), len(frame))
        counts["used"] += used
        counts["dropped_by_front_end"] += len(frame) - used
        events.extend({"t": t_step, "node": m.node, "t_meas": m.t, "z": m.z, "outcome": moved} for m in frame)

    def deliver(dst: str, data: bytes) -> None:
        try:
            nodes[dst].receive(data)
            counts["fused"] += 1
        except MessageError as exc:  # a simulated network never corrupts; log anyway
            counts["rejected"] += 1
            log.warning("%s: %s", dst, exc)

    def between_steps(t0: float, t1: float) -> None:
        """Event sends: the messages that arrive in ``(t0, t1)``, in arrival order, and the sends
        they and the minimum intervals trigger (:class:`SendSchedule`); the nodes' states stay at
        ``t0`` (the next step predicts)."""
        for _ in range(MAX_EVENTS_PER_STEP):
            here = [nm for nm in names if nm in nodes]
            tau = min(net.next_arrival(here), min((sched[nm].next_event(nodes[nm]) for nm in here), default=math.inf))
            tau = max(tau, t0)
            if tau > t1 - 1e-9:
                return
            for nm in here:
                for d in net.receive(nm, tau + 1e-12):
                    deliver(nm, d.data)
            for nm in here:
                for nb, data in sched[nm].due(nodes[nm], tau):
                    net.send(nm, nb, data, tau)
        log.warning("more than %d send events between t=%.3f and %.3f: the rest waits for the next step",
                    MAX_EVENTS_PER_STEP, t0, t1)

    seen = [0]

    def record(k: int) -> None:
        for nm in names:
            if nm in nodes:
                node_mean[nm][k], node_cov[nm][k] = nodes[nm].estimate()
        for nm, o in outputs.items():
            chosen = nodes[nm].output()
            o.mean[k], o.cov[k], o.source[k] = chosen.mean, chosen.cov, chosen.name
        for nm in names:
            if nm in nodes:
                health[nm][k] = node_health(nodes[nm], front.get(nm))
        (c_mean[k], c_cov[k]), (o_mean[k], o_cov[k]) = refs.estimate(times[k])
        if on_step is not None:
            est = {nm: (node_mean[nm][k], node_cov[nm][k]) for nm in names if nm in nodes}
            est["centralized"] = (c_mean[k], c_cov[k])
            on_step(float(times[k]), est, truth[k], events[seen[0]:])
            seen[0] = len(events)

    record(0)
    for k in _progress(range(1, K), progress, K - 1):
        t = float(times[k])
        if dyn is not None:
            dyn.step(t, on_join=add_output)
        for nm in names:
            if nm in nodes:
                nodes[nm].predict(t)
        while ia < len(by_arrival) and by_arrival[ia][0].arrival <= t + 1e-9:
            process(by_arrival[ia], t)
            ia += 1
        while ic < len(by_time) and by_time[ic][0].t <= t + 1e-9:
            refs.add(by_time[ic], seq=ic)
            ic += 1
        for nm in names:
            if nm in nodes:
                for d in net.receive(nm, t + 1e-9):
                    deliver(nm, d.data)
        for nm in names:
            node = nodes.get(nm)
            if node is not None:
                for nb, data in sched[nm].due(node, t):
                    net.send(nm, nb, data, t)
        if dyn is not None:
            dyn.observe(t)
        record(k)
        if sc.sends == "event" and k + 1 < K:
            between_steps(t, float(times[k + 1]))

    # the end: every message in flight, every late measurement, then lossless rounds
    T = float(times[-1])
    for d in net.flush():
        deliver(d.dst, d.data)
    for frame in by_arrival[ia:]:
        process(frame, T)
    for frame in by_time[ic:]:
        refs.add(frame, seq=ic)
        ic += 1
    for nm, fe in front.items():
        if nm in nodes:
            fe.finish(nodes[nm])
    if dyn is None:
        counts["final_rounds"] = final_rounds(nodes, sc.tree)
    else:
        counts["final_rounds"] = final_rounds_changing(nodes, dyn.links)
        dyn.end(T)
    (c_final, _), (o_final, _) = refs.estimate(T)

    result = SimulationResult(sc, world, times, truth, c_mean, c_cov, node_mean, node_cov, outputs=outputs,
                              events=events, oracle_mean=o_mean, oracle_cov=o_cov, oracle_final=o_final,
                              health=health, links=dyn)
    everyone = nodes if dyn is None else dyn.all_nodes()
    result.metrics = compute_metrics(sc, result, everyone, c_final, net, len(world.measurements), refused,
                                     front_ends=front, present=set(nodes))
    if dyn is not None:
        result.metrics["links"] = dyn.metrics()
    total = net.stats.total
    result.metrics["traffic"] = {
        "network": {"sent": int(total.sent), "duplicated": int(total.duplicated), "delivered": int(total.delivered),
                    "dropped": int(total.dropped), "in_flight": int(total.in_flight)},
        "fused": counts["fused"], "rejected": counts["rejected"], "final_rounds": counts["final_rounds"],
    }
    result.metrics["measurements_detail"] = {"fused": counts["used"], "rejected": counts["dropped_by_front_end"]}
    result.metrics["sends"] = send_metrics(sc, net.stats.links, sum(s.event_messages for s in sched.values()))
    return result


def send_metrics(sc: Scenario, links: dict, event_messages: int) -> dict[str, Any]:
    """How the nodes sent (``metrics["sends"]``; ``dfusion run`` has the mode and the interval
    only, the other keys None or empty): the mode, the minimum interval, the messages
    sent because of news, and per link (both directions, ``"a-b"``) the bytes and messages per
    second over the run (what went over the network; the final lossless rounds apart), with
    their median and largest over the links that carried anything."""
    per: dict[str, dict[str, float]] = {}
    for (a, b), st in links.items():
        key = "-".join(sorted((a, b)))
        e = per.setdefault(key, {"bytes_per_s": 0.0, "messages_per_s": 0.0})
        e["bytes_per_s"] += st.bytes_sent / sc.duration
        e["messages_per_s"] += st.sent / sc.duration
    used = [v for v in per.values() if v["messages_per_s"] > 0]
    bps = sorted(v["bytes_per_s"] for v in used)
    mps = sorted(v["messages_per_s"] for v in used)
    return {"mode": sc.sends, "min_interval": sc.min_send_interval, "event_messages": int(event_messages),
            "links": dict(sorted(per.items())),
            "bytes_per_link_per_s": {"median": float(np.median(bps)) if bps else 0.0, "max": bps[-1] if bps else 0.0},
            "messages_per_link_per_s": {"median": float(np.median(mps)) if mps else 0.0,
                                        "max": mps[-1] if mps else 0.0}}


def send_lines(m: dict[str, Any]) -> list[str]:
    """The ``sends`` metrics as a table line."""
    se = m.get("sends")
    if se is None:
        return []
    events = "" if se["event_messages"] is None else f"; {se['event_messages']} event messages"
    how = (f"event-triggered (news at once, at least {se['min_interval']:g} s apart per link, plus the periodic "
           f"heartbeat{events})" if se["mode"] == "event" else "periodic only")
    b, n = se["bytes_per_link_per_s"], se["messages_per_link_per_s"]
    if b is None:   # dfusion run: no counts per link
        return [f"sends: {how}"]
    return [(f"sends: {how}; per link (both directions): median {b['median']:.0f} B/s, max {b['max']:.0f} B/s; "
             f"median {n['median']:.1f} msgs/s, max {n['max']:.1f} msgs/s")]


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
    applies it (:meth:`dfusion.frontends.base.FrontEnd.reference_frame`: a camera's gate and
    clutter model), or as EKF updates with the sensor's model. ``oracle``: every true
    measurement as an EKF update, false detections skipped.
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
                self.oracle.add(m.t, m.z, model_at(sensor, m.t), seq=seq)
        fe = self.front.get(m0.node)
        update = fe.reference_frame(m0.t, np.array([m.z for m in frame])) if fe is not None else None
        if update is not None:
            self.fair.add_frame(m0.t, update, seq=seq)
        else:
            for m in frame:
                self.fair.add(m.t, m.z, model_at(sensor, m.t), seq=seq)

    def estimate(self, t: float) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
        """``((fair mean, cov), (oracle mean, cov))`` at ``t``."""
        return self.fair.estimate(t), self.oracle.estimate(t)


def final_rounds(nodes: dict[str, FusionNode], graph: Tree | nx.Graph) -> int:
    """:func:`dfusion.topology.settling_rounds` rounds in which every node sends to every
    neighbour, losslessly; returns the number of messages."""
    n = 0
    for _ in range(settling_rounds(graph)):
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in sorted(nodes) for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)
        n += len(msgs)
    return n


def final_rounds_changing(nodes: dict[str, FusionNode], links: set[tuple[str, str]]) -> int:
    """Links that change: lossless rounds over every link (fusion messages and beacons) until the
    tree rule has settled (at most one per node), then :func:`dfusion.topology.settling_rounds`
    of the largest tree; returns the number of messages."""
    n = 0

    def one_round() -> int:
        msgs = [(nb, data) for nm in sorted(nodes) for nb, data in nodes[nm].outgoing()]
        for nb, data in msgs:
            nodes[nb].receive(data)
        return len(msgs)

    for _ in range(len(nodes) + 2):
        if forest_settled({nm: x.tree.state() for nm, x in nodes.items()}, links)[0]:
            break
        n += one_round()
    edges = agreed_edges(nodes)
    rounds = 2
    for comp in tree_components(edges, nodes):
        if len(comp) > 1:
            tree = Tree()
            for a, b in (e for e in edges if e[0] in comp):
                tree.add_edge(a, b)
            rounds = max(rounds, settling_rounds(tree))
    for _ in range(rounds):
        n += one_round()
    return n


def compute_metrics(sc, res: SimulationResult, nodes, c_final, net, n_meas, refused,
                    front_ends: dict[str, Any] | None = None, present: set[str] | None = None) -> dict[str, Any]:
    """The figures of a run (the JSON keys of docs/scenarios.md).

    ``nodes`` maps names to objects with ``estimate()`` and ``stats`` (and, for the
    diagnostics, ``guard`` and ``health()``); ``c_final`` is the fair centralized mean at the
    end; ``net`` has ``stats.total`` (delivered, dropped); ``front_ends`` (optional) gives the
    camera counters. Shared by ``dfusion simulate`` and ``dfusion run``. With links that
    change a node's figures are over the steps it was present (its rows are NaN otherwise),
    and a node not ``present`` at the end has no final gap (None).
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
        "anees_interval_independent": list(chi2_interval(motion.dim, len(res.times))),
        "centralized": {
            "rmse": rmse(res.central_mean, res.truth, axes),
            "anees": float(np.mean(nees(res.central_mean, res.central_cov, res.truth, resid))),
        },
        "nodes": {},
    }
    o_final = getattr(res, "oracle_final", None)
    out["centralized_oracle"] = None   # a result without the oracle reference
    if getattr(res, "oracle_mean", None) is not None:
        out["centralized_oracle"] = {
            "rmse": rmse(res.oracle_mean, res.truth, axes),
            "anees": float(np.mean(nees(res.oracle_mean, res.oracle_cov, res.truth, resid))),
        }
    prot = getattr(sc, "protection", None)
    if prot is not None:
        out["protection"] = prot.describe()
    health = getattr(res, "health", None) or {}
    pos, vel = state_parts(motion.dim, axes)
    for nm, node in nodes.items():
        final_mean, _ = node.estimate()
        ok = np.isfinite(res.node_mean[nm]).all(axis=1)
        mean_k, cov_k, truth_k = res.node_mean[nm][ok], res.node_cov[nm][ok], res.truth[ok]
        diff = mean_k - res.central_mean[ok]
        gap = np.abs(diff).max(axis=1)
        fd = np.asarray(final_mean) - np.asarray(c_final)
        here = present is None or nm in present
        out["nodes"][nm] = {
            "rmse": rmse(mean_k, truth_k, axes),
            "anees": float(np.mean(nees(mean_k, cov_k, truth_k, resid))),
            "final_gap": float(np.max(np.abs(final_mean - c_final))) if here else None,
            "final_gap_oracle": (float(np.max(np.abs(final_mean - o_final)))
                                 if o_final is not None and here else None),
            "mean_gap": float(np.mean(gap)),
            "final_gap_position": float(np.linalg.norm(fd[pos])) if here else None,
            "mean_gap_position": float(np.mean(np.linalg.norm(diff[:, pos], axis=1))),
            "messages": node.stats.messages_sent,
            "bytes": node.stats.bytes_sent,
            "rejected": node.stats.messages_rejected,
            "received": int(getattr(node.stats, "messages_received", 0)),
        }
        if not ok.all():
            out["nodes"][nm]["present_steps"] = int(ok.sum())
        if vel:
            out["nodes"][nm]["final_gap_velocity"] = float(np.linalg.norm(fd[vel])) if here else None
            out["nodes"][nm]["mean_gap_velocity"] = float(np.mean(np.linalg.norm(diff[:, vel], axis=1)))
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


def state_parts(dim: int, axes: int) -> tuple[list[int], list[int]]:
    """Indices of the position and velocity components of a state: the first ``axes``
    are positions (m); the next ``axes`` velocities (m/s) when the state is
    ``(position, velocity)`` (``dim == 2 axes``), else none."""
    pos = list(range(min(axes, dim)))
    vel = list(range(axes, 2 * axes)) if dim == 2 * axes else []
    return pos, vel


def series_of(res: SimulationResult) -> dict[str, Any]:
    """The per-step time series of a run, as lists (for JSON):

    ``t`` (s); ``truth``; ``centralized.mean`` and ``centralized.var`` (the diagonal of
    its covariance); for each node ``mean``, ``var``, ``nees`` (``e' P^-1 e``),
    ``gap_position`` (m, distance to the centralized mean) and ``gap_velocity`` (m/s,
    when the state has a velocity). ``state`` names the state components with units.
    """
    sc = res.scenario
    motion = sc.target.motion
    axes = sc.target.axes
    pos, vel = state_parts(motion.dim, axes)
    resid = motion.residual if motion.angle_indices else None
    letters = "xyz"
    names = [f"{letters[i]} [m]" for i in pos] + [f"v{letters[i - axes]} [m/s]" for i in vel]
    names += [f"x{i}" for i in range(len(names), motion.dim)]
    out: dict[str, Any] = {
        "state": names,
        "t": res.times.tolist(),
        "truth": res.truth.tolist(),
        "centralized": {"mean": res.central_mean.tolist(),
                        "var": np.diagonal(res.central_cov, axis1=1, axis2=2).tolist(),
                        "nees": nees(res.central_mean, res.central_cov, res.truth, resid).tolist()},
        "nodes": {},
    }
    for nm in sorted(res.node_mean):
        m, P = res.node_mean[nm], res.node_cov[nm]
        d = m - res.central_mean
        v: dict[str, Any] = {"mean": m.tolist(), "var": np.diagonal(P, axis1=1, axis2=2).tolist(),
                             "nees": nees(m, P, res.truth, resid).tolist(),
                             "gap_position": np.linalg.norm(d[:, pos], axis=1).tolist()}
        if vel:
            v["gap_velocity"] = np.linalg.norm(d[:, vel], axis=1).tolist()
        out["nodes"][nm] = v
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


def write_series_csv(res: SimulationResult, path) -> None:
    """The per-step series (:func:`series_of`) as CSV, one row per step and node (and one
    for the centralized EKF, ``node = "centralized"``): ``t_s``, ``node``, the truth, the
    mean and the covariance diagonal of each state component (units in the column
    names), ``nees``, ``gap_position_m`` and ``gap_velocity_mps`` (empty for the
    centralized rows)."""
    import csv
    from pathlib import Path

    ser = series_of(res)
    names = ser["state"]

    def unit(n: str) -> tuple[str, str, str]:
        base, _, u = n.partition(" [")
        u = u.rstrip("]")
        sq = {"m": "m2", "m/s": "m2ps2"}.get(u, u + "2" if u else "")
        return base, u.replace("/", "p"), sq

    cols = ["t_s", "node"]
    for n in names:
        b, u, sq = unit(n)
        cols += [f"truth_{b}_{u}".rstrip("_"), f"mean_{b}_{u}".rstrip("_"), f"var_{b}_{sq}".rstrip("_")]
    cols += ["nees", "gap_position_m", "gap_velocity_mps"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        rows = [("centralized", ser["centralized"])] + list(ser["nodes"].items())
        for k, t in enumerate(ser["t"]):
            for name, v in rows:
                row: list[Any] = [f"{t:.9g}", name]
                for i in range(len(names)):
                    row += [repr(ser["truth"][k][i]), repr(v["mean"][k][i]), repr(v["var"][k][i])]
                row.append(repr(v["nees"][k]))
                row.append(repr(v["gap_position"][k]) if "gap_position" in v else "")
                row.append(repr(v["gap_velocity"][k]) if "gap_velocity" in v else "")
                w.writerow(row)
