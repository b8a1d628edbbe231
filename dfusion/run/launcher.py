"""``dfusion run``: one OS process per fusion node, a monitor, and the ``simulate`` table at the end.

The launcher

1. takes the run directory's lock (``RUN_DIR/launcher.lock``: its liveliness, see
   :mod:`dfusion.run.supervision`), picks a fresh network name and a random run
   identifier, so that concurrent runs never see each other, and a network key: the
   one given (``--network-key-file``, the scenario's ``[security]`` table or the
   environment) or a fresh random one, in ``RUN_DIR/network.key`` (mode 0600; never
   on a command line);
2. opens the :class:`~dfusion.run.monitor.Monitor` on a loopback port the kernel
   picks (over mutual TLS when TLS is on) and writes the endpoint it got to
   ``RUN_DIR/run.json``; no port is chosen in advance for any node: each binds its
   own, registers it in ``RUN_DIR/endpoints/`` and connects to the monitor and to its
   peers registered before it (:mod:`dfusion.run.endpoints`), so a port seen on a
   command line cannot be taken first, and a restarted node listens on a fresh port;
3. starts one ``python -m dfusion.run.node_process --run-dir RUN_DIR ...`` per node
   with ``subprocess.Popen(start_new_session=True)``: each node is the leader of its
   own process group, so the launcher can signal the whole group. The command line
   of each node is written to ``RUN_DIR/commands/NAME.sh``: run by hand, it restarts
   that node into the running run;
4. waits until every node reported ``ready`` (its neighbours are up), then
   writes the common start time to ``RUN_DIR/start`` (scenario time 0 is that
   UNIX time, on every node);
5. follows the run (progress on stderr: a bar on a terminal, else a line every 10 s and one at the end): restarts a
   node process that exits before its final estimate, after a backoff, at most
   ``max_restarts`` times per node (:class:`~dfusion.run.supervision.RestartPolicy`;
   ``--no-supervise`` turns it off); follows a node restarted by hand instead;
   kills and restarts nodes as asked (``--restart NAME@T[+D]``); and waits for
   every node to exit after its final phase;
6. builds the result from the nodes' final estimates (``RUN_DIR/results``) and
   the monitor's records (:func:`~dfusion.run.monitor.build_result`), with the
   restarts and their reasons in ``run.supervision``.

On SIGTERM or SIGINT (or any error) every node group gets SIGTERM, then SIGKILL
after :data:`TERM_GRACE` seconds: nothing is left behind within 2 s. If the
launcher itself is killed (SIGKILL), every node stops by itself: the kernel
sends it SIGTERM (parent-death signal) and its lock watch sees the launcher's
lock free.

``RUN_DIR`` (``--run-dir``, default a temporary directory removed after a
successful run) holds ``logs/NAME.log`` (every incarnation's output),
``state/`` (the measurement logs), ``results/NAME.json``, ``commands/NAME.sh``,
``locks/`` (one per node, held while it runs), ``endpoints/`` (where each node listens),
``launcher.lock``, ``endpoints.lock``,
``network.key``, ``run.json``, ``pids.json`` and ``start``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dfusion.errors import DfusionError
from dfusion.run.common import (
    ENV_KEY,
    ENV_KEY_FILE,
    ROUND_TIMEOUT,
    Status,
    final_rounds,
    generate_network_key,
    load_network_key,
    new_run_id,
    write_secret,
)
from dfusion.run.endpoints import EndpointRegistry, bound_endpoints
from dfusion.run.links import describe as describe_links
from dfusion.run.measurements import nodes_measurements, save_recording
from dfusion.scenario.security import SecurityOptions, security_options
from dfusion.run.monitor import Monitor, build_result
from dfusion.run.supervision import (
    EXIT_ALREADY_RUNNING,
    LAUNCHER_LOCK,
    FileLock,
    RestartPolicy,
    child_command,
    exit_reason,
    lock_holder,
    node_lock_path,
    pid_running,
)
from dfusion.scenario.links import peers
from dfusion.scenario.loader import load_scenario
from dfusion.transport.zenoh import ZenohConfig, check_name

log = logging.getLogger(__name__)

#: Seconds between SIGTERM and SIGKILL when stopping the nodes.
TERM_GRACE = 1.2
#: Seconds between the start time being written and scenario time 0.
START_MARGIN = 0.3
#: Launcher loop period (seconds).
TICK = 0.02
#: Seconds after the start, or after one was used, before a (new) warm standby process is started.
STANDBY_DELAY = 1.0

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Restart:
    """Kill ``node`` with SIGKILL at scenario time ``at`` and start it again ``down`` seconds later."""

    node: str
    at: float
    down: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Restart:
        """``NAME@T`` or ``NAME@T+D`` (scenario seconds)."""
        name, sep, when = text.partition("@")
        try:
            at, _, down = when.partition("+")
            r = cls(name, float(at), float(down) if down else 0.0)
        except ValueError:
            r = None
        if not sep or not name or r is None or r.at < 0 or r.down < 0:
            raise DfusionError(f"--restart needs NAME@T or NAME@T+D (seconds), got {text!r}")
        return r


@dataclass
class RunOptions:
    """Options of :func:`run_processes` (the ``dfusion run`` flags).

    ``security`` (command line) takes precedence over the scenario's ``[security]``
    table; ``network_key_file`` over both. ``emulate_links`` (default on) applies
    the scenario's links at the senders (:mod:`dfusion.run.links`).
    """

    scenario: str
    seed: int | None = None
    fusion: str | None = None
    duration: float | None = None
    speed: float = 1.0
    #: Override the scenario's ``sends`` ("event" or "periodic") and ``min_send_interval``.
    sends: str | None = None
    min_send_interval: float | None = None
    run_dir: str | None = None
    network: str | None = None
    network_key_file: str | None = None
    restarts: list[Restart] = field(default_factory=list)
    emulate_links: bool = True
    round_timeout: float = ROUND_TIMEOUT
    progress: bool = False
    startup_timeout: float = 60.0
    keep_run_dir: bool = False
    python: str = sys.executable
    node_args: list[str] = field(default_factory=list)
    plugins: list[str] = field(default_factory=list)
    security: SecurityOptions = field(default_factory=SecurityOptions)
    supervision: RestartPolicy = field(default_factory=RestartPolicy)
    #: Restart nodes from a warm standby process (imports done: about 0.1-0.3 s instead of 1-4 s).
    warm_restarts: bool = True
    #: Serve the nodes' estimates live to Foxglove on this WebSocket port (needs ``dfusion[live]``).
    foxglove: int | None = None
    #: Nodes per OS process (a host: one Zenoh session, one loop driving its nodes); 1: a process per node.
    nodes_per_process: int = 1
    #: Testing only: the nodes apply the one-sided link lapses a chaos driver requests in this
    #: directory (``dfusion.run.chaos``, ``docs/chaos.md``); None (the default): no such surface.
    chaos_dir: str | None = None


@dataclass
class _Proc:
    name: str                            # the host: its node's name when it runs one node
    cmd: list[str]
    nodes: list[str] = field(default_factory=list)
    popen: subprocess.Popen | None = None
    incarnations: int = 0
    killed_by_us: bool = False
    exit_seen: bool = False              # the exit of ``popen`` was handled by _check_exits
    exit_codes: list[int] = field(default_factory=list)
    started: float = 0.0                 # monotonic time of the last spawn
    restarts: int = 0                    # unplanned exits followed by a restart
    in_a_row: int = 0                    # quick failures in a row (backoff)
    restart_at: float | None = None      # monotonic time of a planned supervision restart
    gave_up: bool = False
    external: int | None = None          # pid of an incarnation started by hand, while it runs
    by_hand: int = 0                     # incarnations started by hand that the launcher followed
    waiting_back: dict | None = None     # the supervision event waiting for the new incarnation's first step


class Launcher:
    """Starts, follows, restarts and stops the node processes of one run (see the module docstring)."""

    def __init__(self, opts: RunOptions) -> None:
        if not (opts.speed > 0 and math.isfinite(opts.speed)):
            raise DfusionError(f"--speed must be a positive number, got {opts.speed}")
        self.opts = opts
        self.sc = load_scenario(opts.scenario, seed=opts.seed, fusion=opts.fusion, duration=opts.duration,
                                plugins=opts.plugins, sends=opts.sends, min_send_interval=opts.min_send_interval)
        if self.sc.multi_target:
            raise DfusionError(f"{self.sc.path}: dfusion run does not take multi-target scenarios ([[targets]]) yet; "
                               f"dfusion simulate runs them")
        for name in self.sc.nodes:
            check_name(name)
        if isinstance(opts.nodes_per_process, bool) or not isinstance(opts.nodes_per_process, int) \
                or opts.nodes_per_process < 1:
            raise DfusionError(f"--nodes-per-process must be a positive integer, got {opts.nodes_per_process!r}")
        #: host name -> its nodes; a host of one node is named after it
        self.hosts = host_groups(self.sc, opts.nodes_per_process)
        self.host_of = {n: h for h, nodes in self.hosts.items() for n in nodes}
        for r in opts.restarts:
            if r.node not in self.sc.nodes and r.node not in self.hosts:
                raise DfusionError(f"--restart: {r.node!r} is not a node of {self.sc.path}")
        self.security = opts.security.over(scenario_security(self.sc))
        self.policy = opts.supervision
        self.run_id = new_run_id()
        self.network = opts.network or f"run{os.getpid()}x{self.run_id[:8]}"
        check_name(self.network, "network name")
        self._tmp = opts.run_dir is None
        self.run_dir = Path(opts.run_dir or tempfile.mkdtemp(prefix="dfusion-run-")).resolve()
        self.key_file, self.key_source = self._key_file()
        self.key: bytes | None = None
        self.tls = self.security.tls_files("launcher")   # checks the launcher's files now
        for name in self.sc.nodes:
            self.security.tls_files(name)                 # and every node's
        self.rounds = final_rounds(self.sc)
        self.scheme = "tls" if self.tls is not None else "tcp"
        #: Where the nodes register the endpoints their sessions got (dfusion.run.endpoints).
        self.registry = EndpointRegistry(self.run_dir)
        #: where the launcher's monitor listens (in run.json; bound before it is written): a tool may connect to it
        self.monitor_endpoint: str | None = None
        #: host name -> every endpoint its incarnations listened on, in order (run.endpoints in the JSON)
        self.endpoint_history: dict[str, list[str]] = {h: [] for h in self.hosts}
        self._endpoints_due = 0.0
        self.procs = {h: _Proc(h, self._command(h), list(nodes)) for h, nodes in self.hosts.items()}
        self.world = None
        self.monitor: Monitor | None = None
        self.start: float | None = None
        self.stop_reason: str | None = None
        self._pending = sorted(opts.restarts, key=lambda r: r.at)
        self._relaunch: list[tuple[float, str]] = []
        self.failures: list[str] = []
        self.events: list[dict[str, Any]] = []
        self._lock: FileLock | None = None
        self.standby: subprocess.Popen | None = None
        self._standby_due: float | None = None
        #: Every process this launcher started (nodes and standbys), for the record and the tests.
        self.spawned: list[int] = []

    @property
    def endpoints(self) -> dict[str, str]:
        """``{node: endpoint}`` its host's session listens on now (registered nodes only)."""
        return self.registry.endpoints(sorted(self.host_of))

    @property
    def host_endpoints(self) -> dict[str, str]:
        """``{host: endpoint}`` of the registered hosts."""
        return {h: ep for h, ep in ((h, self.registry.endpoint(nodes[0])) for h, nodes in self.hosts.items())
                if ep is not None}

    def _note_endpoints(self, force: bool = False) -> None:
        """Add the hosts' newly registered endpoints to :attr:`endpoint_history` (every 0.5 s at most)."""
        now = time.monotonic()
        if not force and now < self._endpoints_due:
            return
        self._endpoints_due = now + 0.5
        for h, ep in self.host_endpoints.items():
            seen = self.endpoint_history[h]
            if not seen or seen[-1] != ep:
                seen.append(ep)
                if len(seen) > 1:
                    log.info("%s listens on a fresh endpoint %s (was %s)", _what(self.procs[h]), ep, seen[-2])

    # ------------------------------------------------------------------ security
    def _key_file(self) -> tuple[Path, str]:
        """Where the nodes read the network key, and where it comes from."""
        given = self.opts.network_key_file or self.security.network_key_file
        if given:
            return Path(given).resolve(), "given"
        if os.environ.get(ENV_KEY_FILE):
            return Path(os.environ[ENV_KEY_FILE]).resolve(), f"${ENV_KEY_FILE}"
        if os.environ.get(ENV_KEY):
            return self.run_dir / "network.key", f"${ENV_KEY}"
        return self.run_dir / "network.key", "generated"

    def _write_key(self) -> None:
        if self.key_source == "generated":
            self.key = generate_network_key(self.key_file)
        elif self.key_source == f"${ENV_KEY}":
            self.key = load_network_key(None)
            write_secret(self.key_file, self.key + b"\n")
        else:
            self.key = load_network_key(self.key_file)
        log.info("network key: %s (%s)", self.key_file, self.key_source)

    # ------------------------------------------------------------------ commands and processes
    def _command(self, host: str) -> list[str]:
        o = self.opts
        nodes = self.hosts[host]
        cmd = [o.python, "-m", "dfusion.run.node_process", "--scenario", str(Path(o.scenario).resolve())]
        for name in nodes:
            cmd += ["--node", name]
        if len(nodes) > 1:
            cmd += ["--host", host]
        # no --listen, no --connect: the node binds a port the kernel picks, connects to the monitor
        # (run.json) and to its peers registered so far, and registers its own (dfusion.run.endpoints)
        cmd += ["--run-dir", str(self.run_dir), "--network", self.network, "--run-id", self.run_id,
                "--speed", repr(o.speed), "--network-key-file",
                str(self.key_file), "--round-timeout", repr(o.round_timeout),
                "--measurements", str(self.run_dir / "measurements")]
        if o.seed is not None:
            cmd += ["--seed", str(o.seed)]
        if o.fusion is not None:
            cmd += ["--fusion", o.fusion]
        if o.duration is not None:
            cmd += ["--duration", repr(o.duration)]
        if o.sends is not None:
            cmd += ["--sends", o.sends]
        if o.min_send_interval is not None:
            cmd += ["--min-send-interval", repr(o.min_send_interval)]
        if o.emulate_links:
            cmd.append("--emulate-links")
        tls = self.security.tls_files(nodes[0])   # one session per host: its first node's certificate
        if tls is not None:
            cmd += ["--tls-ca", str(Path(tls.ca).resolve()), "--tls-cert", str(Path(tls.cert).resolve()),
                    "--tls-key", str(Path(tls.key).resolve())]
        for plugin in o.plugins:
            cmd += ["--plugin", _absolute_plugin(plugin)]
        if o.chaos_dir is not None:
            cmd += ["--chaos-dir", str(Path(o.chaos_dir).resolve())]
        return cmd + list(o.node_args)

    def _env(self) -> dict[str, str]:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        return env

    def _write_commands(self) -> None:
        """``RUN_DIR/commands/NAME.sh``: the command that (re)starts node NAME into this run."""
        d = self.run_dir / "commands"
        d.mkdir(exist_ok=True)
        pypath = self._env()["PYTHONPATH"]
        for name, p in self.procs.items():
            what = f"node {name}" if p.nodes == [name] else f"host {name} (nodes {', '.join(p.nodes)})"
            (d / f"{name}.sh").write_text(
                "#!/bin/sh\n"
                f"# {what} of run {self.run_id} (network {self.network}). Run this while dfusion run is\n"
                "# running to restart it by hand: it joins the run (it refuses to start when one of its nodes\n"
                "# already runs or the launcher is gone).\n"
                f"cd {shlex.quote(os.getcwd())} && PYTHONPATH={shlex.quote(pypath)} exec {shlex.join(p.cmd)}\n")

    def _spawn(self, name: str) -> None:
        p = self.procs[name]
        log_path = self.run_dir / "logs" / f"{name}.log"
        warm = self.standby is not None and self.standby.poll() is None
        with log_path.open("ab") as out:
            out.write(f"--- incarnation {p.incarnations + 1}{' (warm standby)' if warm else ''} ---\n".encode())
            out.flush()
            if warm:   # the standby becomes the node: same arguments, its imports already done
                sb, self.standby = self.standby, None
                try:
                    sb.stdin.write((json.dumps({"argv": p.cmd[3:], "log": str(log_path)}) + "\n").encode())
                    sb.stdin.close()
                    p.popen = sb
                except OSError:   # it died meanwhile: start cold
                    warm = False
                self._standby_due = time.monotonic() + STANDBY_DELAY
            if not warm:
                # close_fds (the default): the launcher's lock is not inherited, so it dies with the launcher
                cmd = child_command(p.cmd[0], p.cmd[2], p.cmd[3:])   # p.cmd, with the parent-death signal first
                p.popen = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                           env=self._env(), start_new_session=True, cwd=os.getcwd())
                self.spawned.append(p.popen.pid)
        p.incarnations += 1
        p.killed_by_us = False
        p.exit_seen = False
        p.started = time.monotonic()
        log.info("%s started (pid %d, incarnation %d%s)", _what(p), p.popen.pid, p.incarnations,
                 ", from the warm standby" if warm else "")
        self._write_pids()

    def _keep_standby(self) -> None:
        """Keep one warm standby process ready for the next restart (started when due)."""
        if not (self.opts.warm_restarts and self.policy.enabled) or self._standby_due is None:
            return
        if self.standby is not None and self.standby.poll() is None:
            return
        if self.standby is not None:   # it died: reap it, start another later
            log.warning("the warm standby process exited with status %s", self.standby.returncode)
            self.standby = None
            self._standby_due = time.monotonic() + STANDBY_DELAY
        if time.monotonic() < self._standby_due:
            return
        with (self.run_dir / "logs" / "standby.log").open("ab") as out:
            cmd = child_command(self.opts.python, "dfusion.run.node_process", ["--standby", str(self.run_dir)])
            self.standby = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=out,
                                            stderr=subprocess.STDOUT, env=self._env(), start_new_session=True,
                                            cwd=os.getcwd())
        self.spawned.append(self.standby.pid)
        self._write_pids()
        log.info("warm standby started (pid %d)", self.standby.pid)

    def _write_pids(self) -> None:
        pids = {n: p.popen.pid for n, p in self.procs.items() if p.popen is not None}
        pids.update({n: p.external for n, p in self.procs.items() if p.external is not None})
        if self.standby is not None:
            pids["standby"] = self.standby.pid
        pids["launcher"] = os.getpid()
        tmp = self.run_dir / "pids.json.tmp"
        tmp.write_text(json.dumps(pids))
        tmp.replace(self.run_dir / "pids.json")

    @staticmethod
    def _signal_group(p: subprocess.Popen, sig: int) -> None:
        try:
            os.killpg(p.pid, sig)   # start_new_session: the node leads its own group
        except (ProcessLookupError, PermissionError):
            pass

    def _kill(self, name: str) -> None:
        p = self.procs[self.host_of.get(name, name)]
        if p.popen is not None and p.popen.poll() is None:
            p.killed_by_us = True
            self._signal_group(p.popen, signal.SIGKILL)
            p.popen.wait()
            log.warning("%s killed (SIGKILL) at scenario time %.2f", _what(p), self.now())

    def _external_pids(self) -> list[int]:
        """Nodes started by hand that hold their lock now (not the launcher's children)."""
        mine = {p.popen.pid for p in self.procs.values() if p.popen is not None}
        out = []
        for name in self.host_of:
            pid = lock_holder(node_lock_path(self.run_dir, name))
            if pid is not None and pid > 0 and pid not in mine:
                out.append(pid)
        return out

    def terminate(self, grace: float = TERM_GRACE) -> None:
        """SIGTERM every node group (and node started by hand), SIGKILL what is left after ``grace``
        seconds, reap every child."""
        if self.standby is not None:
            self._signal_group(self.standby, signal.SIGKILL)   # it holds nothing: no need to be gentle
            self.standby.wait()
            self.standby = None
        live = [p.popen for p in self.procs.values() if p.popen is not None and p.popen.poll() is None]
        for pp in live:
            self._signal_group(pp, signal.SIGTERM)
        external = self._external_pids() if self._lock is not None else []
        for pid in external:
            _signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + grace
        while (any(pp.poll() is None for pp in live) or any(pid_running(pid) for pid in external)) \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        for pp in live:
            if pp.poll() is None:
                log.warning("node pid %d ignored SIGTERM: killing it", pp.pid)
            self._signal_group(pp, signal.SIGKILL)   # also any process the node may have left in its group
            try:
                pp.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                log.error("node pid %d did not die", pp.pid)
        for pid in external:
            if pid_running(pid):
                log.warning("node pid %d (started by hand) ignored SIGTERM: killing it", pid)
                _signal(pid, signal.SIGKILL)

    def request_stop(self, reason: str) -> None:
        """Ask :meth:`run` to stop (only sets a flag: safe in a signal handler)."""
        if self.stop_reason is None:
            self.stop_reason = reason

    def now(self) -> float:
        return -math.inf if self.start is None else (time.time() - self.start) * self.opts.speed

    def _log_tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.run_dir / "logs" / f"{name}.log").read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])

    def _finished(self, host: str) -> bool:
        return all((self.run_dir / "results" / f"{n}.json").exists() for n in self.procs[host].nodes)

    # ------------------------------------------------------------------ supervision
    def _check_exits(self) -> None:
        for name, p in self.procs.items():
            # not ``popen.returncode``: another look (``_running``, ``_supervise``, ``_kill``) may have
            # reaped the process first, and its exit must still be handled here, once
            if p.popen is None or p.exit_seen:
                continue
            rc = p.popen.poll()
            if rc is None:
                continue
            p.exit_seen = True
            p.exit_codes.append(rc)
            finished = self._finished(name)
            if p.killed_by_us or (rc == 0 and finished):
                continue
            if rc == EXIT_ALREADY_RUNNING:   # an incarnation started by hand holds the node's lock
                log.warning("%s: an incarnation started by hand runs: following it", _what(p))
                continue
            reason = exit_reason(rc, finished)
            if rc > 0:
                log.error("%s: %s; its log ends with:\n%s", _what(p), reason, self._log_tail(name))
            if self.start is None:   # before the run: a configuration error, restarting would not help
                self.failures.append(f"{_what(p)} {reason} before the start")
                continue
            self._plan_restart(p, reason)

    def _plan_restart(self, p: _Proc, reason: str) -> None:
        now = time.monotonic()
        event: dict[str, Any] = {"node": p.name, "t": round(self.now(), 3), "reason": reason,
                                 "restarted": False, "backoff_s": None, "back_after_s": None, "by_hand": False}
        if p.nodes != [p.name]:
            event["nodes"] = list(p.nodes)   # a host: all its nodes went, and come back together
        self.events.append(event)
        pol = self.policy
        if not pol.enabled or p.restarts >= pol.max_restarts:
            why = "supervision is off" if not pol.enabled else f"restart limit {pol.max_restarts} reached"
            p.gave_up = True
            log.error("%s %s at scenario time %.2f; not restarted (%s): restart it by hand with "
                      "sh %s", _what(p), reason, self.now(), why, self.run_dir / "commands" / f"{p.name}.sh")
            event["given_up"] = why
            p.waiting_back = event   # a restart by hand is still timed
            event["_exit"] = now
            event["_epochs"] = len(self.monitor.records[p.nodes[0]].epochs) if self.monitor is not None else 0
            return
        p.in_a_row = 1 if now - p.started >= pol.stable else p.in_a_row + 1
        delay = pol.delay(p.in_a_row)
        p.restart_at = now + delay
        event["backoff_s"] = round(delay, 3)
        event["_exit"] = now
        event["_epochs"] = len(self.monitor.records[p.nodes[0]].epochs) if self.monitor is not None else 0
        p.waiting_back = event
        log.warning("%s %s at scenario time %.2f: restarting it in %.2f s (restart %d of at most %d)",
                    _what(p), reason, self.now(), delay, p.restarts + 1, pol.max_restarts)

    def _supervise(self) -> None:
        """Planned restarts that are due; incarnations started by hand; the new incarnations' return."""
        now = time.monotonic()
        for name, p in self.procs.items():
            child_running = p.popen is not None and p.popen.poll() is None
            if not child_running:
                holder = lock_holder(node_lock_path(self.run_dir, p.nodes[0]))   # a host holds all its nodes' locks
                ext = holder if holder is not None and holder > 0 else None
                if ext is not None and ext != p.external:
                    p.by_hand += 1
                    p.restart_at = None
                    log.warning("%s: an incarnation started by hand runs (pid %d): following it", _what(p), ext)
                    if p.waiting_back is not None:
                        p.waiting_back["by_hand"] = True
                if ext != p.external:
                    p.external = ext
                    self._write_pids()
            if p.restart_at is not None and now >= p.restart_at and p.external is None:
                p.restart_at = None
                p.restarts += 1
                if p.waiting_back is not None:
                    p.waiting_back["restarted"] = True
                self._spawn(name)
            ev = p.waiting_back
            if ev is not None and self.monitor is not None:
                rec = self.monitor.records[p.nodes[0]]
                if len(rec.epochs) > ev["_epochs"] and rec.phase in ("run", "final"):
                    ev["back_after_s"] = round(now - ev["_exit"], 3)
                    p.waiting_back = None
                    log.warning("%s is back %.2f s after it went (scenario time %.2f)", _what(p),
                                ev["back_after_s"], self.now())

    def _running(self) -> list[str]:
        """Hosts still running, or whose exit is not handled yet (it may be restarted), or due to restart."""
        return [n for n, p in self.procs.items()
                if (p.popen is not None and (p.popen.poll() is None or not p.exit_seen)) or p.external is not None
                or p.restart_at is not None]

    # ------------------------------------------------------------------ the run
    def _prepare_run_dir(self) -> None:
        for sub in ("logs", "state", "results", "locks"):
            (self.run_dir / sub).mkdir(parents=True, exist_ok=True)
        self._lock = FileLock(self.run_dir / LAUNCHER_LOCK)
        if not self._lock.acquire():
            self._lock = None
            raise DfusionError(f"another dfusion run launcher works in {self.run_dir} "
                               f"(pid {lock_holder(self.run_dir / LAUNCHER_LOCK)})")
        for stale in [self.run_dir / "start", *self.run_dir.joinpath("results").glob("*.json")]:
            stale.unlink(missing_ok=True)
        for stale in self.registry.dir.glob("*.json") if self.registry.dir.exists() else ():
            stale.unlink(missing_ok=True)
        self._write_key()
        self._write_measurements()

    def _write_run_info(self) -> None:
        """``run.json`` (with the monitor's bound endpoint: written once the monitor listens) and the commands."""
        (self.run_dir / "run.json").write_text(json.dumps({
            "run_id": self.run_id, "network": self.network, "scenario": str(Path(self.opts.scenario).resolve()),
            "launcher_pid": os.getpid(), "speed": self.opts.speed,
            "endpoints_dir": str(self.registry.dir), "monitor_endpoint": self.monitor_endpoint,
            "hosts": self.hosts, "tls": self.tls is not None, "links_emulated": self.opts.emulate_links,
            "plugins": [_absolute_plugin(x) for x in self.opts.plugins],
        }, indent=1))
        self._write_commands()

    def _write_measurements(self) -> None:
        """The world of the scenario's seed, simulated once here: every node's measurements in
        ``RUN_DIR/measurements/NAME.jsonl`` (what the nodes fuse: they need not simulate it, nor import
        the simulator), and the monitor's reference at the end."""
        from dfusion.sim.world import simulate_world

        self.world = simulate_world(self.sc)
        d = self.run_dir / "measurements"
        d.mkdir(exist_ok=True)
        for name, meas in nodes_measurements(self.sc, self.world).items():
            save_recording(d / f"{name}.jsonl", name, meas)

    def run(self):
        """Launch, follow and finish the run; returns the result (``None`` if stopped)."""
        t_wall = time.monotonic()
        t_cpu = time.process_time()
        live = None
        try:
            self._prepare_run_dir()
            # the monitor binds a port the kernel picks, then the nodes learn it (run.json) and connect to it
            self.monitor = Monitor(self.sc, self.network,
                                   ZenohConfig(listen=(f"{self.scheme}/127.0.0.1:0",), tls=self.tls,
                                               report_endpoints=True),
                                   network_key=self.key, run=self.run_id)
            self.monitor_endpoint = bound_endpoints(self.monitor.session)[0]
            log.info("monitor listens on %s", self.monitor_endpoint)
            self._write_run_info()
            if self.opts.foxglove is not None:
                from dfusion.viz.foxglove import LiveView

                live = LiveView(self.sc, port=self.opts.foxglove, speed=0)
                self.monitor.listeners.append(live.node_estimate)
            for name in self.procs:
                self._spawn(name)
            if not self._wait_ready():
                return None
            self.start = time.time() + START_MARGIN
            self._standby_due = time.monotonic() + START_MARGIN + STANDBY_DELAY
            tmp = self.run_dir / "start.tmp"
            tmp.write_text(repr(self.start))
            tmp.replace(self.run_dir / "start")
            log.info("start time %.3f written; scenario of %.1f s at x%g", self.start, self.sc.duration, self.opts.speed)
            # the result needs the centralized EKF (filterpy, scipy.stats: seconds to import on a busy
            # machine): import it now, while the nodes run, not at the end
            threading.Thread(target=_preload, daemon=True).start()
            if not self._follow():
                return None
            finals = self._finals()
            for name in self.host_of:
                what = _what(self.procs[self.host_of[name]])
                if name not in finals and not any(f.startswith(f"{what} ") for f in self.failures):
                    self.failures.append(f"node {name} did not finish")
            extra = {
                "speed": self.opts.speed,
                "network": self.network,
                "run_id": self.run_id,
                "wall_seconds": time.monotonic() - t_wall,
                "restarts": [f"{r.node}@{r.at}+{r.down}" for r in self.opts.restarts],
                "monitor_rejected": self.monitor.rejected,
                "monitor_rejections": dict(self.monitor.rejections),
                # the monitor's pending queue: its bounds, its peak and what it shed (docs/processes.md)
                "monitor_queue": dict(self.monitor.queue),
                "failures": list(self.failures),
                "links_emulated": self.opts.emulate_links,
                # links that change: the [radio] table describes the links not in [[links]]
                "links": describe_links(self.opts.emulate_links, {**self.sc.links, ("", "radio"): self.sc.radio}
                                        if self.sc.dynamic else self.sc.links),
                "authenticated": self.key is not None,
                "network_key": self.key_source,
                "tls": self.tls is not None,
                "supervision": self.supervision_report(),
                "launcher_cpu_s": time.process_time() - t_cpu,
                "hosts": len(self.procs),
                # every endpoint each host's incarnations listened on (a restart gets a fresh one)
                "endpoints": self._endpoint_report(),
                "nodes_per_process": self.opts.nodes_per_process,
                "host_nodes": {h: list(p.nodes) for h, p in self.procs.items()},
            }
            return build_result(self.sc, self.monitor.records, finals, world=self.world, extra=extra)
        finally:
            self.terminate()
            if self.monitor is not None:
                self.monitor.close()
            if live is not None:
                live.close()
            if self._lock is not None:
                self._lock.release()
            failed = self.failures or self.stop_reason is not None
            if self._tmp and not failed and not self.opts.keep_run_dir:
                shutil.rmtree(self.run_dir, ignore_errors=True)
            elif failed:
                log.warning("run directory (logs): %s", self.run_dir)

    def _endpoint_report(self) -> dict[str, Any]:
        """``run.endpoints``: the monitor's endpoint, and per host every endpoint its incarnations listened on."""
        self._note_endpoints(force=True)
        return {"monitor": self.monitor_endpoint, "hosts": {h: list(v) for h, v in self.endpoint_history.items()},
                "fresh_endpoints": sum(max(0, len(v) - 1) for v in self.endpoint_history.values())}

    def supervision_report(self) -> dict[str, Any]:
        """``run.supervision``: the policy, and per node its restarts, their reasons and durations."""
        pol = self.policy
        nodes = {}
        for name, p in self.procs.items():
            evs = [e for e in self.events if e["node"] == name]
            nodes[name] = {
                "restarts": p.restarts,
                "started_by_hand": p.by_hand,
                "exits": [e["reason"] for e in evs],
                "gave_up": p.gave_up and p.by_hand == 0,
                "back_after_s": [e["back_after_s"] for e in evs if e["back_after_s"] is not None],
            }
        return {
            "enabled": pol.enabled, "max_restarts": pol.max_restarts, "backoff_s": [pol.backoff, pol.backoff_max],
            "nodes": nodes,
            "events": [{k: v for k, v in e.items() if not k.startswith("_")} for e in self.events],
        }

    def _wait_ready(self) -> bool:
        deadline = time.monotonic() + self.opts.startup_timeout
        while True:
            if self.stop_reason is not None:
                return False
            self._check_exits()
            if self.failures:
                raise DfusionError("; ".join(self.failures) + f" (logs in {self.run_dir / 'logs'})")
            ready = self.monitor.ready()
            if len(ready) == len(self.host_of):
                return True
            if time.monotonic() > deadline:
                missing = sorted(set(self.host_of) - ready)
                raise DfusionError(f"nodes not ready after {self.opts.startup_timeout:.0f} s: {missing} "
                                   f"(logs in {self.run_dir / 'logs'})")
            time.sleep(TICK)

    def _follow(self) -> bool:
        sc, o = self.sc, self.opts
        K = sc.steps + 1
        end_wall = self.start + sc.duration / o.speed
        deadline = end_wall + 20.0 + 0.2 * sc.duration / o.speed + self.rounds * o.round_timeout
        bar = None
        if o.progress:
            from dfusion.sim.runner import Progress

            bar = Progress(K - 1, desc="dfusion run")
        try:
            while True:
                if self.stop_reason is not None:
                    log.warning("stopping: %s", self.stop_reason)
                    return False
                self.monitor.poll()
                self._check_exits()
                t = self.now()
                while self._pending and t >= self._pending[0].at:
                    r = self._pending.pop(0)
                    self._kill(r.node)
                    self._relaunch.append((r.at + r.down, self.host_of.get(r.node, r.node)))
                for when, name in sorted(self._relaunch):
                    if t >= when:
                        self._relaunch.remove((when, name))
                        self._spawn(name)
                self._supervise()
                self._keep_standby()
                self._note_endpoints()
                if bar is not None:
                    alive = len(self.monitor.alive())
                    bar.update(max(0, self.monitor.progress()), f"alive {alive}/{len(self.host_of)}")
                running = self._running()
                if not running and not self._relaunch and not self._pending:
                    return True
                if time.time() > deadline:
                    self.failures.append(f"nodes {running} still running {deadline - end_wall:.0f} s after the end")
                    raise DfusionError(self.failures[-1] + f" (logs in {self.run_dir / 'logs'})")
                time.sleep(TICK)
        finally:
            if bar is not None:
                bar.close()

    def _finals(self) -> dict[str, Status]:
        finals: dict[str, Status] = {}
        self.monitor.poll()
        for name in sorted(self.host_of):
            path = self.run_dir / "results" / f"{name}.json"
            if path.exists():
                finals[name] = Status.from_json(json.loads(path.read_text()))
            elif self.monitor.records[name].final is not None:
                finals[name] = self.monitor.records[name].final
            else:
                log.warning("node %s published no final estimate", name)
        return finals


