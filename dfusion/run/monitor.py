"""The monitor: records what every node publishes and builds the ``simulate`` result from it.

A :class:`Monitor` opens its own Zenoh session (connected to every node's
endpoint), subscribes to ``dfusion/NET/monitor/*`` (estimates, ready, final)
and to the nodes' liveliness tokens. At the end, :func:`build_result` turns
the recorded estimates into a :class:`~dfusion.sim.runner.SimulationResult`:

* each node's estimate at grid step ``k`` is the one it published at step
  ``k``; a step it did not publish (it was down, or a publication was lost) holds
  the previous one (the prior before the first);
* the two centralized references (fair: the same detections through the same gate
  and clutter model as the nodes; oracle: false detections skipped) run here on the
  same world (the scenario's seed), exactly as ``dfusion.sim.runner.run_scenario``
  runs them (its ``References``), on every measurement except those a node reported
  lost (made while no incarnation of it was running: nobody could fuse them);
* the metrics are computed by the runner's own code, so the table, the JSON
  keys and the plot are those of ``dfusion simulate``; the JSON has one extra
  key, ``run``, with what only a multi-process run has (incarnations,
  rejected messages, lost measurements, wall-clock figures).

Links that change at run time (``Scenario.dynamic``): every step publication also carries
the node's view of the tree rule (:class:`~dfusion.run.common.TreeStatus`), and
:func:`tree_metrics` rebuilds from them what ``simulate`` reports under ``metrics["links"]``:
every change of the links (a link exists when both ends report it), whether it changed the
agreed fusion tree, and how many send periods the rule took to settle after it
(:func:`dfusion.fusion.tree.forest_settled` over the nodes' published states).
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np

from dfusion.errors import MessageError
from dfusion.fusion.channel import time_key
from dfusion.fusion.stats import RejectionLog
from dfusion.fusion.tree import NodeTreeState, TreeEpoch, forest_settled
from dfusion.run.common import (MAX_STATUS_BATCH, Status, TreeStatus, add_tls_arguments, load_network_key,
                                security_from_args, split_status_batch, status_limit)
from dfusion.scenario.loader import load_scenario
from dfusion.scenario.spec import Scenario
from dfusion.sim.links import LinkChange
from dfusion.scenario.build import build_front_ends
from dfusion.sim.runner import NodeOutput, References, SimulationResult, compute_metrics, frames
from dfusion.sim.world import simulate_world
from dfusion.transport.base import LineBudget, TransportStats
from dfusion.wire import FrameKey
from dfusion.transport.zenoh import (
    ZenohConfig,
    alive_key,
    close_session,
    monitor_batch_key,
    monitor_key,
    open_session,
)

log = logging.getLogger(__name__)

#: Publications waiting for :meth:`Monitor.poll` before the oldest are dropped (counted).
MAX_PENDING = 10_000
#: Bytes of publications waiting for :meth:`Monitor.poll` before the oldest are dropped (counted):
#: a hundred polls' worth of a 128-node run's publications (a few hundred bytes each, 10 per
#: second per node), so a flood costs the launcher at most this much memory.
MAX_PENDING_BYTES = 16 * 1024 * 1024


@dataclass
class NodeRecord:
    """Everything the monitor heard from one node."""

    name: str
    mean: np.ndarray
    cov: np.ndarray
    have: np.ndarray
    last_k: int = -1
    phase: str = "unknown"
    ready: bool = False
    final: Status | None = None
    epochs: list[int] = field(default_factory=list)
    stats: dict[int, dict[str, int]] = field(default_factory=dict)   # last counters per epoch
    alive: bool = False
    losses: int = 0
    #: Policy output per step (only for nodes whose policy is not plain fusion), and its source.
    out_mean: np.ndarray | None = None
    out_cov: np.ndarray | None = None
    out_source: list[str] | None = None
    #: Links that change: the node's view of the tree at each step it published (None: none).
    tree: list[TreeStatus | None] = field(default_factory=list)


class Monitor:
    """Subscriber to every node's estimates (see the module docstring).

    Parameters
    ----------
    sc : Scenario
    network : str
    config : ZenohConfig
        Usually ``ZenohConfig(connect=<every node's endpoint>)``.
    network_key : bytes, optional
        Monitor messages must carry its HMAC, keyed for ``network`` and ``run``
        (:class:`dfusion.wire.FrameKey`); the others are rejected and counted.
    run : str
        The run identifier the nodes were given (``--run-id``; ``dfusion run`` makes one).

    Every publication is validated (:meth:`Status.decode`: MAC, types, ranges, the state
    dimension) and must come from the node it names (its key expression
    ``dfusion/NET/monitor/NAME``; a host process's batch of its nodes' step publications,
    :func:`~dfusion.run.common.encode_status_batch`, goes on the key of its first one, each
    publication in it checked alone); a bad one is counted by reason in :attr:`rejections`
    (total :attr:`rejected`) and logged at most once per :data:`dfusion.fusion.stats.LOG_INTERVAL`
    seconds, never fatal. At most :data:`MAX_PENDING` publications and :data:`MAX_PENDING_BYTES`
    bytes wait between two polls (the oldest are dropped, counted in ``rejections["queue-full"]``
    and :attr:`queue`), and a publication longer than any node of the scenario can make
    (:func:`~dfusion.run.common.status_limit`; a batch: that times
    :data:`~dfusion.run.common.MAX_STATUS_BATCH`) is dropped as it arrives, before its payload is
    copied (``rejections["oversized"]``): a flood of large publications costs a length check each;
    the envelope and MAC are checked as a publication arrives too (:meth:`Status.authenticate`, the
    only HMAC computed per publication; :meth:`poll` reads the authenticated body with
    :meth:`Status.from_body`), so forged publications never take queue space nor push genuine ones out.
    The subscriber is a callback that only counts and appends (Zenoh's FIFO channel would block
    Zenoh's receiving thread when full, stalling the session; its ring channel bounds the count,
    not the bytes).
    """

    def __init__(self, sc: Scenario, network: str, config: ZenohConfig | None = None, *,
                 network_key: bytes | None = None, run: str = "") -> None:
        self.sc, self.network, self.run = sc, network, run
        self.key = None if network_key is None else FrameKey(bytes(network_key), network, run)
        K, n = sc.steps + 1, sc.target.motion.dim
        self.records = {
            name: NodeRecord(name, np.full((K, n), np.nan), np.full((K, n, n), np.nan), np.zeros(K, bool),
                             tree=[None] * K)
            for name in sorted(sc.nodes)
        }
        self.rejected = 0
        #: rejected publications by reason
        self.rejections: dict[str, int] = {}
        self._rejection_log = RejectionLog("monitor", logger=log)
        #: Called as ``f(node, t, mean, cov)`` for every estimate a node publishes (a live
        #: view: :meth:`dfusion.viz.foxglove.LiveView.node_estimate`).
        self.listeners: list = []
        #: The longest publication accepted (bytes).
        self.max_status_bytes = status_limit(sc)
        self._queue: deque = deque()
        self._queue_lock = threading.Lock()
        self._queued_bytes = 0
        self._dropped = 0
        self._oversized = 0
        self._oversized_detail = ""
        self._arrival_rejects: dict[str, int] = {}   # by reason, since the last poll
        self._arrival_detail = ""
        #: The pending queue's bounds and what it shed (``run.monitor_queue`` in the run's JSON).
        self.queue = {"max_count": MAX_PENDING, "max_bytes": MAX_PENDING_BYTES, "max_publication_bytes":
                      self.max_status_bytes, "peak_bytes": 0, "shed": 0, "shed_bytes": 0,
                      "oversized": 0, "oversized_bytes": 0}
        self._alive_events: deque = deque()
        #: at most one line per node's loss, and one per return, a second (``log_budget.held_back``: the rest)
        self.log_budget = LineBudget()
        self._session = open_session(config or ZenohConfig())
        try:
            self._session.declare_subscriber(monitor_key(network), self._on_sample)
            self._session.declare_subscriber(monitor_batch_key(network), lambda s: self._on_sample(s, batch=True))
            self._session.liveliness().declare_subscriber(alive_key(network), self._on_alive, history=True)
        except BaseException:
            self.close()
            raise

    def _on_sample(self, sample, batch: bool = False) -> None:
        """Zenoh's callback (its thread): queue the publication, bounded in count and bytes, never blocking.

        ``batch``: a host's batch of publications (:func:`~dfusion.run.common.encode_status_batch`, at
        most :data:`~dfusion.run.common.MAX_STATUS_BATCH`, on ``monitor/FIRST/batch``): each is checked
        alone, as a single one."""
        size = len(sample.payload)
        q = self.queue
        if size > self.max_status_bytes * (MAX_STATUS_BATCH + 1 if batch else 1):   # before copying the payload
            self._oversized_one(size)
            return
        chunk = str(sample.key_expr).split("/")[3]   # dfusion/NET/monitor/NAME[/batch]
        if batch:
            try:
                parts = split_status_batch(sample.payload.to_bytes(), self.max_status_bytes)
            except MessageError as exc:
                self._arrival_reject(exc)
                return
        else:
            parts = [sample.payload.to_bytes()]
        items = []
        for i, part in enumerate(parts):
            if len(part) > self.max_status_bytes:
                self._oversized_one(len(part))
                continue
            try:   # forged (or garbled) publications never take queue space; the HMAC is computed here only
                body = Status.authenticate(part, self.key)
            except MessageError as exc:
                self._arrival_reject(exc)
                continue
            # the key names the (first) node of the payload: the others of a batch are its host's
            items.append((chunk if i == 0 else None, body, len(part)))
        with self._queue_lock:
            for item in items:
                size = item[2]
                while self._queue and (len(self._queue) >= MAX_PENDING
                                       or self._queued_bytes + size > MAX_PENDING_BYTES):
                    _, _, old = self._queue.popleft()
                    self._queued_bytes -= old
                    self._dropped += 1
                    q["shed"] += 1
                    q["shed_bytes"] += old
                self._queue.append(item)
                self._queued_bytes += size
                q["peak_bytes"] = max(q["peak_bytes"], self._queued_bytes)

    def _oversized_one(self, size: int) -> None:
        with self._queue_lock:
            self._oversized += 1
            self.queue["oversized"] += 1
            self.queue["oversized_bytes"] += size
            self._oversized_detail = f"{size} bytes, more than any node's {self.max_status_bytes}"

    def _arrival_reject(self, exc: MessageError) -> None:
        with self._queue_lock:
            reason = getattr(exc, "reason", "malformed")
            self._arrival_rejects[reason] = self._arrival_rejects.get(reason, 0) + 1
            self._arrival_detail = str(exc)

    def _on_alive(self, sample) -> None:
        """Zenoh's liveliness callback: only the scenario's nodes are followed (a flood of tokens of
        other names takes no memory)."""
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name in self.records:
            self._alive_events.append((name, sample.kind))

    @property
    def session(self):
        """The monitor's Zenoh session (e.g. to read the endpoint it listens on)."""
        return self._session

    def _reject(self, reason: str, detail: str, count: int = 1) -> None:
        self.rejected += count
        self.rejections[reason] = self.rejections.get(reason, 0) + count
        self._rejection_log.add(reason, detail, count)

    def poll(self) -> int:
        """Apply everything received so far; returns the number of publications applied."""
        import zenoh

        while self._alive_events:
            name, kind = self._alive_events.popleft()
            rec = self.records.get(name)
            if rec is None:
                continue
            up = kind == zenoh.SampleKind.PUT
            if rec.alive and not up and rec.final is None:
                rec.losses += 1
                write, held = self.log_budget.allow(f"{name}:lost")
                if write:
                    log.warning("monitor: node %s lost%s", name, LineBudget.suffix(held))
            elif up and not rec.alive and rec.losses:
                write, held = self.log_budget.allow(f"{name}:back")
                if write:
                    log.info("monitor: node %s is back%s", name, LineBudget.suffix(held))
            rec.alive = up
        count = 0
        self._rejection_log.tick()
        with self._queue_lock:
            dropped, self._dropped = self._dropped, 0
            oversized, self._oversized = self._oversized, 0
            batch, self._queue, self._queued_bytes = self._queue, deque(), 0
            arrivals, self._arrival_rejects = self._arrival_rejects, {}
        for reason, n in arrivals.items():
            self._reject(reason, self._arrival_detail, n)
        if dropped:
            self._reject("queue-full", f"{dropped} publications dropped: more than {MAX_PENDING} or "
                                       f"{MAX_PENDING_BYTES} bytes waiting", dropped)
        if oversized:
            self._reject("oversized", self._oversized_detail, oversized)
        dim = self.sc.target.motion.dim
        while batch:
            chunk, body, _ = batch.popleft()
            try:   # authenticated on arrival (_on_sample): the fields are read and checked here
                st = Status.from_body(body, dim)
            except MessageError as exc:
                self._reject(getattr(exc, "reason", "malformed"), str(exc))
                continue
            rec = self.records.get(st.node)
            if rec is None:
                self._reject("not-a-node", f"publication of {st.node!r}, not a node of the scenario")
                continue
            if chunk is not None and st.node != chunk:
                self._reject("forged-sender", f"publication of {st.node!r} on the key of {chunk!r}")
                continue
            if 0 <= st.k and st.k >= len(rec.have) or (st.phase in ("run", "final") and st.k < 0):
                self._reject("malformed", f"step {st.k} of {st.node!r} outside the scenario (0..{len(rec.have) - 1})")
                continue
            self.apply(rec, st)
            count += 1
        return count

    def apply(self, rec: NodeRecord, st: Status) -> None:
        """Record one publication of ``rec``'s node."""
        if st.epoch not in rec.epochs:
            rec.epochs.append(st.epoch)
        if st.stats or st.epoch not in rec.stats:   # a step publication carries the counters once a second
            rec.stats[st.epoch] = st.stats
        if st.phase == "ready":
            rec.ready = True
        elif st.phase in ("run", "final") and st.mean is not None and 0 <= st.k < len(rec.have):
            rec.mean[st.k], rec.cov[st.k], rec.have[st.k] = st.mean, st.cov, True
            if st.tree is not None and rec.tree:
                rec.tree[st.k] = st.tree
            for f in self.listeners:
                f(rec.name, round(st.k * self.sc.dt, 9), st.mean, st.cov)
            if st.output is not None:
                if rec.out_mean is None:
                    rec.out_mean, rec.out_cov = np.full_like(rec.mean, np.nan), np.full_like(rec.cov, np.nan)
                    rec.out_source = [""] * len(rec.have)
                rec.out_source[st.k], rec.out_mean[st.k], rec.out_cov[st.k] = st.output
            rec.last_k = max(rec.last_k, st.k) if st.phase == "run" else st.k
            if st.phase == "final":
                rec.final = st
        rec.phase = st.phase

    def ready(self) -> set[str]:
        self.poll()
        return {n for n, r in self.records.items() if r.ready}

    def progress(self) -> int:
        """The smallest step every node has published (``-1`` before any)."""
        return min(r.last_k for r in self.records.values())

    def alive(self) -> set[str]:
        return {n for n, r in self.records.items() if r.alive}

    def close(self) -> None:
        self._rejection_log.flush()
        close_session(self._session)

    def __enter__(self) -> Monitor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_final(self, names, timeout: float) -> bool:
        """Wait until every node in ``names`` published its final estimate."""
        deadline = time.monotonic() + timeout
        while True:
            self.poll()
            if all(self.records[n].final is not None for n in names):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)


