"""One fusion node as an OS process, talking to its neighbours over Zenoh.

``python -m dfusion.run.node_process --scenario F --node NAME [options]`` (what
``dfusion run`` starts for every node). The node

1. loads the scenario and takes its own measurements from the simulated world
   of the scenario's seed (the same world ``dfusion simulate`` uses), or from a
   recording (``--measurements``);
2. opens a :class:`~dfusion.transport.zenoh.ZenohTransport`, declares its
   liveliness token and waits for the common start time (``--start-time`` or
   ``--start-file``), publishing ``ready`` to the monitor once its neighbours
   are up;
3. runs in real time, scenario time ``(wall - start) * speed``; every ``dt``:
   predict, fuse the measurements whose arrival time has come, receive, send to
   each neighbour whose send period has elapsed and whose liveliness token is
   seen, and publish its estimate on ``dfusion/NET/monitor/NAME``; messages are
   also received as soon as they arrive between steps;
4. after the scenario's end, exchanges ``diameter + 2`` more rounds without
   new measurements (synchronized rounds: round ``r`` goes to every neighbour,
   then the node waits for every live neighbour's round ``r``), publishes its
   final estimate (and writes it to ``--result``) and exits 0.

SIGTERM or SIGINT stops it within a fraction of a second (the session is
closed, exit status 0). With ``--state-dir`` every measurement is appended to a
log before it is fused and a restarted node replays it (``docs/processes.md``).

``--run-dir DIR`` joins the run of the ``dfusion run`` launcher working in ``DIR``
(what the launcher gives every node, so that the same command line, run by hand,
restarts a node): the start time, state log, result and network key are taken
from ``DIR``; the node refuses to start when no launcher runs there or when
another incarnation of it runs, and stops when the launcher is gone
(:mod:`dfusion.run.supervision`: the launcher's lock, and the parent-death signal
when the launcher is its parent).

``--emulate-links`` applies the scenario's links (latency, jitter, drops,
duplicates, reordering, outages) at the sender (:mod:`dfusion.run.links`).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import zenoh

from dfusion.errors import DfusionError, MessageError, OutsideWindowError
from dfusion.run.common import (
    MAX_STATUS_BATCH,
    ROUND_TIMEOUT,
    LogByteCap,
    Status,
    TreeStatus,
    add_tls_arguments,
    encode_status_batch,
    final_rounds,
    load_network_key,
    parse_zenoh_options,
    security_from_args,
)
from dfusion.fusion.node import FusionNode
from dfusion.fusion.tree import initial_parents
from dfusion.run.chaos import LapseInbox
from dfusion.run.endpoints import EndpointRegistry, bound_endpoints
from dfusion.run.links import EmulatedLinks, node_links
from dfusion.run.measurements import (
    MeasurementLog,
    claim_epoch,
    OwnMeasurement,
    load_recording,
    nodes_measurements,
    save_recording,
    world_measurements,
)
from dfusion.scenario.build import build_front_end, build_node
from dfusion.scenario.links import LinkSchedule, peers
from dfusion.fusion.sending import SendSchedule
from dfusion.scenario.loader import load_scenario
from dfusion.scenario.spec import Scenario
from dfusion.run.supervision import (
    EXIT_ALREADY_RUNNING,
    EXIT_NO_LAUNCHER,
    FileLock,
    LauncherWatch,
    node_lock_path,
    set_parent_death_signal,
)
from dfusion.policies.base import records_output
from dfusion.transport.zenoh import ZenohConfig, ZenohTransport, check_name, monitor_batch_key, monitor_key

log = logging.getLogger("dfusion.node")

#: Longest time the node blocks without looking at its stop flag (seconds).
POLL = 0.05
#: Longest time a host's loop sleeps without looking at its stop flags (seconds). Its steps,
#: event sends, delayed copies and arrivals wake it anyway; a shorter bound would add wake-ups
#: (each costs the process tens of microseconds of CPU on a VM) between steps of 0.1 s.
LOOP_POLL = 0.25
#: Wall-clock period of the "ready" publication while waiting for the start.
READY_PERIOD = 0.2
#: Wall-clock period of the counters in a node's step publications (the estimate goes every step).
STATS_PERIOD = 1.0
EPS = 1e-9
#: Environment variable naming a directory: each node process profiles its loop with cProfile and
#: writes ``DIR/HOST.pstats`` when it ends (a diagnostic; ``docs/processes.md``).
ENV_PROFILE = "DFUSION_PROFILE"


@dataclass(frozen=True)
class Wait:
    """What a node's program (:meth:`NodeProcess.program`) waits for: the wall-clock
    ``deadline``, or ``until()`` becoming true before it (checked whenever messages arrive)."""

    deadline: float
    until: Callable[[], bool] | None = None


class StartFile:
    """The common start time: given, or read from the launcher's start file (at most every :data:`POLL` s)."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self._next = 0.0

    def read(self) -> float | None:
        if self.path is None or time.monotonic() < self._next:
            return None
        self._next = time.monotonic() + POLL
        try:
            return float(self.path.read_text().strip())
        except (OSError, ValueError):   # not written yet, or being written
            return None


