r"""``dfusion run`` of a multi-target scenario: one OS process per tracking node, over Zenoh, in lockstep.

Every process runs its node's :class:`~dfusion.fusion.tracking_node.TrackingNode` through the
steps ``t_k = k dt`` of the scenario, with the same code as ``dfusion simulate``
(:class:`~dfusion.sim.tracking_runner.NodeDriver`: frames, receive, predict, send) over the same
world (:func:`~dfusion.sim.target_world.simulate_targets`, deterministic by the scenario's seed:
each process computes it). The network is real (one Zenoh session per process, one key
expression per directed link, :class:`~dfusion.transport.zenoh.ZenohTransport`); what the
scenario's links do to a bundle is decided at the sender, as ``simulate`` decides it.

**Lockstep.** ``simulate`` delivers a bundle sent at ``t_s`` on link ``a -> b`` when ``b``
receives at the first step ``t_k >= t_s + delay`` (the delay drawn by
:class:`~dfusion.transport.SimulatedNetwork` from the link's own random generator, seeded
from the scenario's seed and the link's name only: the ``n``-th bundle on a link gets the same
latency, jitter, drop, duplicate and reordering draws whatever the other links do). So:

1. at step ``k`` a sender passes each bundle through its own ``SimulatedNetwork`` (the
   scenario's links and seed), which gives every copy's arrival time or loses it (drop,
   outage), and publishes **one step frame per neighbour per step** (also when it carries no
   bundle): ``[k, [[t_arrival, copy index, bundle], ...]]``, with an HMAC-SHA256 over the
   network, the run, the link and the frame under the run's network key (a frame that fails
   it is dropped, counted and logged; the bundles carry their own MAC too);
2. before receiving at step ``k``, node ``n`` waits until it holds neighbour ``j``'s frames
   up to step ``k`` if ``j`` comes before ``n`` in name order (``simulate`` steps the nodes in
   that order, so ``j``'s bundles of step ``k`` can reach ``n`` at step ``k`` over a link
   without delay), else up to step ``k - 1``; nothing sent later can arrive by ``t_k``;
3. it then receives the copies with ``t_arrival <= t_k`` in ``simulate``'s order: by arrival
   time, ties by send order (step, sender's rank, copy index).

So every node's tracks equal ``simulate``'s at every step, to the last bit, for every link
setting (latency, jitter, drops, duplicates, reordering, outages). A frame that does not come
within ``lag_timeout`` seconds (a stalled or killed neighbour, a lost frame) is waited for no
longer: the node goes on, counts a **lag** and logs it (the run's JSON: ``run.lags``), and
does not wait for that neighbour again until its frames have caught up; the run is then no
longer identical to ``simulate``. The processes run as fast as the lockstep
lets them (no real-time pacing: ``--speed`` does not apply).

**Processes.** The launcher (:class:`TrackingLauncher`) writes ``RUN_DIR/run.json`` (the
scenario, its overrides, the network name, run identifier and key file: ``RUN_DIR/network.key``,
mode 0600, or the one given), starts ``python -m dfusion.run.tracking --run-dir RUN_DIR --node
NAME`` per node (its own process group, SIGTERM when the launcher dies), each of which opens its
session on a port the kernel picks and registers it (:mod:`dfusion.run.endpoints`), writes
``RUN_DIR/ready/NAME`` once its tree neighbours are alive (Zenoh liveliness) and starts when the
launcher writes ``RUN_DIR/start``. After the last step a node waits for its neighbours' last
frames (what is still in flight is counted as ``simulate`` counts it), writes its tracks at
every step and its counters to ``RUN_DIR/results/NAME.json``, and exits when the launcher
writes ``RUN_DIR/finish`` (all results in). The launcher computes the centralized reference
and the table of ``simulate`` (:func:`~dfusion.sim.tracking_runner.tracking_metrics`).

A node process that exits before its result (killed, crashed) ends the run: the launcher
stops every other process and raises one line. Multi-target nodes are **not restarted**
(a restarted tracking node would need its neighbours' track windows again: not built).
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from dfusion.errors import DfusionError, MessageError
from dfusion.run.common import generate_network_key, load_network_key, new_run_id
from dfusion.run.endpoints import EndpointRegistry, bound_endpoints
from dfusion.run.supervision import child_command, exit_reason
from dfusion.scenario.build import build_tracking_node
from dfusion.scenario.loader import load_scenario
from dfusion.scenario.spec import Scenario
from dfusion.sim.target_world import simulate_targets
from dfusion.sim.tracking_runner import NodeDriver, TrackingResult, frames_by_step, run_central, tracking_metrics
from dfusion.tracking.history import TrackHistory
from dfusion.tracking.track import TrackId
from dfusion.transport.simulated import SimulatedNetwork
from dfusion.transport.zenoh import ZenohConfig, ZenohTransport, check_name

__all__ = ["TrackingRunOptions", "TrackingLauncher", "run_tracking_processes", "compare_with_simulate",
           "history_difference", "LAG_TIMEOUT"]

log = logging.getLogger("dfusion.run.tracking")   # also when run as __main__

#: Seconds a node waits for a neighbour's step frame before it goes on (a counted, logged lag).
LAG_TIMEOUT = 10.0
#: Seconds between SIGTERM and SIGKILL when the launcher stops the node processes.
TERM_GRACE = 1.2
#: Bytes of a step frame's HMAC-SHA256.
_TAG = 32
#: Lag lines a node logs before it only counts them.
_LAG_LINES = 5
_SAME_TIME = 1e-9
#: Most bundle copies one step frame may carry (a link delivers a few per step), and its largest size.
_MAX_COPIES = 1024
_MAX_FRAME_BYTES = 64 * 1024 * 1024


# ---------------------------------------------------------------------------- step frames
def _frame_tag(key: bytes, network: str, run: str, src: str, dst: str, body: bytes) -> bytes:
    head = json.dumps(["dfusion-lockstep", network, run, src, dst]).encode()
    return hmac.new(key, head + b"\0" + body, hashlib.sha256).digest()


def encode_frame(key: bytes, network: str, run: str, src: str, dst: str, step: int,
                 copies: list[tuple[float, int, bytes]]) -> bytes:
    """The step frame of link ``src -> dst`` at ``step`` (module docstring, 1)."""
    body = msgpack.packb([step, [[t, i, data] for t, i, data in copies]], use_bin_type=True)
    return body + _frame_tag(key, network, run, src, dst, body)


def decode_frame(key: bytes, network: str, run: str, src: str, dst: str,
                 data: bytes) -> tuple[int, list[tuple[float, int, bytes]]]:
    """``(step, [(t_arrival, copy index, bundle), ...])`` of a step frame; :class:`MessageError`
    when it is not a frame of this run's link ``src -> dst`` (its HMAC fails) or is malformed."""
    body, tag = data[:-_TAG], data[-_TAG:]
    if len(data) <= _TAG or not hmac.compare_digest(tag, _frame_tag(key, network, run, src, dst, body)):
        raise MessageError(f"step frame {src} -> {dst} fails its HMAC")
    try:
        step, copies = msgpack.unpackb(body, raw=False, max_bin_len=len(body), max_array_len=_MAX_COPIES,
                                       max_str_len=0, max_map_len=0, max_ext_len=0)
        if (isinstance(step, bool) or not isinstance(step, int) or step < 0
                or not isinstance(copies, list) or len(copies) > _MAX_COPIES):
            raise ValueError(f"step {step!r}")
        out = []
        for t, i, b in copies:
            if (not isinstance(b, bytes) or isinstance(i, bool) or not isinstance(i, int)
                    or isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)):
                raise ValueError("a copy must be [finite arrival time, integer index, bytes]")
            out.append((float(t), i, b))
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise MessageError(f"malformed step frame {src} -> {dst}: {exc}") from None
    return step, out