def centralized_references(sc: Scenario, world, exclude: set[tuple[str, int]] = frozenset()):
    """The two centralized references as ``run_scenario`` runs them (its
    :class:`~dfusion.sim.runner.References` on the world's frames in time order): the *fair* one
    (every detection of a frame through the front end's gate and clutter model) and the
    *oracle* (false detections skipped). Returns ``(fair mean (K,n), fair cov (K,n,n), fair
    final mean, oracle mean, oracle cov, oracle final mean)``.

    ``exclude`` holds ``(node, time_key)`` of measurements nobody received.
    """
    refs = References(sc, build_front_ends(sc))
    K, n = sc.steps + 1, sc.target.motion.dim
    times = np.round(sc.dt * np.arange(K), 9)
    by_time = frames([m for m in world.measurements if (m.node, time_key(m.t)) not in exclude])
    c_mean, c_cov = np.empty((K, n)), np.empty((K, n, n))
    o_mean, o_cov = np.empty((K, n)), np.empty((K, n, n))
    (c_mean[0], c_cov[0]), (o_mean[0], o_cov[0]) = refs.estimate(times[0])
    ic = 0
    for k in range(1, K):
        t = float(times[k])
        while ic < len(by_time) and by_time[ic][0].t <= t + 1e-9:
            refs.add(by_time[ic], seq=ic)
            ic += 1
        (c_mean[k], c_cov[k]), (o_mean[k], o_cov[k]) = refs.estimate(times[k])
    for frame in by_time[ic:]:
        refs.add(frame, seq=ic)
        ic += 1
    (c_final, _), (o_final, _) = refs.estimate(float(times[-1]))
    return c_mean, c_cov, c_final, o_mean, o_cov, o_final