class NodeProcess:
    """The real-time loop of one fusion node (see the module docstring).

    :meth:`run` runs it alone in its process; a :class:`Host` runs several in one
    process over one Zenoh session (``--node`` given several times,
    ``dfusion run --nodes-per-process N``). The loop itself is :meth:`program`.

    Parameters
    ----------
    sc : Scenario
    name : str
        This node.
    network : str
        Network name (Zenoh key chunk).
    zconfig : ZenohConfig
        Session settings: this node's listen endpoints, its neighbours' as ``connect``.
    speed : float
        Scenario seconds per wall-clock second.
    start : float or None
        Common start (UNIX time) of scenario time 0; ``None``: read ``start_file``.
    start_file : path, optional
        A file that will hold the start time (written by the launcher).
    measurements : list of OwnMeasurement
        This node's measurements, in fusing order (default: the scenario's world's).
    state_dir : path, optional
        Where the measurement log lives; ``run_id`` identifies the run.
    network_key : bytes, optional
        HMAC key of fusion and monitor messages.
    result : path, optional
        Where to write the final status (JSON).
    emulate_links : bool
        Apply the scenario's links (latency, jitter, drop, duplicate, reorder,
        outages) to outgoing messages (:class:`~dfusion.run.links.EmulatedLinks`).
    round_timeout : float
        Wall-clock seconds to wait for a live neighbour's message of a final-phase round.
    parent_pid : int, optional
        Stop when this process is no longer the parent.
    watch : LauncherWatch, optional
        Stop when the launcher of the run directory is gone.
    chaos_dir : path, optional
        Testing only (``--chaos-dir``, ``benchmarks/chaos.py``): apply the one-sided link lapses
        requested there (:mod:`dfusion.run.chaos`); None (the default): no such requests are read.
    """

    #: Where this node's step publications wait for its host to send them together
    #: (:meth:`Host.flush_monitor`); None: each goes at once.
    monitor_batch: list[tuple[NodeProcess, bytes]] | None = None
    #: The byte cap on this process's log output (:class:`dfusion.run.common.LogByteCap`); the
    #: first node of a process reports its drops (``log_lines_dropped``), so they are counted once.
    log_cap: LogByteCap | None = None

    def __init__(
        self,
        sc: Scenario,
        name: str,
        *,
        network: str = "dfusion",
        zconfig: ZenohConfig | None = None,
        speed: float = 1.0,
        start: float | None = None,
        start_file: str | Path | None = None,
        measurements: list[OwnMeasurement] | None = None,
        state_dir: str | Path | None = None,
        run_id: str | None = None,
        fsync: bool = False,
        network_key: bytes | None = None,
        result: str | Path | None = None,
        emulate_links: bool = False,
        round_timeout: float = ROUND_TIMEOUT,
        parent_pid: int | None = None,
        ready_timeout: float = 5.0,
        watch: LauncherWatch | None = None,
        chaos_dir: str | Path | None = None,
    ) -> None:
        if name not in sc.nodes:
            raise DfusionError(f"{name!r} is not a node of {sc.path} (nodes: {sorted(sc.nodes)})")
        check_name(name)
        if not (speed > 0 and math.isfinite(speed)):
            raise DfusionError(f"speed must be a positive number, got {speed}")
        self._start_now = start is None and start_file is None   # start as soon as the session is open
        self.sc, self.name, self.network = sc, name, network
        #: Links that change at run time (``docs/processes.md``): the scenario's rule of which links
        #: are allowed when (None: a fixed tree).
        self.schedule = LinkSchedule(sc) if sc.dynamic else None
        #: The nodes this one may link to: its tree neighbours, or every possible peer when links change.
        self.neighbors = peers(sc, name)
        self._links_frozen = False
        self.zconfig = zconfig or ZenohConfig()
        self.speed = float(speed)
        self.start = start
        self.start_file = StartFile(start_file)
        self.meas = measurements if measurements is not None else world_measurements(sc, name)
        self.state_dir, self.run_id, self.fsync = state_dir, run_id, fsync
        self.key = network_key
        self.result = Path(result) if result else None
        self.emulate_links = emulate_links
        self.rounds, self.round_timeout = final_rounds(sc), float(round_timeout)
        self._round_seen: dict[str, int] = {}
        self._replay: dict[int, OwnMeasurement] = {}
        self.parent_pid = parent_pid
        self.watch = watch
        self.ready_timeout = ready_timeout
        self.stop_reason: str | None = None
        self.times = np.round(sc.dt * np.arange(sc.steps + 1), 9)
        spec = sc.nodes[name]
        self.sensor = spec.sensor
        # the same front end as in `dfusion simulate` (EIF update, camera gate, WSN particle filter...)
        self.front = build_front_end(sc, name)
        self.send_period = spec.send_period
        # a new epoch per incarnation: the clock, strictly newer than the last one recorded in the state dir;
        # a restart whose start time has passed joins the running network (built once, one epoch claimed)
        self._joins = self._starts_late()
        self.node = self._build_node(joining=self._joins)
        self._records_output = records_output(self.node.policy)
        self.counters = {"skipped_not_alive": 0, "measurements_fused": 0,
                         "measurements_refused": 0, "measurements_replayed": 0,
                         "max_lag_ms": 0, "lag_ms": 0}
        self.lost: list[float] = []
        self.t_started = 0.0
        self.links: EmulatedLinks | None = None
        self.tr: ZenohTransport | None = None
        self._mlog: MeasurementLog | None = None
        self._pub = None
        #: CPU seconds of this node's own work in its process's main thread (its steps and receives),
        #: counted by whoever drives it (:class:`Host`)
        self.cpu = 0.0
        #: this node's share of its process's CPU (every thread, Zenoh's included) since its start
        self.host_share = 1.0
        self._cpu_at_start: float | None = None
        self._stats_due = 0.0
        #: When the node sends (:class:`~dfusion.fusion.sending.SendSchedule`); set when the run starts.
        self.sched = SendSchedule(self.send_period, sc.min_send_interval, sc.sends)
        self._sending = False
        #: Injected one-sided link lapses (``--chaos-dir``, chaos runs only; ``dfusion.run.chaos``).
        self.chaos = LapseInbox(chaos_dir, name) if chaos_dir is not None and self.schedule is not None else None

    def _starts_late(self) -> bool:
        """Whether the common start time is known already and more than half a step past (a
        restart): a node whose links change then joins the running network. The start read from
        the start file is kept (it does not change)."""
        if self.schedule is None:
            return False
        if self.start is None:
            self.start = self.start_file.read()
        return self.start is not None and self.now() > self.sc.dt * 0.5

    def _build_node(self, *, joining: bool, epoch: int | None = None) -> FusionNode:
        """This incarnation's :class:`FusionNode` (its incarnation epoch: ``epoch``, else the clock,
        strictly newer than the last one claimed in the state directory, :func:`claim_epoch`).

        Links that change: a node started on time begins on the tree the tree rule's
        :func:`~dfusion.fusion.tree.initial_parents` picks among the links the scenario allows
        at time 0 (the tree ``simulate`` starts on; the launcher starts the clock once every
        node is up); a node that starts late (a restart) or joins later begins alone in the
        lowest tree epoch and adopts its neighbours' (``docs/dynamic-topology.md``).
        """
        if epoch is None and self.state_dir is not None:
            epoch = claim_epoch(self.state_dir, self.name)
        kw = {"network_key": self.key, "network": self.network, "run": self.run_id or "", "epoch": epoch}
        if self.schedule is None:
            return build_node(self.sc, self.name, **kw)
        present = self.schedule.present(0.0)
        if joining or self.name not in present:
            return build_node(self.sc, self.name, links=(), **kw)
        links0 = self.schedule.links(0.0)
        mine = [b if a == self.name else a for a, b in sorted(links0) if self.name in (a, b)]
        return build_node(self.sc, self.name, links=mine, tree_start=initial_parents(sorted(present), links0), **kw)

    # ------------------------------------------------------------------ clocks and stopping
    def request_stop(self, reason: str) -> None:
        """Ask the loop to stop (safe from a signal handler: only sets a flag)."""
        if self.stop_reason is None:
            self.stop_reason = reason

    def _should_stop(self) -> bool:
        if self.parent_pid is not None and os.getppid() != self.parent_pid:
            self.request_stop(f"parent process {self.parent_pid} is gone")
        if self.watch is not None and not self.watch.alive():
            self.request_stop(f"the launcher is gone ({self.watch.path} is free)")
        return self.stop_reason is not None

    def now(self) -> float:
        """Scenario time (``-inf`` before the start time is known)."""
        if self.start is None:
            return -math.inf
        return (time.time() - self.start) * self.speed

    # ------------------------------------------------------------------ the loop
    def run(self) -> int:
        """Run to the end (or until stopped) alone in this process; returns the exit status (0)."""
        return Host([self], network=self.network, zconfig=self.zconfig, parent_pid=self.parent_pid,
                    watch=self.watch).run()

    def attach(self, tr: ZenohTransport) -> None:
        """Use ``tr`` (opened by the host) for messages, liveliness and monitor publications."""
        self.tr = tr
        if self.emulate_links:   # links that change: every link this node may have ([[links]], else [radio])
            specs = node_links(self.sc.links, self.name) if self.schedule is None else {
                nb: self.sc.link_spec(self.name, nb) for nb in self.neighbors}
            self.links = EmulatedLinks(self.name, specs, self.sc.seed, tr.send, speed=self.speed)
        # garbage and forged copies are dropped in Zenoh's callback, before they take queue space
        tr.set_check(self.name, self.node.check_frame, self.node.max_message_bytes)
        self._monitor_key = monitor_key(self.network, self.name)
        self._pub = tr.session.declare_publisher(self._monitor_key)

    def stopped(self) -> None:
        """The loop was stopped before its end (a signal, the launcher gone): say so to the monitor."""
        log.info("%s: stopping: %s", self.name, self.stop_reason)
        self._count_rejected_on_arrival()
        self.node.flush_log()
        if self.links is not None and self.links.pending():
            log.info("%s: %d delayed messages not sent", self.name, self.links.discard())
        self._publish("stopped", -1)

    def close(self) -> None:
        if self._mlog is not None:
            self._mlog.close()
            self._mlog = None

    def program(self) -> Iterator[Wait]:
        """The node's life as a generator of :class:`Wait`: start, steps, final phase.

        Whoever drives it (:class:`Host`) resumes it once the wait is over and hands the
        node its messages meanwhile (:meth:`receive`).
        """
        yield from self._wait_for_start()
        if self.schedule is not None and self.t_started > 0 and not self._joins:
            # the start time came (or passed) after the node was built on time: a late start joins the
            # running network, as the same incarnation (no second epoch claimed)
            self._joins = True
            self.node = self._build_node(joining=True, epoch=self.node.epoch)
            if self.tr is not None:
                self.tr.set_check(self.name, self.node.check_frame, self.node.max_message_bytes)
        self._cpu_at_start = time.process_time()
        if self.state_dir is not None:
            self._mlog = MeasurementLog(self.state_dir, self.name, self.run_id or repr(self.start), fsync=self.fsync)
        k = self._catch_up()
        self._publish("run", k)
        self.sched = SendSchedule(self.send_period, self.sc.min_send_interval, self.sc.sends,
                                  first=self.send_period * (math.floor(self.t_started / self.send_period + EPS) + 1))
        self._sending = True   # event sends between steps (Host._loop: send_news)
        for k in range(k + 1, len(self.times)):
            t = float(self.times[k])
            yield Wait(self.start + t / self.speed)
            self.node.predict(t)
            self.collect(t)
            self._fuse_until(t)
            self.sync_links(t)
            if self.chaos is not None and self.chaos.apply_due(self.node) is not None:
                self._stats_due = 0.0   # this step's publication carries the count
            self.receive()
            self._send_due(t)
            self._publish("run", k)
            lag = (time.time() - self.start) - t / self.speed   # wall seconds behind the schedule
            self.counters["lag_ms"] = max(0, int(lag * 1000))   # (the last step's: the lag at the end)
            if lag * 1000 > self.counters["max_lag_ms"]:
                self.counters["max_lag_ms"] = int(lag * 1000)
        self._sending = False
        yield from self._final_phase()

    def _send_due(self, t: float) -> None:
        """Send what :class:`~dfusion.fusion.sending.SendSchedule` says is due at scenario time ``t``:
        every link at the send period or after a change of the tree, news at once (event sends,
        at least ``min_send_interval`` apart per link). On a fixed tree a neighbour that is not
        alive is skipped (counted; with emulated links the draws are made, as ``simulate`` makes
        them for every send)."""
        skip = () if self.schedule is not None else tuple(nb for nb in self.neighbors if not self.tr.alive(nb))
        msgs = self.sched.due(self.node, t, skip=skip)
        for nb in self.sched.skipped:
            self.counters["skipped_not_alive"] += 1
            if self.links is not None:
                self.links.send(nb, b"", t, deliver=False)
        for nb, data in msgs:
            if self.links is not None:
                self.links.send(nb, data, t)
            else:
                self.tr.send(self.name, nb, data, t)

    def send_news(self) -> None:
        """Between steps: send the news that messages brought (event sends), if their links' minimum
        intervals have passed; the time is scenario time now, at most the run's end."""
        if not self._sending or self.start is None:
            return
        t = min(self.now(), float(self.times[-1]))
        if self.sched.next_event(self.node) <= t + EPS:
            self._send_due(t)

    def next_send_due(self) -> float:
        """Wall time of this node's next event send (``inf``: none waits)."""
        if not self._sending or self.start is None:
            return math.inf
        te = self.sched.next_event(self.node)
        return -math.inf if te == -math.inf else (math.inf if te == math.inf else self.start + te / self.speed)

    def _wait_for_start(self) -> Iterator[Wait]:
        """Wait for the start time; publish "ready" once the neighbours are seen."""
        opened = time.time()
        last_ready = -math.inf
        before_start = self._start_now
        if self.start is None and self._start_now:
            self.start = opened
        while True:
            if self.start is None:
                self.start = self.start_file.read()
            now = time.time()
            if self.start is not None:
                if now >= self.start:
                    break
                before_start = True
            up = all(self.tr.alive(nb) for nb in self.neighbors)
            if (up or now - opened > self.ready_timeout) and now - last_ready >= READY_PERIOD:
                self._publish("ready", -1)
                last_ready = now
            yield Wait(now + POLL if self.start is None else min(now + POLL, self.start))
        now = self.now()
        # started on time: scenario time 0; started late (restart): everything before now is past
        self.t_started = 0.0 if before_start or now <= self.sc.dt * 0.5 else now
        if self.t_started > 0:
            log.warning("%s: started at scenario time %.3f (incarnation %d)", self.name, self.t_started, self.node.epoch)

    def _catch_up(self) -> int:
        """After a late start: predict to now, replaying logged measurements; returns the last step done."""
        self._replay = {m.key: m for m in self._mlog.entries} if self._mlog is not None else {}
        k0 = int(np.searchsorted(self.times, self.t_started + EPS, side="right")) - 1
        for k in range(1, k0 + 1):
            t = float(self.times[k])
            self.node.predict(t)
            self._fuse_until(t)
        if self.t_started > 0:
            log.warning("%s: replayed %d logged measurements, %d lost while down; resuming at step %d (t=%.2f)",
                        self.name, self.counters["measurements_replayed"], len(self.lost), k0, self.times[k0])
        return k0

    # ------------------------------------------------------------------ pieces of a step
    def _fuse_until(self, t: float) -> None:
        meas, i = self.meas, getattr(self, "_im", 0)
        while i < len(meas) and meas[i].arrival <= t + EPS:
            self._fuse(meas[i])
            i += 1
        self._im = i

    def _fuse(self, m: OwnMeasurement) -> None:
        logged = self._replay.get(m.key)
        replayed = logged is not None
        if replayed:
            m = logged   # the log is the record of what this node measured
        elif m.arrival < self.t_started - EPS:
            self.lost.append(m.t)   # arrived while no incarnation of this node was running
            return
        if self._mlog is not None and not replayed:
            self._mlog.append(m)   # write-ahead: logged before it is fused
        try:
            self.fuse_one(m)
            self.counters["measurements_fused"] += 1
            self.counters["measurements_replayed"] += replayed
        except OutsideWindowError:
            self.counters["measurements_refused"] += 1
            log.info("%s: measurement at t=%.3f arrived after it left the window", self.name, m.t)

    def collect(self, t: float) -> None:
        """Before fusing at scenario time ``t``: append what arrived to :attr:`meas` (arrival ``t``).
        Nothing here: the measurements are known in advance; a live node takes its topics'
        (:class:`dfusion.run.live.LiveNodeProcess`)."""

    def forget_fused(self) -> None:
        """Drop the measurements fused so far from :attr:`meas` (a live node's list would grow without end)."""
        del self.meas[: getattr(self, "_im", 0)]
        self._im = 0

    def fuse_one(self, m: OwnMeasurement) -> None:
        """Fuse one measurement with the node's front end (raises ``OutsideWindowError`` when it
        is older than the window)."""
        self.front.process(self.node, m.t, m.z)

    def published(self, status: Status) -> None:
        """After every publication to the monitor (``ready``, each step, ``final``, ``stopped``).
        Nothing here; a live node publishes its estimate and health to ROS 2."""

    def linked(self) -> tuple[str, ...]:
        """The neighbours this node has a link to now: with links that change, those
        :meth:`sync_links` keeps; on a fixed tree every tree neighbour."""
        return tuple(self.node.neighbors) if self.schedule is not None else self.neighbors

    def sync_links(self, t: float) -> tuple[list[str], list[str]]:
        """Links that change: a link to ``j`` exists while the scenario allows it at ``t``
        (:class:`~dfusion.scenario.links.LinkSchedule`: scripted links and events, radio ranges
        over the nodes' known positions and paths) **and** ``j``'s liveliness token is seen;
        tell the node which links appeared and went (:meth:`FusionNode.link_up`,
        :meth:`FusionNode.link_down`: the tree rule). Frozen during the final phase (a
        neighbour that ends its run is not a link break). Returns ``(up, down)``."""
        if self.schedule is None or self._links_frozen:
            return [], []
        want = {j for j in self.schedule.neighbours(self.name, t) if self.tr.alive(j)}
        have = set(self.node.neighbors)
        down, up = sorted(have - want), sorted(want - have)
        for j in down:
            self.node.link_down(j)
        for j in up:
            self.node.link_up(j)
        if up or down:
            tree = self.node.tree
            log.info("%s: t=%.2f links%s%s; tree epoch %s, parent %s, tree links %s", self.name, t,
                     f" up {','.join(up)}" if up else "", f" down {','.join(down)}" if down else "",
                     tree.epoch, tree.parent, ",".join(self.node.tree_links) or "-")
        return up, down

    def receive(self) -> int:
        """Fuse every message that has arrived for this node; returns the blocks changed."""
        changed = 0
        T = float(self.times[-1])
        self._count_rejected_on_arrival()
        for d in self.tr.receive(self.name):
            if d.t_sent > T + EPS:   # a final-phase round: sent at scenario time T + r dt
                r = int(round((d.t_sent - T) / self.sc.dt))
                self._round_seen[d.src] = max(self._round_seen.get(d.src, 0), r)
            try:
                # the transport ran this node's check_frame (checksum, MAC) on these bytes as they arrived
                changed += self.node.receive(d.data, checked=d.checked)
            except MessageError:
                pass   # counted in node.stats.messages_rejected and logged by the node
        return changed

    def _count_rejected_on_arrival(self) -> None:
        """Count the copies the transport's check dropped as they arrived (in the node's stats and log)."""
        if self.tr is not None:
            counts, detail = self.tr.take_rejections(self.name)
            if counts:
                self.node.count_rejections(counts, detail)

    def _send_all(self, t: float, *, final: bool = False) -> None:
        emulate = self.links is not None and not final   # the final phase is lossless, as in simulate
        if self.schedule is not None:   # links that change: fusion messages on tree links, beacons on the others
            for nb, data in self.node.outgoing(sent_at=t):
                if emulate:
                    self.links.send(nb, data, t)
                else:
                    self.tr.send(self.name, nb, data, t)
            return
        for nb in self.neighbors:
            if not self.tr.alive(nb):
                self.counters["skipped_not_alive"] += 1
                if emulate:   # simulate draws for every send: keep the link's random stream aligned
                    self.links.send(nb, b"", t, deliver=False)
                continue
            data = self.node.message_to(nb, sent_at=t)
            if emulate:
                self.links.send(nb, data, t)
            else:
                self.tr.send(self.name, nb, data, t)
        self.node.settle()   # the bookkeeping the messages left for later, now that they are out

    def _waiting_for(self, r: int) -> list[str]:
        """Live neighbours whose round ``r`` has not arrived yet."""
        return [nb for nb in self.linked() if self._round_seen.get(nb, 0) < r and self.tr.alive(nb)]

    def _final_phase(self) -> Iterator[Wait]:
        """``diameter + 2`` (:func:`dfusion.topology.settling_rounds`) synchronized rounds without new measurements, then the final estimate.

        Round ``r``: send to every live neighbour (transport time ``T + r dt``),
        then wait until every live neighbour's round ``r`` has arrived (or
        ``round_timeout``). Information thus moves one hop per round whatever
        the nodes' relative delays, so after ``diameter + 2`` rounds every node
        holds everything: the in-process ``final_rounds`` over a real network.
        """
        T = float(self.times[-1])
        self.sync_links(T)
        self._links_frozen = True   # neighbours that end their run now do not break links
        self.tr.quiet_loss = True   # neighbours leaving now is the normal end
        if self.links is not None:
            self.links.flush()   # what is still in flight arrives before the rounds (simulate: net.flush())
        self._fuse_until(math.inf)
        for r in range(1, self.rounds + 1):
            self.receive()
            self._send_all(T + r * self.sc.dt, final=True)
            yield Wait(time.time() + self.round_timeout, until=lambda r=r: not self._waiting_for(r))
            waiting = self._waiting_for(r)
            if waiting:
                log.warning("%s: no round %d from %s after %.1f s: going on", self.name, r, waiting,
                            self.round_timeout)
        self.receive()
        status = self._publish("final", len(self.times) - 1)
        self.node.flush_log()
        if self.result is not None:
            self.result.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.result.with_suffix(".tmp")
            tmp.write_text(json.dumps(status.to_json()))
            tmp.replace(self.result)
        log.info("%s: final estimate published (t=%.2f)", self.name, T)
        yield Wait(time.time() + 0.05)   # let the last publications leave before the session closes

    def stats(self) -> dict[str, int]:
        """The node's counters (messages, measurements, CPU, link emulation) as the monitor records them."""
        self._count_rejected_on_arrival()
        self.node.rejection_log.tick()
        s = self.node.stats
        tot = self.tr.node_totals(self.name) if self.tr is not None else None
        out = {
            "messages_sent": s.messages_sent, "bytes_sent": s.bytes_sent, "messages_received": s.messages_received,
            "messages_rejected": s.messages_rejected, "duplicates": s.duplicates,
            "rejected_on_arrival": s.rejected_on_arrival,
            **{f"rejected_{reason}": count for reason, count in s.rejections.items()},
            "blocks_outside_window": s.blocks_outside_window, "blocks_too_far_ahead": s.blocks_too_far_ahead,
            "delivered": tot.delivered if tot else 0, "published": tot.sent if tot else 0,
        }
        if self.tr is not None:   # the receive queue's bound in bytes: its peak and what it shed
            q = self.tr.queue_report(self.name)
            out.update(receive_queue_peak_bytes=q["peak_bytes"], receive_queue_shed=q["shed"],
                       receive_queue_shed_bytes=q["shed_bytes"], log_lines_held_back=self.tr.log_budget.held_back)
        out.update(self.counters)
        if self.schedule is not None:
            out.update(tree_changes=s.tree_changes, new_epochs=s.new_epochs, not_fused=s.not_fused,
                       not_linked=s.not_linked, withdrawn_blocks=s.withdrawn_blocks,
                       epochs_started=self.node.tree.epochs_started)
        guard = getattr(self.node, "guard", None)
        if guard is not None:   # the consistency test of the neighbours' information (docs/clutter.md)
            g = guard.summary()
            out.update(guard_tests=g["tests"], guard_failures=g["failures"], quarantines=g["quarantines"],
                       quarantined_now=len(g["quarantined"]))
        if self.chaos is not None:
            out["chaos_lapses"] = self.chaos.applied
        if self.log_cap is not None:
            out["log_lines_dropped"] = self.log_cap.dropped
        out["cpu_ms"] = int(self.cpu * 1000)
        if self._cpu_at_start is not None:   # the process's CPU clock sums every thread's: costly, not every step
            out["host_cpu_ms"] = int((time.process_time() - self._cpu_at_start) * self.host_share * 1000)
        if self.links is not None:
            em = self.links.totals()
            out.update(dropped_emulated=em["dropped"], delayed_emulated=em["delayed"],
                       duplicated_emulated=em["duplicated"])
        return out

    def _tree_status(self) -> TreeStatus | None:
        """This node's view of the tree (links that change), for the monitor."""
        tree = self.node.tree
        if tree is None:
            return None
        return TreeStatus(tree.epoch.term, tree.epoch.root, tree.parent, tuple(self.node.neighbors),
                          tuple(self.node.tree_links))

    def _publish(self, phase: str, k: int) -> Status:
        if phase in ("ready", "stopped"):
            mean = cov = None
            t = self.now() if self.start is not None else 0.0
        else:
            mean, cov = self.node.estimate()
            t = float(self.times[k])
        output = None
        if mean is not None and self._records_output:
            chosen = self.node.output()
            output = (chosen.name, chosen.mean, chosen.cov)
        stats = {}
        now = time.monotonic()
        if phase != "run" or now >= self._stats_due:   # the counters once a second, the estimate every step
            stats, self._stats_due = self.stats(), now + STATS_PERIOD
        st = Status(self.name, self.node.epoch, phase, k, t if math.isfinite(t) else 0.0, mean, cov,
                    self.t_started, stats, list(self.lost) if phase == "final" else [], output,
                    self._tree_status() if mean is not None else None)
        try:
            if phase == "final":
                self.tr.session.put(self._monitor_key, st.encode(self.node.frame_key),
                                    congestion_control=zenoh.CongestionControl.BLOCK)
            elif phase == "run" and self.monitor_batch is not None:
                self.monitor_batch.append((self, st.encode(self.node.frame_key)))   # the host sends it
            else:
                self._pub.put(st.encode(self.node.frame_key))
        except Exception as exc:   # the monitor is optional
            log.debug("%s: monitor publication failed: %s", self.name, exc)
        self.published(st)
        return st


