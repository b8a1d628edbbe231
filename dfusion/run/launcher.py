"""``dfusion run``: one OS process per fusion node, a monitor, and the ``simulate`` table at the end.

The launcher

1. picks a free loopback port per node and a fresh network name, so that
   concurrent runs never see each other;
2. opens the :class:`~dfusion.run.monitor.Monitor` (connected to every node);
3. starts one ``python -m dfusion.run.node_process`` per node with
   ``subprocess.Popen(start_new_session=True)``: each node is the leader of its
   own process group, so the launcher can signal the whole group; each node also
   stops by itself when the launcher is no longer its parent (``--parent-pid``);
4. waits until every node reported ``ready`` (its neighbours are up), then
   writes the common start time to ``RUN_DIR/start`` (scenario time 0 is that
   UNIX time, on every node);
5. follows the run (progress bar on stderr when it is a terminal), kills and
   restarts nodes as asked (``--restart NAME@T[+D]``), and waits for every node
   to exit after its final phase;
6. builds the result from the nodes' final estimates (``RUN_DIR/results``) and
   the monitor's records (:func:`~dfusion.run.monitor.build_result`).

On SIGTERM or SIGINT (or any error) every node group gets SIGTERM, then SIGKILL
after :data:`TERM_GRACE` seconds: nothing is left behind within 2 s.

``RUN_DIR`` (``--run-dir``, default a temporary directory removed after a
successful run) holds ``logs/NAME.log`` (every incarnation's output),
``state/`` (the measurement logs), ``results/NAME.json``, ``pids.json`` and
``start``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from dfusion.errors import DfusionError
from dfusion.run.common import ROUND_TIMEOUT, Status, final_rounds, load_network_key
from dfusion.run.monitor import Monitor, build_result
from dfusion.scenario.loader import load_scenario
from dfusion.transport.zenoh import ZenohConfig, check_name, free_tcp_endpoints

log = logging.getLogger(__name__)

#: Seconds between SIGTERM and SIGKILL when stopping the nodes.
TERM_GRACE = 1.2
#: Seconds between the start time being written and scenario time 0.
START_MARGIN = 0.3
#: Launcher loop period (seconds).
TICK = 0.02

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
    """Options of :func:`run_processes` (the ``dfusion run`` flags)."""

    scenario: str
    seed: int | None = None
    fusion: str | None = None
    duration: float | None = None
    speed: float = 1.0
    run_dir: str | None = None
    network: str | None = None
    network_key_file: str | None = None
    restarts: list[Restart] = field(default_factory=list)
    emulate_links: bool = False
    round_timeout: float = ROUND_TIMEOUT
    progress: bool = False
    startup_timeout: float = 60.0
    keep_run_dir: bool = False
    python: str = sys.executable
    node_args: list[str] = field(default_factory=list)
    plugins: list[str] = field(default_factory=list)


@dataclass
class _Proc:
    name: str
    cmd: list[str]
    popen: subprocess.Popen | None = None
    incarnations: int = 0
    killed_by_us: bool = False
    exit_codes: list[int] = field(default_factory=list)


class Launcher:
    """Starts, follows and stops the node processes of one run (see the module docstring)."""

    def __init__(self, opts: RunOptions) -> None:
        if not (opts.speed > 0 and math.isfinite(opts.speed)):
            raise DfusionError(f"--speed must be a positive number, got {opts.speed}")
        self.opts = opts
        self.sc = load_scenario(opts.scenario, seed=opts.seed, fusion=opts.fusion, duration=opts.duration,
                                plugins=opts.plugins)
        for name in self.sc.nodes:
            check_name(name)
        for r in opts.restarts:
            if r.node not in self.sc.nodes:
                raise DfusionError(f"--restart: {r.node!r} is not a node of {self.sc.path}")
        self.key = load_network_key(opts.network_key_file)
        self.network = opts.network or f"run{os.getpid()}x{int(time.time() * 1000) % 10**8}"
        check_name(self.network, "network name")
        self._tmp = opts.run_dir is None
        self.run_dir = Path(opts.run_dir or tempfile.mkdtemp(prefix="dfusion-run-"))
        for sub in ("logs", "state", "results"):
            (self.run_dir / sub).mkdir(parents=True, exist_ok=True)
        for stale in [self.run_dir / "start", *self.run_dir.joinpath("results").glob("*.json")]:
            stale.unlink(missing_ok=True)
        self.rounds = final_rounds(self.sc)
        names = sorted(self.sc.nodes)
        self.endpoints = dict(zip(names, free_tcp_endpoints(len(names))))
        self.procs = {name: _Proc(name, self._command(name)) for name in names}
        self.monitor: Monitor | None = None
        self.start: float | None = None
        self.stop_reason: str | None = None
        self._pending = sorted(opts.restarts, key=lambda r: r.at)
        self._relaunch: list[tuple[float, str]] = []
        self.failures: list[str] = []

    # ------------------------------------------------------------------ commands and processes
    def _command(self, name: str) -> list[str]:
        o, sc = self.opts, self.sc
        cmd = [o.python, "-m", "dfusion.run.node_process", "--scenario", str(o.scenario), "--node", name,
               "--network", self.network, "--listen", self.endpoints[name],
               "--speed", repr(o.speed), "--start-file", str(self.run_dir / "start"),
               "--state-dir", str(self.run_dir / "state"), "--run-id", self.network,
               "--result", str(self.run_dir / "results" / f"{name}.json"), "--parent-pid", str(os.getpid()),
               "--round-timeout", repr(o.round_timeout)]
        for nb in sorted(sc.graph.neighbors(name)):
            cmd += ["--connect", self.endpoints[nb]]
        if o.seed is not None:
            cmd += ["--seed", str(o.seed)]
        if o.fusion is not None:
            cmd += ["--fusion", o.fusion]
        if o.duration is not None:
            cmd += ["--duration", repr(o.duration)]
        if o.network_key_file is not None:
            cmd += ["--network-key-file", str(Path(o.network_key_file).resolve())]
        if o.emulate_links:
            cmd.append("--emulate-links")
        for plugin in o.plugins:
            cmd += ["--plugin", _absolute_plugin(plugin)]
        return cmd + list(o.node_args)

    def _spawn(self, name: str) -> None:
        p = self.procs[name]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        with (self.run_dir / "logs" / f"{name}.log").open("ab") as out:
            out.write(f"--- incarnation {p.incarnations + 1} ---\n".encode())
            out.flush()
            p.popen = subprocess.Popen(p.cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                       env=env, start_new_session=True, cwd=os.getcwd())
        p.incarnations += 1
        p.killed_by_us = False
        log.info("node %s started (pid %d, incarnation %d)", name, p.popen.pid, p.incarnations)
        self._write_pids()

    def _write_pids(self) -> None:
        pids = {n: p.popen.pid for n, p in self.procs.items() if p.popen is not None}
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
        p = self.procs[name]
        if p.popen is not None and p.popen.poll() is None:
            p.killed_by_us = True
            self._signal_group(p.popen, signal.SIGKILL)
            p.popen.wait()
            log.warning("node %s killed (SIGKILL) at scenario time %.2f", name, self.now())

    def terminate(self, grace: float = TERM_GRACE) -> None:
        """SIGTERM every node group, SIGKILL what is left after ``grace`` seconds, reap everything."""
        live = [p.popen for p in self.procs.values() if p.popen is not None and p.popen.poll() is None]
        for pp in live:
            self._signal_group(pp, signal.SIGTERM)
        deadline = time.monotonic() + grace
        while any(pp.poll() is None for pp in live) and time.monotonic() < deadline:
            time.sleep(0.01)
        for pp in live:
            if pp.poll() is None:
                log.warning("node pid %d ignored SIGTERM: killing it", pp.pid)
            self._signal_group(pp, signal.SIGKILL)   # also any process the node may have left in its group
            try:
                pp.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                log.error("node pid %d did not die", pp.pid)

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

    def _check_exits(self) -> None:
        for name, p in self.procs.items():
            if p.popen is None or p.popen.returncode is not None:
                continue
            rc = p.popen.poll()
            if rc is None:
                continue
            p.exit_codes.append(rc)
            if rc != 0 and not p.killed_by_us:
                msg = f"node {name} exited with status {rc}"
                self.failures.append(msg)
                log.error("%s; its log ends with:\n%s", msg, self._log_tail(name))

    # ------------------------------------------------------------------ the run
    def run(self):
        """Launch, follow and finish the run; returns the result (``None`` if stopped)."""
        t_wall = time.monotonic()
        try:
            self.monitor = Monitor(self.sc, self.network, ZenohConfig(connect=tuple(self.endpoints.values())),
                                   network_key=self.key)
            for name in self.procs:
                self._spawn(name)
            if not self._wait_ready():
                return None
            self.start = time.time() + START_MARGIN
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
            extra = {
                "speed": self.opts.speed,
                "network": self.network,
                "wall_seconds": time.monotonic() - t_wall,
                "restarts": [f"{r.node}@{r.at}+{r.down}" for r in self.opts.restarts],
                "monitor_rejected": self.monitor.rejected,
                "failures": list(self.failures),
            }
            return build_result(self.sc, self.monitor.records, finals, extra=extra)
        finally:
            self.terminate()
            if self.monitor is not None:
                self.monitor.close()
            failed = self.failures or self.stop_reason is not None
            if self._tmp and not failed and not self.opts.keep_run_dir:
                shutil.rmtree(self.run_dir, ignore_errors=True)
            elif failed:
                log.warning("run directory (logs): %s", self.run_dir)

    def _wait_ready(self) -> bool:
        deadline = time.monotonic() + self.opts.startup_timeout
        while True:
            if self.stop_reason is not None:
                return False
            self._check_exits()
            if self.failures:
                raise DfusionError("; ".join(self.failures) + f" (logs in {self.run_dir / 'logs'})")
            ready = self.monitor.ready()
            if len(ready) == len(self.procs):
                return True
            if time.monotonic() > deadline:
                missing = sorted(set(self.procs) - ready)
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
            from tqdm import tqdm

            bar = tqdm(total=K - 1, unit="step", file=sys.stderr, leave=False, desc="dfusion run")
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
                    self._relaunch.append((r.at + r.down, r.node))
                for when, name in sorted(self._relaunch):
                    if t >= when:
                        self._relaunch.remove((when, name))
                        self._spawn(name)
                if bar is not None:
                    shown = (max(0, self.monitor.progress()), len(self.monitor.alive()))
                    if shown != (bar.n, getattr(bar, "_alive", None)):
                        bar.n, bar._alive = shown
                        bar.set_postfix_str(f"alive {shown[1]}/{len(self.procs)}", refresh=False)
                        bar.refresh()
                running = [p for p in self.procs.values() if p.popen is not None and p.popen.poll() is None]
                if not running and not self._relaunch and not self._pending:
                    return True
                if time.time() > deadline:
                    names = [p.name for p in running]
                    self.failures.append(f"nodes {names} still running {deadline - end_wall:.0f} s after the end")
                    raise DfusionError(self.failures[-1] + f" (logs in {self.run_dir / 'logs'})")
                time.sleep(TICK)
        finally:
            if bar is not None:
                bar.close()

    def _finals(self) -> dict[str, Status]:
        finals: dict[str, Status] = {}
        self.monitor.poll()
        for name in self.procs:
            path = self.run_dir / "results" / f"{name}.json"
            if path.exists():
                finals[name] = Status.from_json(json.loads(path.read_text()))
            elif self.monitor.records[name].final is not None:
                finals[name] = self.monitor.records[name].final
            else:
                log.warning("node %s published no final estimate", name)
        return finals


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