def centralized_reference(sc: Scenario, world, exclude: set[tuple[str, int]] = frozenset()):
    """The fair centralized reference of :func:`centralized_references`: ``(mean (K,n), cov (K,n,n), final mean)``."""
    return centralized_references(sc, world, exclude)[:3]


def _filled(rec: NodeRecord, sc: Scenario) -> tuple[np.ndarray, np.ndarray, int]:
    """The record on the whole grid, holding the last published estimate; and the number of gaps."""
    mean, cov = rec.mean.copy(), rec.cov.copy()
    have = rec.have
    if not have[0]:
        mean[0], cov[0] = sc.target.initial_mean, sc.target.initial_cov
    for k in range(1, len(have)):
        if not have[k]:
            mean[k], cov[k] = mean[k - 1], cov[k - 1]
    return mean, cov, int(np.count_nonzero(~have[1:]))


def _filled_output(rec: NodeRecord, sc: Scenario, mean: np.ndarray, cov: np.ndarray):
    """The policy output on the whole grid (``None`` if the node published none): steps
    without a publication hold the previous output; before the first, the node's estimate."""
    if rec.out_mean is None:
        return None
    spec_policy = sc.nodes[rec.name].policy
    out = NodeOutput(getattr(spec_policy, "name", "policy"), rec.out_mean.copy(), rec.out_cov.copy(),
                     list(rec.out_source))
    for k in range(len(out.source)):
        if not out.source[k]:
            if k == 0:   # later gaps find step k - 1 already filled
                out.mean[k], out.cov[k], out.source[k] = mean[k], cov[k], "fused"
            else:
                out.mean[k], out.cov[k], out.source[k] = out.mean[k - 1], out.cov[k - 1], out.source[k - 1]
    return out