class Host:
    """Several :class:`NodeProcess` in one OS process, over one Zenoh session.

    Each node keeps its own loop (its program, :meth:`NodeProcess.program`), timing,
    message keys, state log and result; they share the session, so a message between
    two nodes of one host is still encoded, published and received through Zenoh
    (delivered inside the session), exactly as between processes. The host runs the
    programs in one thread: it resumes each node whose wait is over, in turn, and hands
    every node its messages as soon as they arrive.

    A node whose program raises ends the host (the exception propagates: the process
    exits with an error status, and ``dfusion run`` restarts the host with all its
    nodes, each as a new incarnation).

    Parameters
    ----------
    procs : list of NodeProcess
        The nodes (one network; one start time and speed).
    network, zconfig : the session's network name and settings.
    parent_pid, watch : stop when the parent or the launcher is gone.
    registry : EndpointRegistry, optional
        A run directory's endpoint registry (``--run-dir`` without ``--listen``): the session
        listens on a port the kernel picks, connects to the peers registered so far, and
        registers the endpoint it got (:mod:`dfusion.run.endpoints`).
    label : str
        The host's name in the registry (default: its nodes' names joined by ``+``).
    """

    def __init__(self, procs: list[NodeProcess], *, network: str, zconfig: ZenohConfig | None = None,
                 parent_pid: int | None = None, watch: LauncherWatch | None = None,
                 registry: EndpointRegistry | None = None, label: str | None = None) -> None:
        if not procs:
            raise DfusionError("a host needs at least one node")
        names = [p.name for p in procs]
        if len(set(names)) != len(names):
            raise DfusionError(f"a node appears twice in one host: {names}")
        self.procs = list(procs)
        self.network = network
        self.zconfig = zconfig or ZenohConfig()
        self.parent_pid = parent_pid
        self.watch = watch
        self.stop_reason: str | None = None
        self.tr: ZenohTransport | None = None
        self.registry = registry
        self.label = label or "+".join(names)
        #: The endpoint this host's session listens on (known once the session is open).
        self.endpoint: str | None = None
        self._monitor_batch: list[tuple[NodeProcess, bytes]] = []
        self._batch_pubs: dict[str, object] = {}

    def request_stop(self, reason: str) -> None:
        """Ask every node to stop (safe from a signal handler: only sets flags)."""
        if self.stop_reason is None:
            self.stop_reason = reason
        for p in self.procs:
            p.request_stop(reason)

    def _should_stop(self) -> bool:
        if self.parent_pid is not None and os.getppid() != self.parent_pid:
            self.request_stop(f"parent process {self.parent_pid} is gone")
        if self.watch is not None and not self.watch.alive():
            self.request_stop(f"the launcher is gone ({self.watch.path} is free)")
        if self.stop_reason is None:
            stopped = next((p.stop_reason for p in self.procs if p.stop_reason is not None), None)
            if stopped is not None:
                self.request_stop(stopped)
        return self.stop_reason is not None

    def now(self) -> float:
        """Scenario time of the host's nodes (the first one's clock: they share start and speed)."""
        return self.procs[0].now()

    def flush_monitor(self) -> None:
        """Send the step publications the nodes made since the last call: one Zenoh put per
        :data:`~dfusion.run.common.MAX_STATUS_BATCH` of them, on the key of the first one's node
        (:func:`~dfusion.run.common.encode_status_batch` on
        :func:`~dfusion.transport.zenoh.monitor_batch_key`; one alone goes as it is). An isolated
        put costs a Zenoh session tens of microseconds of CPU in its own threads and the caller's;
        a host's nodes step together, so their publications of a step share one."""
        batch = self._monitor_batch
        if not batch:
            return
        for i in range(0, len(batch), MAX_STATUS_BATCH):
            part = batch[i:i + MAX_STATUS_BATCH]
            first = part[0][0]
            try:
                if len(part) == 1:
                    first._pub.put(part[0][1])
                    continue
                pub = self._batch_pubs.get(first.name)
                if pub is None:
                    pub = self._batch_pubs[first.name] = self.tr.session.declare_publisher(
                        monitor_batch_key(self.network, first.name))
                pub.put(encode_status_batch([d for _, d in part]))
            except Exception as exc:   # the monitor is optional
                log.debug("%s: monitor publication failed: %s", self.label, exc)
        batch.clear()

    def run(self) -> int:
        """Run every node to its end (or until stopped); returns the exit status (0)."""
        try:
            with self._open_transport() as tr:
                self.tr = tr
                for p in self.procs:
                    p.attach(tr)
                    p.host_share = 1.0 / len(self.procs)
                    if len(self.procs) > 1:
                        p.monitor_batch = self._monitor_batch
                try:
                    self._loop(tr)
                finally:
                    self.flush_monitor()
                if self.stop_reason is not None:
                    for p in self.procs:
                        p.stopped()
        finally:
            for p in self.procs:
                p.close()
        return 0

    def _open_transport(self) -> ZenohTransport:
        """The host's session: on its configured endpoints, or (a registry) on a port the kernel
        picks, connected to the peers registered so far, and registered under the registry's lock."""
        nodes = {p.name: p.neighbors for p in self.procs}
        if self.registry is None:
            return self._transport(nodes, self.zconfig)
        with self.registry.lock():
            mine = set(nodes)
            peers_of = sorted({nb for nbs in nodes.values() for nb in nbs} - mine)
            known = sorted(set(self.registry.endpoints(peers_of).values()))
            cfg = replace(self.zconfig, connect=tuple(dict.fromkeys(self.zconfig.connect + tuple(known))),
                          report_endpoints=True)
            tr = self._transport(nodes, cfg)
            try:
                self.endpoint = bound_endpoints(tr.session)[0]
                self.registry.register(self.label, list(nodes), self.endpoint)
            except BaseException:
                tr.close()
                raise
        log.info("host %s listens on %s (connected to %d registered peer endpoints)", self.label, self.endpoint,
                 len(known))
        return tr

    def _transport(self, nodes: dict[str, tuple[str, ...]], cfg: ZenohConfig) -> ZenohTransport:
        try:
            return ZenohTransport(self.network, nodes, cfg, clock=self.now)
        except zenoh.ZError as exc:   # e.g. an explicit --listen port someone else holds
            first = str(exc).split(" at /", 1)[0]
            raise DfusionError(f"cannot open the Zenoh session (listen {list(cfg.listen) or 'default'}): {first}") \
                from None

    def _loop(self, tr: ZenohTransport) -> None:
        opened = time.time()
        for p in self.procs:
            if p.start is None and p._start_now:   # one start for every node of the host
                p.start = opened
        programs = {p.name: p.program() for p in self.procs}
        waits = {p.name: Wait(0.0) for p in self.procs}
        procs = {p.name: p for p in self.procs}
        linked = [p for p in self.procs if p.links is not None]
        cpu = time.thread_time   # this thread's CPU: what each node's own work costs
        # when each node's next event send is due (NodeProcess.next_send_due): it changes only when
        # the node's own code runs (a step, a receive, a send), so it is asked again only then
        send_due = {name: -math.inf for name in procs}
        while programs:
            if self._should_stop():
                return
            now = time.time()
            for p in linked:
                if p.links.next_due() <= now:
                    p.links.release_due(now)
            c = None   # the thread's CPU clock read last in this pass (one read per node resumed)
            for name in list(programs):
                w = waits[name]
                if now >= w.deadline or (w.until is not None and w.until()):
                    c0 = cpu() if c is None else c
                    p = procs[name]
                    try:
                        waits[name] = next(programs[name])
                        send_due[name] = p.next_send_due()
                    except StopIteration:
                        del programs[name], waits[name]
                    c = cpu()
                    p.cpu += c - c0
                    now = time.time()
            self.flush_monitor()   # the step publications of the nodes resumed now, together
            if not programs:
                return
            for name in programs:   # event sends whose minimum interval has passed
                if send_due[name] <= now:
                    p = procs[name]
                    c0 = cpu()
                    p.send_news()
                    send_due[name] = p.next_send_due()
                    p.cpu += cpu() - c0
            due = min(min(w.deadline for w in waits.values()), min(send_due[name] for name in programs),
                      min((p.links.next_due() for p in linked), default=math.inf))
            if tr.wait(max(0.0, min(due - time.time(), LOOP_POLL))):
                c = None
                for name, p in procs.items():
                    if tr.pending(name):
                        if name in programs:
                            c0 = cpu() if c is None else c
                            p.receive()
                            p.send_news()   # relay at once what changed the node's belief
                            send_due[name] = p.next_send_due()
                            c = cpu()
                            p.cpu += c - c0
                        else:
                            tr.receive(name)   # after its final estimate a node fuses nothing more
                tr.poll()