# ---------------------------------------------------------------------------- node process
class _Inbox:
    """A node's step frames from its neighbours: which steps it holds, and the copies not yet received."""

    def __init__(self, me: str, neighbors: tuple[str, ...], rank: dict[str, int]) -> None:
        self.me, self.rank = me, rank
        self.have = dict.fromkeys(neighbors, -1)
        self.pending: list[tuple[float, int, int, int, bytes]] = []   # (t_arrival, step, sender rank, copy, data)
        self.frames_lost = 0
        self.frames_rejected = 0
        self.frames_repeated = 0
        self.delivered = 0
        self.last = -1   # the run's last step

    def add(self, src: str, step: int, copies: list[tuple[float, int, bytes]]) -> None:
        if step <= self.have[src]:   # a step frame again (a replay: a link delivers each once): ignored, counted
            self.frames_repeated += 1
            return
        if step > self.have[src] + 1:
            self.frames_lost += step - self.have[src] - 1
            log.warning("%s: the step frames %d-%d of %s never came", self.me, self.have[src] + 1, step - 1, src)
        self.have[src] = max(self.have[src], step)
        self.pending += [(t, step, self.rank[src], i, data) for t, i, data in copies]

    def needed(self, src: str, k: int) -> int:
        """The last step of ``src`` whose frame must be here before receiving at step ``k``."""
        return k if self.rank[src] < self.rank[self.me] else k - 1

    def missing(self, k: int | None) -> list[str]:
        """The neighbours whose frames needed at step ``k`` are not here (``None``: up to the last step)."""
        if k is None:
            return [j for j, s in self.have.items() if s < self.last]
        return [j for j, s in self.have.items() if s < self.needed(j, k)]

    def take(self, t: float) -> list[bytes]:
        """The copies arrived by ``t``, in ``simulate``'s delivery order."""
        due = sorted(e for e in self.pending if e[0] <= t + _SAME_TIME)
        self.pending = [e for e in self.pending if e[0] > t + _SAME_TIME]
        self.delivered += len(due)
        return [e[4] for e in due]