def measurement_events(world, times: np.ndarray, lost: set[tuple[str, int]]) -> list[dict[str, Any]]:
    """What a multi-process run can say of each measurement, in the form of
    :attr:`SimulationResult.events` (for the recording's ``/detections``): the step at which it
    reached its node (the first step at or after its arrival) and ``"delivered"`` to the
    node's process, or ``"lost"`` while the node was down. The node processes gate and fuse
    their measurements themselves and report counters, not a verdict per measurement.
    Measurements arriving after the last step are left out."""
    events: list[dict[str, Any]] = []
    last = float(times[-1]) if len(times) else -math.inf
    for m in world.measurements:
        if m.arrival > last + 1e-9:
            continue
        k = int(np.searchsorted(times, m.arrival - 1e-9))
        outcome = ["lost"] if (m.node, time_key(m.t)) in lost else ["delivered"]
        events.append({"t": float(times[k]), "node": m.node, "t_meas": m.t, "z": m.z, "outcome": outcome})
    return events


def build_result(
    sc: Scenario,
    records: dict[str, NodeRecord],
    finals: dict[str, Status],
    *,
    world=None,
    extra: dict[str, Any] | None = None,
):
    """The :class:`SimulationResult` of a multi-process run (see the module docstring).

    ``finals`` holds each node's final status (from its result file or the
    monitor); a node without one is judged on its last published estimate.
    """
    world = world if world is not None else simulate_world(sc)
    lost = {(name, time_key(t)) for name, st in finals.items() for t in st.lost}
    c_mean, c_cov, c_final, o_mean, o_cov, o_final = centralized_references(sc, world, lost)
    K = sc.steps + 1
    times = np.round(sc.dt * np.arange(K), 9)
    truth = np.array([world.truth(t) for t in times])
    node_mean, node_cov, views, run_nodes, outputs = {}, {}, {}, {}, {}
    delivered = sent = refused = 0
    tsum = {"published": 0, "dropped_emulated": 0, "messages_received": 0, "messages_rejected": 0,
            "rejected_on_arrival": 0}
    for name in sorted(records):
        rec = records[name]
        node_mean[name], node_cov[name], gaps = _filled(rec, sc)
        out = _filled_output(rec, sc, node_mean[name], node_cov[name])
        if out is not None:
            outputs[name] = out
        fin = finals.get(name)
        final_mean = fin.mean if fin is not None and fin.mean is not None else node_mean[name][-1]
        per_epoch = list(rec.stats.values())
        if fin is not None:
            rec.stats[fin.epoch] = fin.stats
            per_epoch = list(rec.stats.values())
        total = {key: sum(s.get(key, 0) for s in per_epoch) for key in set().union(*per_epoch)} if per_epoch else {}
        stats = SimpleNamespace(messages_sent=total.get("messages_sent", 0), bytes_sent=total.get("bytes_sent", 0),
                                messages_rejected=total.get("messages_rejected", 0))
        views[name] = SimpleNamespace(estimate=lambda m=final_mean: (m, None), stats=stats)
        delivered += total.get("delivered", 0)
        sent += total.get("messages_sent", 0)
        refused += total.get("measurements_refused", 0)
        for key in tsum:
            tsum[key] += total.get(key, 0)
        run_nodes[name] = {
            "incarnations": max(1, len(rec.epochs)),
            "finished": fin is not None,
            "steps_missing": gaps,
            "messages_received": total.get("messages_received", 0),
            "messages_rejected": total.get("messages_rejected", 0),
            "blocks_outside_window": total.get("blocks_outside_window", 0),
            # of those, dropped by the cheap checks as they arrived (never queued, never delivered)
            "rejected_on_arrival": total.get("rejected_on_arrival", 0),
            "rejections": {key[len("rejected_"):]: v for key, v in sorted(total.items())
                           if key.startswith("rejected_") and key != "rejected_on_arrival" and v},
            "duplicates": total.get("duplicates", 0),
            "sends_skipped_not_alive": total.get("skipped_not_alive", 0),
            "dropped_emulated": total.get("dropped_emulated", 0),
            "measurements_fused": total.get("measurements_fused", 0),
            "measurements_replayed": total.get("measurements_replayed", 0),
            "measurements_lost": len(fin.lost) if fin is not None else 0,
            "liveliness_losses": rec.losses,
            "max_lag_wall_s": max((s.get("max_lag_ms", 0) for s in per_epoch), default=0) / 1000,
            # the lag of the last step the node reported (its final incarnation's): behind the clock at the end
            "lag_at_end_wall_s": (fin.stats if fin is not None else per_epoch[-1] if per_epoch else {}).get(
                "lag_ms", 0) / 1000,
            "cpu_s": total.get("cpu_ms", 0) / 1000,
            # the consistency test of the neighbours' information (docs/clutter.md), summed over incarnations
            "guard_tests": total.get("guard_tests", 0),
            "guard_failures": total.get("guard_failures", 0),
            "quarantines": total.get("quarantines", 0),
            "host_cpu_s": total.get("host_cpu_ms", 0) / 1000,
            # the receive queue (bounded in copies and bytes, dfusion.transport.zenoh): shed summed over
            # incarnations, the largest peak of any
            "receive_queue_shed": total.get("receive_queue_shed", 0),
            "receive_queue_shed_bytes": total.get("receive_queue_shed_bytes", 0),
            "receive_queue_peak_bytes": max((s.get("receive_queue_peak_bytes", 0) for s in per_epoch), default=0),
            # liveliness log lines held back (at most one per neighbour's loss, one per return, a second)
            "log_lines_held_back": total.get("log_lines_held_back", 0),
            # log lines dropped past the process's byte cap (dfusion.run.common.MAX_LOG_BYTES), and blocks
            # ahead of the held-information bound (max_held / max_ahead): not stored, sent again
            "log_lines_dropped": total.get("log_lines_dropped", 0),
            "blocks_too_far_ahead": total.get("blocks_too_far_ahead", 0),
            # one-sided link lapses injected by a chaos driver (--chaos-dir; dfusion.run.chaos)
            **({"chaos_lapses": total["chaos_lapses"]} if "chaos_lapses" in total else {}),
        }
    result = SimulationResult(sc, world, times, truth, c_mean, c_cov, node_mean, node_cov, outputs=outputs,
                              events=measurement_events(world, times, lost),
                              oracle_mean=o_mean, oracle_cov=o_cov, oracle_final=o_final)
    net = SimpleNamespace(stats=SimpleNamespace(total=TransportStats(delivered=delivered,
                                                                       dropped=max(0, sent - delivered))))
    result.metrics = compute_metrics(sc, result, views, c_final, net, len(world.measurements), refused)
    links = tree_metrics(sc, records)
    if links is not None:
        links["epochs_started"] = int(sum(
            sum(s.get("epochs_started", 0) for s in records[n].stats.values()) for n in records))
        result.metrics["links"] = links
    # how the nodes sent; the nodes do not count bytes per link (per node: metrics["nodes"])
    result.metrics["sends"] = {"mode": sc.sends, "min_interval": sc.min_send_interval, "event_messages": None,
                               "links": {}, "bytes_per_link_per_s": None, "messages_per_link_per_s": None}
    # the counts of traffic_lines: built = published + dropped by link emulation; published =
    # delivered + not received (lost by the transport, or the receiver was down); delivered =
    # fused + rejected + ignored (copies a node already had: naive fusion's old sequence numbers).
    # Copies rejected on arrival (garbage, forged or foreign traffic dropped by the cheap checks in
    # the transport's callback) were never delivered: they are counted apart, not as delivered.
    pub, emu = tsum["published"], tsum["dropped_emulated"]
    on_arrival = tsum["rejected_on_arrival"]
    rejected = tsum["messages_rejected"] - on_arrival
    ignored = max(0, delivered - tsum["messages_received"] - rejected)
    result.metrics["traffic"] = {
        "network": {"sent": pub + emu, "duplicated": 0, "delivered": delivered,
                    "dropped": emu + max(0, pub - delivered), "in_flight": 0},
        "fused": delivered - rejected - ignored, "rejected": rejected,
        "ignored": ignored, "final_rounds": 0, "final_rounds_over_network": True,
        "rejected_on_arrival": on_arrival,
    }
    speed = (extra or {}).get("speed", 1.0)
    wall = sc.duration / speed   # wall seconds of the run proper (start to the scenario's end)
    result.metrics["run"] = {
        "nodes": run_nodes,
        "measurements_lost": len(lost),
        # CPU per node per wall second: every host process's CPU (all its threads) from the start to its
        # end, shared among its nodes; and the nodes' own work in their loops
        "cpu_ms_per_node_per_s": 1000 * sum(v["host_cpu_s"] for v in run_nodes.values()) / len(run_nodes) / wall,
        "node_cpu_ms_per_node_per_s": 1000 * sum(v["cpu_s"] for v in run_nodes.values()) / len(run_nodes) / wall,
        **(extra or {}),
    }
    return result