# ---------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m dfusion.run.node_process",
                                description="Run dfusion fusion nodes over Zenoh: one, or several in one process (a host).")
    p.add_argument("--scenario", required=True, help="scenario TOML file")
    p.add_argument("--node", required=True, action="append", metavar="NAME",
                   help="a node of the scenario to run here (repeatable: several nodes in this process, one Zenoh "
                        "session)")
    p.add_argument("--host", default=None, metavar="NAME",
                   help="this process's name in its log lines (default: its node's name, or its nodes' joined by +)")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    p.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    p.add_argument("--duration", type=float, default=None, help="override the scenario's duration")
    p.add_argument("--sends", choices=("event", "periodic"), default=None,
                   help="override when the nodes send (event: news at once, rate-limited per link, plus the periodic "
                        "heartbeat; periodic: every send period only)")
    p.add_argument("--min-send-interval", type=float, default=None, metavar="S",
                   help="override the least seconds between two messages on one link (event sends)")
    p.add_argument("--network", default="dfusion", help="network name: the Zenoh key space dfusion/NETWORK/...")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (repeatable; default tcp/127.0.0.1:0). With --run-dir and no "
                        "--listen the port the kernel gives is registered in RUN_DIR/endpoints/ and the peers "
                        "registered there are connected to (dfusion.run.endpoints)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint of a neighbour or router to connect to (repeatable)")
    p.add_argument("--mode", choices=("peer", "client"), default="peer", help="Zenoh mode (client: via routers)")
    p.add_argument("--zenoh-option", action="append", default=[], metavar="PATH=JSON",
                   help="extra Zenoh configuration, e.g. transport/link/tx/lease=2000 (repeatable)")
    p.add_argument("--speed", type=float, default=1.0, help="scenario seconds per wall-clock second")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--start-time", type=float, default=None, help="UNIX time of scenario time 0 (default: now)")
    g.add_argument("--start-file", default=None, help="wait for this file to hold the UNIX start time")
    p.add_argument("--measurements", default=None,
                   help="recording of the nodes' measurements (.jsonl or .npz), or a directory of NAME.jsonl files")
    p.add_argument("--record", default=None, metavar="OUT",
                   help="write the node's measurements of the scenario to OUT (.jsonl or .npz) and exit (one --node)")
    p.add_argument("--state-dir", default=None, help="directory of the measurement log replayed at restart")
    p.add_argument("--run-id", default=None, help="identifies the run in the state log (default: the start time)")
    p.add_argument("--fsync", action="store_true", help="fsync the measurement log after every line")
    p.add_argument("--network-key-file", default=None,
                   help="HMAC key file (default: $DFUSION_NETWORK_KEY_FILE or $DFUSION_NETWORK_KEY)")
    p.add_argument("--result", default=None,
                   help="write the final estimate and counters here (JSON); with several nodes a directory (NAME.json)")
    p.add_argument("--run-dir", default=None, metavar="DIR",
                   help="join the run of the dfusion run launcher working in DIR (start time, state, result and "
                        "network key from DIR); refused when no launcher runs there or this node already runs; "
                        "stops when the launcher is gone")
    p.add_argument("--emulate-links", action="store_true",
                   help="apply the scenario's links (latency, jitter, drops, duplicates, reordering, outages) to sends")
    p.add_argument("--round-timeout", type=float, default=ROUND_TIMEOUT,
                   help="seconds to wait for a live neighbour's message of a final-phase round")
    p.add_argument("--parent-pid", type=int, default=None,
                   help="stop when this process is no longer the parent (prefer --run-dir: a restart by hand keeps it)")
    p.add_argument("--ready-timeout", type=float, default=5.0,
                   help="report ready after this many seconds even if a neighbour is not up")
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable)")
    p.add_argument("--chaos-dir", default=None, metavar="DIR",
                   help="testing only (benchmarks/chaos.py): apply the one-sided link lapses requested in DIR "
                        "(docs/chaos.md); off by default")
    add_tls_arguments(p, directory=False)
    p.add_argument("-v", "--verbose", action="count", default=0)
    return p