class _NodeProcess:
    """One tracking node in its own process (module docstring)."""

    def __init__(self, run_dir: Path, name: str) -> None:
        self.run_dir = run_dir
        self.launcher = os.getppid()
        self.cfg = json.loads((run_dir / "run.json").read_text())
        self.name = name
        self.sc = _load(self.cfg)
        if name not in self.sc.nodes:
            raise DfusionError(f"{name!r} is not a node of {self.sc.path}")
        self.key = load_network_key(self.cfg["key_file"])
        if self.key is None:
            raise DfusionError("no network key: dfusion run of a multi-target scenario authenticates every frame")
        self.network, self.run_id = self.cfg["network"], self.cfg["run_id"]
        names = sorted(self.sc.nodes)
        self.rank = {n: i for i, n in enumerate(names)}
        self.neighbors = tuple(self.sc.neighbors(name))
        self.node = build_tracking_node(self.sc, name, network_key=self.key, epoch=self.rank[name] + 1,
                                        network=self.network, run=self.run_id)
        self.driver = NodeDriver(self.sc, self.node)
        self.net = SimulatedNetwork(((a, b, spec) for (a, b), spec in self.sc.links.items()), seed=self.sc.seed)
        self.inbox = _Inbox(name, self.neighbors, self.rank)
        self.lags = 0
        self.lagging: set[str] = set()   # neighbours that lagged and have not caught up since
        self.lag_timeout = float(self.cfg["lag_timeout"])

    def _open(self) -> ZenohTransport:
        registry = EndpointRegistry(self.run_dir)
        with registry.lock():
            known = sorted(set(registry.endpoints(self.neighbors).values()))
            tr = ZenohTransport(self.network, {self.name: self.neighbors},
                                ZenohConfig(connect=tuple(known), report_endpoints=True))
            try:
                registry.register(self.name, [self.name], bound_endpoints(tr.session)[0])
                # forged and garbage copies are dropped in Zenoh's callback, before they take queue space
                # (a flood could otherwise push genuine step frames out of the bounded queue)
                tr.set_check(self.name, self._check_on_arrival, _MAX_FRAME_BYTES)
            except BaseException:
                tr.close()
                raise
        return tr

    def _check_on_arrival(self, data: bytes) -> None:
        """A step frame of one of this node's links, or :class:`MessageError` (Zenoh's callback)."""
        body, tag = data[:-_TAG], data[-_TAG:]
        if len(data) > _TAG and any(hmac.compare_digest(tag, _frame_tag(self.key, self.network, self.run_id, j,
                                                                         self.name, body)) for j in self.neighbors):
            return
        err = MessageError("a step frame of no link of this node (its HMAC fails)")
        err.reason = "unauthenticated"
        raise err

    def _drain(self, tr: ZenohTransport) -> None:
        counts, detail = tr.take_rejections(self.name)   # dropped on arrival (_check_on_arrival): counted
        if counts:
            before = self.inbox.frames_rejected
            self.inbox.frames_rejected += sum(counts.values())
            if before < _LAG_LINES:
                log.warning("%s: %d copies rejected on arrival (%s)", self.name, sum(counts.values()), detail)
        for d in tr.receive(self.name):
            try:
                step, copies = decode_frame(self.key, self.network, self.run_id, d.src, self.name, d.data)
            except MessageError as exc:   # forged, corrupt or of another run: dropped, counted
                self.inbox.frames_rejected += 1
                if self.inbox.frames_rejected <= _LAG_LINES:
                    log.warning("%s: %s", self.name, exc)
                continue
            self.inbox.add(d.src, step, copies)

    def _wait_for(self, tr: ZenohTransport, k: int | None, what: str) -> None:
        """Wait until the frames needed at step ``k`` (``None``: every last frame) are here, at most
        ``lag_timeout`` seconds. A neighbour that lagged is not waited for again until its frames
        have caught up (a stalled but live neighbour costs one ``lag_timeout``, not one per step)."""
        deadline = time.monotonic() + self.lag_timeout
        while True:
            self._drain(tr)
            missing = self.inbox.missing(k)
            self.lagging &= set(missing)       # caught up: waited for again from now on
            if not missing:
                return
            gone = [j for j in missing if not tr.alive(j)]
            left = deadline - time.monotonic()
            if all(j in self.lagging for j in missing) and k is not None:
                return                         # only neighbours that lag already: go on at once
            if left <= 0 or len(gone) == len(missing):
                self.lagging |= set(missing)
                self.lags += 1
                if self.lags <= _LAG_LINES:
                    log.warning("%s: lag at %s: no frame from %s after %.1f s%s (the run is no longer identical "
                                "to simulate)", self.name, what, ", ".join(missing), self.lag_timeout - max(left, 0),
                                f"; {', '.join(gone)} not alive" if gone else "")
                return
            tr.wait(min(left, 0.5))

    def _wait_file(self, path: Path, timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while not path.exists():
            if time.monotonic() > end:
                raise DfusionError(f"{self.name}: {what} did not come within {timeout:g} s")
            if os.getppid() != self.launcher:
                raise DfusionError(f"{self.name}: the launcher is gone")
            time.sleep(0.02)

    def run(self) -> None:
        world = simulate_targets(self.sc)
        tr = self._open()
        try:
            end = time.monotonic() + float(self.cfg["startup_timeout"])
            while not all(tr.alive(j) for j in self.neighbors):
                if time.monotonic() > end:
                    raise DfusionError(f"{self.name}: neighbours {[j for j in self.neighbors if not tr.alive(j)]} "
                                       f"did not come up")
                tr.wait(0.1)
                tr.poll()
            _write(self.run_dir / "ready" / self.name, "")
            self._wait_file(self.run_dir / "start", float(self.cfg["startup_timeout"]), "the start")
            records = []
            times = world.times
            self.inbox.last = len(times) - 1
            for k, (t, batch) in enumerate(zip(times, frames_by_step(world))):
                t = float(t)
                for f in batch:
                    if f.node == self.name:
                        self.driver.frame(f)
                self._wait_for(tr, k, f"step {k} (t = {t:g} s)")
                sends = self.driver.step(t, self.inbox.take(t))
                copies: dict[str, list[tuple[float, int, bytes]]] = {j: [] for j in self.neighbors}
                for j, data in sends:
                    self.net.send(self.name, j, data, t)
                    for d in self.net.receive(j, math.inf):
                        copies[j].append((d.t_arrival, len(copies[j]), d.data))
                for j in self.neighbors:
                    tr.send(self.name, j, encode_frame(self.key, self.network, self.run_id, self.name, j, k,
                                                       copies[j]), t)
                if k:
                    records.append([t, [[tid.origin, tid.serial, m.tolist(), P.tolist()]
                                        for tid, m, P in self.node.estimates()]])
            self._wait_for(tr, None, "the end")   # every neighbour's last frame: what is in flight
            total = self.net.stats.total
            result = {"node": self.name, "stats": self.driver.stats(), "records": records, "lags": self.lags,
                      "frames_lost": self.inbox.frames_lost, "frames_rejected": self.inbox.frames_rejected,
                      "frames_repeated": self.inbox.frames_repeated,
                      "traffic": {"sent": int(total.sent), "duplicated": int(total.duplicated),
                                  "dropped": int(total.dropped), "delivered": self.inbox.delivered,
                                  "in_flight": len(self.inbox.pending)}}
            _write(self.run_dir / "results" / f"{self.name}.json", json.dumps(result))
            self._wait_file(self.run_dir / "finish", math.inf, "the launcher's finish")   # the launcher lives
        finally:
            tr.quiet_loss = True
            tr.close()


def _write(path: Path, text: str) -> None:
    """Write ``path`` atomically (write, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def _load(cfg: dict[str, Any]) -> Scenario:
    return load_scenario(cfg["scenario"], seed=cfg.get("seed"), duration=cfg.get("duration"),
                         plugins=cfg.get("plugins", []))


# ---------------------------------------------------------------------------- launcher
@dataclass
class TrackingRunOptions:
    """Options of :func:`run_tracking_processes` (the ``dfusion run`` flags that apply)."""

    scenario: str
    seed: int | None = None
    duration: float | None = None
    run_dir: str | None = None
    network: str | None = None
    network_key_file: str | None = None
    plugins: list[str] = field(default_factory=list)
    startup_timeout: float = 60.0
    lag_timeout: float = LAG_TIMEOUT
    keep_run_dir: bool = False
    python: str = sys.executable


class TrackingLauncher:
    """Starts the node processes of a multi-target run, waits for their results, builds the table."""

    def __init__(self, opts: TrackingRunOptions) -> None:
        self.opts = opts
        self.sc = load_scenario(opts.scenario, seed=opts.seed, duration=opts.duration, plugins=opts.plugins)
        if not self.sc.multi_target:
            raise DfusionError(f"{self.sc.path} is a single-target scenario: dfusion.run.launcher runs it")
        for name in self.sc.nodes:
            check_name(name)
        if not (opts.lag_timeout > 0 and math.isfinite(opts.lag_timeout)):
            raise DfusionError(f"the lag timeout must be a positive number of seconds, got {opts.lag_timeout}")
        self.run_id = new_run_id()
        self.network = opts.network or f"run{os.getpid()}x{self.run_id[:8]}"
        check_name(self.network, "network name")
        self._tmp = opts.run_dir is None
        self.run_dir = Path(opts.run_dir or tempfile.mkdtemp(prefix="dfusion-run-")).resolve()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}
        self.stop_reason: str | None = None
        self.failures: list[str] = []

    def request_stop(self, reason: str) -> None:
        """Stop the run (from a signal handler: only sets a flag)."""
        self.stop_reason = self.stop_reason or reason

    def _key_file(self) -> Path:
        given = self.opts.network_key_file or os.environ.get("DFUSION_NETWORK_KEY_FILE")
        if given:
            if load_network_key(given) is None:
                raise DfusionError(f"the network key file {given} is empty")
            return Path(given).resolve()
        path = self.run_dir / "network.key"
        if os.environ.get("DFUSION_NETWORK_KEY"):
            from dfusion.run.common import write_secret

            write_secret(path, load_network_key(None) + b"\n")
        else:
            generate_network_key(path)
        return path

    def _spawn(self) -> None:
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        for name in sorted(self.sc.nodes):
            cmd = child_command(self.opts.python, "dfusion.run.tracking",
                                ["--run-dir", str(self.run_dir), "--node", name])
            with (self.run_dir / "logs" / f"{name}.log").open("ab") as out:
                self.procs[name] = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out,
                                                    stderr=subprocess.STDOUT, env=env, start_new_session=True)
            log.info("node %s started (pid %d)", name, self.procs[name].pid)

    def _check_exits(self, results: Path) -> None:
        for name, p in self.procs.items():
            rc = p.poll()
            if rc is not None and not (results / f"{name}.json").exists():
                raise DfusionError(f"node process {name} (pid {p.pid}) {exit_reason(rc, False)} before its result "
                                   f"(multi-target nodes are not restarted; log: {self.run_dir / 'logs' / name}.log)")

    def _wait(self, what: str, done, timeout: float) -> None:
        end = time.monotonic() + timeout
        while not done():
            if self.stop_reason is not None:
                raise _Stopped(self.stop_reason)
            self._check_exits(self.run_dir / "results")
            if time.monotonic() > end:
                raise DfusionError(f"{what} did not happen within {timeout:g} s (logs: {self.run_dir / 'logs'})")
            time.sleep(0.02)

    def _stop_all(self) -> None:
        """SIGTERM every node's process group, SIGKILL after :data:`TERM_GRACE` seconds; reap them all."""
        live = [p for p in self.procs.values() if p.poll() is None]
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for p in live:
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    pass
            end = time.monotonic() + TERM_GRACE
            while time.monotonic() < end and any(p.poll() is None for p in live):
                time.sleep(0.02)
            live = [p for p in live if p.poll() is None]
            if not live:
                break
        for p in self.procs.values():
            p.wait()

    def run(self) -> TrackingResult | None:
        """Run the nodes; the result, or None when stopped by :meth:`request_stop`."""
        names = sorted(self.sc.nodes)
        results = self.run_dir / "results"
        ok = False
        try:
            key_file = self._key_file()
            _write(self.run_dir / "run.json", json.dumps({
                "scenario": str(Path(self.opts.scenario).resolve()), "seed": self.opts.seed,
                "duration": self.opts.duration, "plugins": list(self.opts.plugins), "network": self.network,
                "run_id": self.run_id, "key_file": str(key_file), "lag_timeout": self.opts.lag_timeout,
                "startup_timeout": self.opts.startup_timeout}))
            self._spawn()
            t0 = time.monotonic()
            self._wait("every node ready", lambda: all((self.run_dir / "ready" / n).exists() for n in names),
                       self.opts.startup_timeout)
            _write(self.run_dir / "start", str(time.time()))
            t1 = time.monotonic()
            self._wait("every node's result", lambda: all((results / f"{n}.json").exists() for n in names),
                       math.inf)
            wall = time.monotonic() - t1
            _write(self.run_dir / "finish", "")
            out = {n: json.loads((results / f"{n}.json").read_text()) for n in names}
            end = time.monotonic() + 10.0
            while any(p.poll() is None for p in self.procs.values()) and time.monotonic() < end:
                time.sleep(0.02)
            for n, p in self.procs.items():
                if p.poll() not in (0, None):
                    self.failures.append(f"node process {n} {exit_reason(p.returncode, True)} after its result")
            result = self._result(out, startup=t1 - t0, wall=wall)
            ok = True
            return result
        except _Stopped:
            return None
        finally:
            self._stop_all()
            if ok and self._tmp and not self.opts.keep_run_dir:
                shutil.rmtree(self.run_dir, ignore_errors=True)

    def _result(self, out: dict[str, dict[str, Any]], startup: float, wall: float) -> TrackingResult:
        sc = self.sc
        world = simulate_targets(sc)
        history = TrackHistory()
        for n, r in out.items():
            for t, rows in r["records"]:
                history.record(n, t, [(TrackId(o, s), np.asarray(m, float), np.asarray(P, float))
                                      for o, s, m, P in rows])
        cpu_central = run_central(sc, world, history)
        traffic = {k: sum(r["traffic"][k] for r in out.values())
                   for k in ("sent", "duplicated", "delivered", "dropped", "in_flight")}
        metrics = tracking_metrics(sc, world, history, {n: r["stats"] for n, r in out.items()}, traffic, cpu_central)
        lags = {n: r["lags"] for n, r in out.items()}
        metrics["run"] = {"processes": len(out), "network": self.network, "lockstep": True,
                          "lag_timeout": self.opts.lag_timeout, "lags": lags,
                          "frames_lost": {n: r["frames_lost"] for n, r in out.items()},
                          "frames_rejected": {n: r["frames_rejected"] for n, r in out.items()},
                          "startup_s": startup, "wall_s": wall, "failures": list(self.failures)}
        if any(lags.values()):
            log.warning("lockstep lags %s: the run is not identical to simulate", lags)
        return TrackingResult(sc, world, history, metrics)


class _Stopped(Exception):
    pass


def run_tracking_processes(opts: TrackingRunOptions) -> TrackingResult | None:
    """Run a multi-target scenario with one process per node; see :class:`TrackingLauncher`."""
    return TrackingLauncher(opts).run()


def history_difference(a: TrackHistory, b: TrackHistory, node: str) -> float:
    """The largest difference between two histories of ``node``: ``inf`` when the times or the track
    identities differ, else the largest ``|mean_a - mean_b|`` and ``|cov_a - cov_b|`` entry."""
    ra, rb = a.nodes.get(node, []), b.nodes.get(node, [])
    if len(ra) != len(rb):
        return math.inf
    worst = 0.0
    for (ta, xa), (tb, xb) in zip(ra, rb):
        if ta != tb or [e[0] for e in xa] != [e[0] for e in xb]:
            return math.inf
        for (_, ma, Pa), (_, mb, Pb) in zip(xa, xb):
            worst = max(worst, float(np.max(np.abs(ma - mb), initial=0.0)), float(np.max(np.abs(Pa - Pb), initial=0.0)))
    return worst


def compare_with_simulate(result: TrackingResult) -> str:
    """``dfusion run --compare``: ``simulate`` of the same scenario, and per node the metrics of both
    and the largest difference of the tracks over the run (:func:`history_difference`)."""
    from dfusion.sim.tracking_runner import run_tracking_scenario

    ref = run_tracking_scenario(result.scenario, world=result.world)
    lines = ["", "against dfusion simulate (same scenario and seed):",
             f"{'node':<12} {'GOSPA run':>10} {'GOSPA sim':>10} {'IDF1 run':>9} {'IDF1 sim':>9} {'sw. run':>8} "
             f"{'sw. sim':>8} {'max |track diff|':>17}"]
    for n, v in result.metrics["nodes"].items():
        r = ref.metrics["nodes"][n]
        diff = history_difference(result.history, ref.history, n)
        lines.append(f"{n:<12} {v['gospa']['mean']:10.4f} {r['gospa']['mean']:10.4f} {v['idf1']:9.4f} "
                     f"{r['idf1']:9.4f} {v['switches']:8d} {r['switches']:8d} "
                     f"{'other tracks' if math.isinf(diff) else f'{diff:.1e}':>17}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """A node process (started by :class:`TrackingLauncher`)."""
    p = argparse.ArgumentParser(prog="python -m dfusion.run.tracking",
                                description="one tracking node of a dfusion run (started by the launcher)")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--node", required=True)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {args.node} %(levelname)s %(name)s: %(message)s")
    try:
        _NodeProcess(Path(args.run_dir), args.node).run()
    except DfusionError as exc:
        log.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