def _pair(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a < b else (b, a)


def tree_metrics(sc: Scenario, records: dict[str, NodeRecord]) -> dict[str, Any] | None:
    """Links that change: the changes of the links and the tree of a run, from the nodes' published
    tree states (``metrics["links"]`` as ``simulate`` has it; None on a fixed tree).

    At each grid step the nodes that published a tree state there are the network; a link
    exists when both ends list it (each end keeps a link while the scenario allows it and it
    sees the other's liveliness token); a node that published nothing at a step (down, or not
    yet started) has no links then. A step whose links differ from the previous step's is a
    change (``what``: links up and down, nodes gone and back); the tree has settled when
    :func:`~dfusion.fusion.tree.forest_settled` holds for the published states on those links.
    Information settling is not inspected here (``info_settled`` stays None: the nodes do
    not publish their information blocks).
    """
    if not sc.dynamic:
        return None
    period = max(s.send_period for s in sc.nodes.values())
    K = sc.steps + 1
    changes: list[LinkChange] = []
    prev_links: set[tuple[str, str]] | None = None
    prev_nodes: set[str] = set()
    settled_tree: set[tuple[str, str]] = set()
    for k in range(K):
        states = {n: r.tree[k] for n, r in records.items() if r.tree and r.tree[k] is not None}
        if not states:
            continue
        t = round(k * sc.dt, 9)
        links = {_pair(a, b) for a, s in states.items() for b in s.links if b in states and a in states[b].links}
        edges = {_pair(a, b) for a, s in states.items() for b in s.tree_links
                 if b in states and a in states[b].tree_links}
        view = {n: NodeTreeState(n, TreeEpoch(s.term, s.root), s.parent, frozenset(s.tree_links))
                for n, s in states.items()}
        settled, _ = forest_settled(view, links)
        if prev_links is not None and (links != prev_links or set(states) != prev_nodes):
            what = [f"{n} gone" for n in sorted(prev_nodes - set(states))] + \
                   [f"{n} back" for n in sorted(set(states) - prev_nodes)] + \
                   [f"{a} - {b} down" for a, b in sorted(prev_links - links)] + \
                   [f"{a} - {b} up" for a, b in sorted(links - prev_links)]
            if what:
                for c in changes:
                    if c.tree_settled is None:
                        c.overlapped = True
                changes.append(LinkChange(t, what, set(settled_tree)))
        if settled:
            settled_tree = edges
            for c in changes:
                if c.tree_settled is None:
                    c.tree_settled, c.tree_after = t, set(edges)
        prev_links, prev_nodes = links, set(states)
    rows = [c.as_dict(period) for c in changes]
    done = [r for r in rows if r["tree_settled_send_periods"] is not None and not r["overlapped"]]
    trees = [r for r in done if r["tree_changed"]]
    v = [r["tree_settled_send_periods"] for r in trees]
    none = {"median": None, "max": None}
    return {
        "send_period": period,
        "link_changes": len(rows),
        "tree_changes": sum(r["tree_changed"] for r in rows),
        "changes": rows,
        "settling_tree_changes": {"tree": {"median": float(np.median(v)) if v else None,
                                           "max": float(np.max(v)) if v else None},
                                  "information": none, "count": len(trees)},
        "settling_other_changes": {"information": none},
        "information_inspected": False,
    }


def run_table(result) -> str:
    """The lines ``dfusion run`` prints after the ``simulate`` table."""
    run = result.metrics.get("run", {})
    lines = []
    for name, v in run.get("nodes", {}).items():
        bits = []
        if v["incarnations"] > 1:
            bits.append(f"{v['incarnations']} incarnations, {v['measurements_replayed']} measurements replayed")
        if v["measurements_lost"]:
            bits.append(f"{v['measurements_lost']} measurements lost while down")
        if v["messages_rejected"]:
            why = ", ".join(f"{r} {c}" for r, c in sorted(v.get("rejections", {}).items(), key=lambda x: -x[1]))
            bits.append(f"{v['messages_rejected']} messages rejected" + (f" ({why})" if why else ""))
        if v["liveliness_losses"]:
            bits.append(f"lost {v['liveliness_losses']}x")
        if v.get("quarantines"):
            bits.append(f"{v['quarantines']} quarantines of a neighbour by the consistency test "
                        f"({v['guard_failures']} of {v['guard_tests']} tests failed)")
        if not v["finished"]:
            bits.append("did not finish")
        if bits:
            lines.append(f"  {name}: " + "; ".join(bits))
    lag = max((v.get("max_lag_wall_s", 0.0) for v in run.get("nodes", {}).values()), default=0.0)
    cpu_lines = []
    if run.get("cpu_ms_per_node_per_s"):
        cpu = (f"CPU per node per wall second: {run['cpu_ms_per_node_per_s']:.1f} ms (its process's share, every "
               f"thread), {run.get('node_cpu_ms_per_node_per_s', 0.0):.1f} ms in the node's own loop")
        if run.get("launcher_cpu_s") is not None:
            cpu += f"; launcher and monitor {run['launcher_cpu_s']:.1f} s"
        cpu_lines.append("  " + cpu)
    bits = []
    if "hosts" in run:
        n = len(run.get("nodes", {}))
        per = run.get("nodes_per_process", 1)
        bits.append(f"{run['hosts']} host process{'es' if run['hosts'] != 1 else ''} for {n} nodes"
                    + (f" (up to {per} per process)" if per > 1 else " (one per node)"))
    if "speed" in run:
        bits.append(f"speed x{run['speed']:g}, wall {run.get('wall_seconds', math.nan):.1f} s")
    end = max((v.get("lag_at_end_wall_s", 0.0) for v in run.get("nodes", {}).values()), default=0.0)
    bits.append(f"largest lag behind the clock {lag:.2f} s wall ({end:.2f} s at the end)")
    bits.append(f"network {run.get('network', '?')}")
    if run.get("monitor_rejected"):
        why = ", ".join(f"{r} {c}" for r, c in sorted(run.get("monitor_rejections", {}).items(), key=lambda x: -x[1]))
        lines.append(f"  monitor: {run['monitor_rejected']} publications rejected" + (f" ({why})" if why else ""))
    head = "processes: " + ", ".join(bits)
    if result.metrics.get("links", {}).get("information_inspected") is False:
        cpu_lines.append("  links that change: a link exists while the scenario allows it and both ends see each "
                         "other's liveliness token; settling measured from the tree states the nodes publish "
                         "(information settling is not inspected in dfusion run: '-')")
    return "\n".join([head] + cpu_lines + lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m dfusion.run.monitor``: watch nodes started by hand (e.g. on several hosts).

    Connects to the given node endpoints, waits until every node of the
    scenario has published its final estimate (or ``--timeout``), then prints
    the ``simulate`` table and writes ``--json`` / ``--plot``.
    """
    import argparse
    import json as _json
    import signal
    import sys
    from pathlib import Path

    p = argparse.ArgumentParser(prog="python -m dfusion.run.monitor", description=main.__doc__.split("\n")[0])
    p.add_argument("--scenario", required=True)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--fusion", choices=("channel", "naive"), default=None)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--network", default="dfusion")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="a node's or router's endpoint")
    p.add_argument("--mode", choices=("peer", "client"), default="peer")
    p.add_argument("--network-key-file", default=None)
    p.add_argument("--run-id", default="", help="the run identifier the nodes were given (their --run-id): "
                                                "monitor messages are authenticated for it")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for every final estimate")
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE", help="plug-in module or .py file")
    p.add_argument("--json", default=None)
    p.add_argument("--plot", default=None)
    add_tls_arguments(p)   # --tls-dir: DIR/monitor.pem and .key (else DIR/node.pem)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda s, f: stop.append(s))
    signal.signal(signal.SIGINT, lambda s, f: stop.append(s))
    sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration,
                       plugins=args.plugin)
    cfg = ZenohConfig(mode=args.mode, connect=tuple(args.connect), listen=() if args.mode == "client" else (),
                      tls=security_from_args(args).tls_files("monitor"))
    with Monitor(sc, args.network, cfg, network_key=load_network_key(args.network_key_file), run=args.run_id) as mon:
        deadline = time.monotonic() + args.timeout
        names = sorted(sc.nodes)
        while not stop and time.monotonic() < deadline:
            if mon.wait_final(names, 0.2):
                break
        finals = {n: r.final for n, r in mon.records.items() if r.final is not None}
        if stop or not finals:
            print("monitor: stopped before any final estimate", file=sys.stderr)
            return 1
        result = build_result(sc, mon.records, finals, extra={"network": args.network})
    print(result.table())
    print(run_table(result))
    if args.json:
        Path(args.json).write_text(_json.dumps(result.metrics, indent=2, sort_keys=True))
    if args.plot:
        from dfusion.viz import plot_result

        plot_result(result, args.plot)
    return 0 if len(finals) == len(sc.nodes) else 1


if __name__ == "__main__":
    raise SystemExit(main())