def standby(run_dir: str | Path) -> int:
    """``python -m dfusion.run.node_process --standby RUN_DIR``: a warm spare for fast restarts.

    The launcher keeps one such process ready: it has imported everything (about
    1-3 s of a node's start on a busy machine) and waits for one line on its
    standard input, ``{"argv": [node arguments], "log": path}``. It then sends its
    output to ``log`` and becomes that node (:func:`main` with ``argv``: the same
    command line as ``RUN_DIR/commands/NAME.sh``). It watches the launcher like a
    node: it exits when the launcher is gone (lock free, parent-death signal) or
    closes its standard input.
    """
    import select

    watch = LauncherWatch(run_dir)
    if not watch.alive():
        return EXIT_NO_LAUNCHER
    if watch.launcher_pid() == os.getppid():
        set_parent_death_signal(signal.SIGTERM)   # no handler yet: the default action ends the process
    try:   # warm up what loading the scenario imports (sensor kinds, plug-ins)
        info = json.loads((Path(run_dir) / "run.json").read_text())
        load_scenario(info["scenario"], plugins=info.get("plugins", []))
    except Exception as exc:   # only a warm-up
        print(f"standby: warm-up skipped: {exc}", file=sys.stderr, flush=True)
    while True:
        if not watch.alive():
            return 0
        ready, _, _ = select.select([sys.stdin], [], [], POLL)
        if ready:
            line = sys.stdin.readline()
            if not line:
                return 0   # the launcher closed the pipe: not needed
            order = json.loads(line)
            break
    watch.close()
    sys.stdout.flush()
    sys.stderr.flush()
    fd = os.open(order["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    return main(list(order["argv"]))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--standby"] and len(argv) == 2:
        return standby(argv[1])
    args = build_parser().parse_args(argv)
    if len(set(args.node)) != len(args.node):
        build_parser().error(f"a node is named twice: {args.node}")
    if args.record and len(args.node) != 1:
        build_parser().error("--record writes one node's measurements: give one --node")
    host: Host | None = None
    early: list[str] = []

    def on_signal(signum, frame):  # only sets a flag; the loop looks at it every LOOP_POLL seconds at most
        name = signal.Signals(signum).name
        if host is not None:
            host.request_stop(name)
        else:
            early.append(name)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    level = [logging.INFO, logging.DEBUG][min(args.verbose, 1)]
    label = args.host or "+".join(args.node)
    logging.basicConfig(level=level, stream=sys.stderr, force=True,
                        format=f"%(asctime)s %(levelname)s [{label}] %(name)s: %(message)s")
    handler = logging.getLogger().handlers[0]
    log_cap = LogByteCap(handler)
    handler.addFilter(log_cap)
    watch: LauncherWatch | None = None
    locks: list[FileLock] = []
    try:
        if args.run_dir is not None and not args.record:
            joined = _join_run(args)
            if isinstance(joined, int):
                return joined
            watch, locks = joined
        sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration,
                           plugins=args.plugin, sends=args.sends, min_send_interval=args.min_send_interval)
        if args.record:
            path = save_recording(args.record, args.node[0], world_measurements(sc, args.node[0]))
            print(f"wrote {path}")
            return 0
        several = len(args.node) > 1
        zc = ZenohConfig(mode=args.mode, listen=tuple(args.listen), connect=tuple(args.connect),
                         extra=parse_zenoh_options(args.zenoh_option),
                         tls=security_from_args(args).tls_files(args.node[0]))
        key = load_network_key(args.network_key_file)
        meas = _measurements(sc, args.node, args.measurements)
        procs = [NodeProcess(
            sc, name, network=args.network, zconfig=zc, speed=args.speed, start=args.start_time,
            start_file=args.start_file, measurements=meas[name], state_dir=args.state_dir, run_id=args.run_id,
            fsync=args.fsync, network_key=key,
            result=(Path(args.result) / f"{name}.json" if several else args.result) if args.result else None,
            emulate_links=args.emulate_links, round_timeout=args.round_timeout, ready_timeout=args.ready_timeout,
            chaos_dir=args.chaos_dir,
        ) for name in args.node]
        registry = EndpointRegistry(args.run_dir) if args.run_dir is not None and not args.listen else None
        host = Host(procs, network=args.network, zconfig=zc, parent_pid=args.parent_pid, watch=watch,
                    registry=registry, label=label)
        procs[0].log_cap = log_cap
        if early:
            return 0
        if several:
            log.info("host %s: nodes %s (pid %d)", label, ", ".join(args.node), os.getpid())
        profile_dir = os.environ.get(ENV_PROFILE)
        if not profile_dir:
            return host.run()
        import cProfile

        profiler = cProfile.Profile(time.thread_time)   # CPU of the loop's thread, not time spent waiting
        cpu0, thread0 = time.process_time(), time.thread_time()
        try:
            return profiler.runcall(host.run)
        finally:
            Path(profile_dir).mkdir(parents=True, exist_ok=True)
            profiler.dump_stats(Path(profile_dir) / f"{label}.pstats")
            (Path(profile_dir) / f"{label}.threads.json").write_text(json.dumps(
                {"nodes": list(args.node), "process_cpu_s": time.process_time() - cpu0,
                 "main_thread_cpu_s": time.thread_time() - thread0, "threads": thread_cpu()}))
    except (DfusionError, OSError) as exc:
        log.error("%s", exc)
        return 2
    finally:
        for lock in locks:
            lock.release()
        if watch is not None:
            watch.close()