def host_groups(sc, per_process: int) -> dict[str, list[str]]:
    """The host processes of a run: ``{host: its nodes}``, at most ``per_process`` nodes each.

    One node per process: each host is named after its node. Otherwise the nodes are taken
    in depth-first order of the tree from the first name (so that a host holds neighbours,
    whose messages then stay inside its Zenoh session) and cut into ``ceil(n / per_process)``
    hosts whose sizes differ by at most one, named ``host0``, ``host1``, ... (a suffix is
    added if a node already has such a name).
    """
    names = sorted(sc.nodes)
    if per_process <= 1:
        return {n: [n] for n in names}
    order: list[str] = []
    seen: set[str] = set()
    for first in names:   # links that change may leave several components
        stack = [first]
        while stack:
            u = stack.pop()
            if u in seen:
                continue
            seen.add(u)
            order.append(u)
            stack.extend(sorted(set(peers(sc, u)) - seen, reverse=True))
    count = -(-len(order) // per_process)
    base, extra = divmod(len(order), count)
    prefix = "host"
    while any(n.startswith(prefix) for n in names):
        prefix += "_"
    hosts, i = {}, 0
    for h in range(count):
        size = base + (h < extra)
        hosts[f"{prefix}{h}"] = order[i:i + size]
        i += size
    return hosts


def _what(p: _Proc) -> str:
    """``node NAME``, or ``host NAME (nodes ...)`` for a process of several nodes."""
    return f"node {p.name}" if p.nodes == [p.name] else f"host {p.name} (nodes {', '.join(p.nodes)})"


def scenario_security(sc) -> SecurityOptions:
    """The scenario's ``[security]`` table as :class:`SecurityOptions` (empty options without one)."""
    parsed = getattr(sc, "security", None)
    if isinstance(parsed, SecurityOptions):
        return parsed
    raw = sc.raw.get("security") if isinstance(getattr(sc, "raw", None), dict) else None
    return security_options(raw, sc.base_dir)


def supervision_lines(result) -> str:
    """What ``dfusion run`` prints after the run table: links, security, restarts per node."""
    run = result.metrics.get("run", {})
    lines = []
    if "links" in run:
        lines.append(f"links: {run['links']}")
    if "authenticated" in run:
        sec = ["every message authenticated (network key " + str(run.get("network_key", "?")) + ")"
               if run["authenticated"] else "messages not authenticated"]
        sec.append("mutual TLS" if run.get("tls") else "no TLS (readable on the network)")
        lines.append("security: " + ", ".join(sec))
    sup = run.get("supervision")
    if sup:
        head = (f"supervision: on (at most {sup['max_restarts']} restarts per node, backoff "
                f"{sup['backoff_s'][0]:g}-{sup['backoff_s'][1]:g} s)" if sup["enabled"] else "supervision: off")
        lines.append(head)
        for name, v in sup["nodes"].items():
            if not (v["exits"] or v["started_by_hand"]):
                continue
            counts: dict[str, int] = {}
            for r in v["exits"]:
                counts[r] = counts.get(r, 0) + 1
            n = len(v["exits"])
            bits = [f"{n} unexpected exit{'s' if n != 1 else ''} ("
                    + ", ".join(f"{r} x{c}" for r, c in counts.items()) + ")", f"restarted {v['restarts']}x"]
            if v["started_by_hand"]:
                bits.append(f"started by hand {v['started_by_hand']}x")
            if v["back_after_s"]:
                lo, hi = min(v["back_after_s"]), max(v["back_after_s"])
                bits.append(f"back after {lo:.1f} s wall" if f"{lo:.1f}" == f"{hi:.1f}"
                            else f"back after {lo:.1f}-{hi:.1f} s wall")
            if v["gave_up"]:
                bits.append("given up")
            lines.append(f"  {name}: " + "; ".join(bits))
    return "\n".join(lines)


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _absolute_plugin(plugin: str) -> str:
    """A ``.py`` plug-in path made absolute (node processes may start elsewhere); module names as they are."""
    return str(Path(plugin).resolve()) if plugin.endswith(".py") else plugin


def _preload() -> None:
    try:
        import dfusion.sim.runner  # noqa: F401
    except Exception:  # the import is retried, and reported, when the result is built
        pass


def run_processes(opts: RunOptions):
    """Run a scenario with one process per node; see :class:`Launcher`."""
    return Launcher(opts).run()