def thread_cpu() -> dict[str, float]:
    """CPU seconds of every thread of this process so far, summed by thread name (Linux:
    ``/proc/self/task/TID/stat``; empty elsewhere): the profile's view of Zenoh's own threads."""
    out: dict[str, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            stat = Path(f"/proc/self/task/{tid}/stat").read_text()
        except OSError:
            continue   # the thread ended meanwhile
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick   # utime + stime
    return out


def _measurements(sc: Scenario, names: list[str], source: str | None) -> dict[str, list[OwnMeasurement]]:
    """Each node's measurements: from a recording (a file, or a directory of ``NAME.jsonl``),
    else from the scenario's world, simulated once for every node of the process."""
    if source is not None:
        path = Path(source)
        return {n: load_recording(path / f"{n}.jsonl" if path.is_dir() else path, n) for n in names}
    return nodes_measurements(sc, None, names)   # simulates the world (the launcher gives a recording)


def _join_run(args: argparse.Namespace) -> tuple[LauncherWatch, list[FileLock]] | int:
    """``--run-dir``: watch the launcher, take every node's lock, and default the run's files.

    Returns the watch and the locks, or the exit status when the nodes must not run.
    """
    run_dir = Path(args.run_dir)
    watch = LauncherWatch(run_dir)
    if not watch.alive():
        log.error("no dfusion run launcher runs in %s (its lock %s is free): not starting", run_dir, watch.path)
        watch.close()
        return EXIT_NO_LAUNCHER
    launcher = watch.launcher_pid()
    if launcher is not None and launcher == os.getppid():
        # started by the launcher: the kernel stops us (SIGTERM) if it dies, even between two looks at the lock
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != launcher:   # it died before the prctl
            log.error("the launcher (pid %d) is gone", launcher)
            watch.close()
            return EXIT_NO_LAUNCHER
    locks: list[FileLock] = []
    for name in args.node:
        lock = FileLock(node_lock_path(run_dir, name))
        if not lock.acquire(timeout=2.0):
            holder = lock.path.read_text().strip() if lock.path.exists() else "?"
            log.error("node %s already runs in %s (pid %s): not starting a second incarnation", name, run_dir, holder)
            for taken in locks:
                taken.release()
            watch.close()
            return EXIT_ALREADY_RUNNING
        locks.append(lock)
    if args.start_time is None and args.start_file is None:
        args.start_file = str(run_dir / "start")
    if args.state_dir is None:
        args.state_dir = str(run_dir / "state")
    if args.result is None:
        args.result = str(run_dir / "results" / f"{args.node[0]}.json" if len(args.node) == 1 else run_dir / "results")
    if args.network_key_file is None and (run_dir / "network.key").exists():
        args.network_key_file = str(run_dir / "network.key")
    if not args.listen:   # the registry (dfusion.run.endpoints): connect to the launcher's monitor too
        try:
            monitor = json.loads((run_dir / "run.json").read_text()).get("monitor_endpoint")
        except (OSError, ValueError):
            monitor = None
        if monitor and monitor not in args.connect:
            args.connect.append(monitor)
    log.info("joined the run in %s (launcher pid %s, pid %d)", run_dir, launcher, os.getpid())
    return watch, locks


if __name__ == "__main__":
    sys.exit(main())
