"""A chaos run: ``dfusion run`` of a dynamic linear scenario while a driver injects faults.

The driver generates a scenario (five position-sensor nodes on a graph with a cycle, a
constant-velocity target: linear, so every node must end at the centralized estimate; a
window longer than the run, so nothing leaves it), starts ``dfusion run`` on it as a
subprocess, and injects, on one seeded schedule (one fault at a time, a few seconds apart):

* **lapse**: a one-sided liveliness lapse: one end of a link sees it go down and up within a
  step, the other end sees nothing (``dfusion run --chaos-dir``: :mod:`dfusion.run.chaos`);
  and last, a **lapse round**: every node with a child in the tree lapses a child's link at
  once (no new tree epoch follows to repair what such a lapse breaks);
* **kill**: SIGKILL of a node's process group (the launcher's supervision restarts it);
* **kill+squat**: a kill, then at once a plain socket binds and listens on the port the node
  listened on (held until the run ends);
* **flap**: a link down then up, both ends (scripted in the scenario's ``[[events]]``);
* **flood**: ~1 MiB publications on the monitor's key space, sent to the launcher's monitor
  endpoint (``run.json``) for a few seconds;
* **squat before start** (once, first): as soon as the run directory names the nodes'
  endpoints, a plain socket binds and listens on one of them (held until the run ends).

All traffic stays on loopback. At the end it reads the run's JSON and prints one table: per
fault kind the driver's own count next to what the nodes or the launcher counted, every
node's final gap to the centralized estimate (the goal: <= 1e-9), the processes of the run
still alive and the ports of the run still bound after the launcher exited (the goal: none),
and the launcher's peak resident memory. The schedule depends only on ``--seed`` (and the
duration), the driver only injects between 8 s and ``duration - quiet``, at most
``--max-faults`` faults, and it stops the run after ``duration / speed + 240`` s whatever
happens.

Usage: python benchmarks/chaos.py [--minutes 10] [--seed 1] [--speed 1] [--json OUT] [--run-dir DIR]
       python benchmarks/chaos.py --short       # 40 scenario seconds at x2: the test's run (about 40 s)
Exit status 0 when every goal holds (exact, every fault counted, nothing left), else 1.
Run time: the duration / speed plus about 30 s. ``docs/chaos.md`` has the design and results.
"""
from __future__ import annotations

import argparse
import errno
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dfusion.run.chaos import lapse_path, request_lapse  # noqa: E402

#: Nodes of the generated scenario: (name, position std, measurement rate in Hz).
NODES = [("a", 0.8, 2.0), ("b", 0.6, 2.0), ("c", 1.0, 2.0), ("d", 0.7, 2.0), ("e", 0.9, 2.0)]
#: Links at the start: a - b - d - c - a is a cycle (the tree rule breaks it), d - e a leaf.
START_LINKS = [("a", "b"), ("a", "c"), ("b", "d"), ("c", "d"), ("d", "e")]
#: A link that comes up at :data:`JOIN_T` (a second cycle b - d - e - b): the links change whatever
#: the schedule, so the scenario is dynamic (every node runs the tree rule, the cycles are allowed).
LATE_LINK, JOIN_T = ("b", "e"), 2.0
#: The links a flap may take down (every link is up from :data:`JOIN_T` on).
LINKS = START_LINKS + [LATE_LINK]
#: Fault kinds and their weights in the schedule (the pre-start squat comes once, first).
KINDS = {"lapse": 4, "kill": 2, "kill+squat": 2, "flap": 2, "flood": 2}
FLOOD_SECONDS = 3.0
FLOOD_RATE = 100.0           # publications per second at most
FLOOD_BYTES = (1 << 20) - 1024   # just under the monitor's 1 MiB limit: queued, then checked
#: The short run's faults, in this order (the lapses last: nothing re-forms the tree after them).
SHORT_KINDS = ["kill+squat", "flap", "flood", "kill", "lapse", "lapse"]
DT = 0.5
MAX_KILLS_PER_NODE = 6
FIRST_FAULT = 8.0            # scenario seconds


@dataclass
class Fault:
    """One scheduled fault: scenario time, kind, target node (or link ``"a-b"``), and its draws."""

    t: float
    kind: str
    target: str
    pick: int = 0
    up_after: float = 0.0    # flap: seconds down
    done: bool = False
    outcome: str = ""


def schedule(seed: int, duration: float, quiet: float, gap: tuple[float, float], max_faults: int) -> list[Fault]:
    """The faults of a run: one at a time, ``gap`` scenario seconds apart (uniform), from
    :data:`FIRST_FAULT` to ``duration - quiet``, then a lapse round (at ``duration - quiet / 2``
    at the latest); a function of the arguments only."""
    rng = random.Random(seed)
    names = [n for n, _, _ in NODES]
    kinds, weights = zip(*KINDS.items())
    out: list[Fault] = []
    kills = {n: 0 for n in names}
    t = FIRST_FAULT
    while t < duration - quiet and len(out) < max_faults:
        kind = rng.choices(kinds, weights)[0]
        if kind == "flap":
            a, b = rng.choice(LINKS)
            out.append(Fault(round(t, 1), kind, f"{a}-{b}", up_after=round(rng.uniform(1.0, 4.0), 1)))
        else:
            node = rng.choice(names)
            if kind.startswith("kill"):
                if kills[node] >= MAX_KILLS_PER_NODE:
                    kind = "lapse"
                else:
                    kills[node] += 1
            out.append(Fault(round(t, 1), kind, node, pick=rng.randrange(1000)))
        t += rng.uniform(*gap)
        if out[-1].kind == "flap":
            t = max(t, out[-1].t + out[-1].up_after + 1.0)
    if len(out) < max_faults:   # the last: a lapse of a child's link at every node that has a child
        out.append(Fault(round(min(t, duration - quiet / 2), 1), "lapse-round", "*", pick=rng.randrange(1000)))
    return out


def scenario_toml(duration: float, faults: list[Fault], drop: float = 0.0) -> str:
    """The scenario: linear (constant velocity, position sensors), links with drops and latency,
    the flaps as ``[[events]]``, a window longer than the run."""
    steps = int(round(duration / DT))
    lines = [f"duration = {duration}", f"dt = {DT}", "seed = 5", f"window = {steps + 20}", 'fusion = "channel"', "",
             "[target]", 'motion = "constant_velocity"', "q = 0.05", "initial_mean = [0.0, 0.0, 1.0, 0.5]",
             "initial_cov_diag = [1.0, 1.0, 0.5, 0.5]", ""]
    for name, std, rate in NODES:
        lines += ["[[nodes]]", f'name = "{name}"', 'sensor = "position"', f"std = {std}", f"rate = {rate}",
                  "send_period = 0.5", ""]
    for a, b in START_LINKS:
        lines += ["[[links]]", f'between = ["{a}", "{b}"]', "latency = 0.05", f"drop = {drop}", ""]
    lines += ["[[events]]", f"t = {JOIN_T}", f'link_up = ["{LATE_LINK[0]}", "{LATE_LINK[1]}"]', ""]
    for f in faults:
        if f.kind == "flap":
            a, b = f.target.split("-")
            lines += ["[[events]]", f"t = {f.t}", f'link_down = ["{a}", "{b}"]', "",
                      "[[events]]", f"t = {round(f.t + f.up_after, 1)}", f'link_up = ["{a}", "{b}"]', ""]
    return "\n".join(lines)


# ---------------------------------------------------------------------- /proc
def _proc_stat(pid: int) -> tuple[int, str, int] | None:
    """(parent pid, state, start time in clock ticks) of ``pid``, or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    rest = text[text.rindex(")") + 2:].split()
    return int(rest[1]), rest[0], int(rest[19])


def _cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def descendants(root: int) -> dict[int, int]:
    """Every live descendant of ``root``: ``{pid: start time}``."""
    parent, start = {}, {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _proc_stat(int(d))
            if st is not None and st[1] != "Z":
                parent[int(d)], start[int(d)] = st[0], st[2]
    out, frontier = {}, [root]
    while frontier:
        p = frontier.pop()
        for c, pp in parent.items():
            if pp == p and c not in out:
                out[c] = start[c]
                frontier.append(c)
    return out


def alive(pid: int, start: int) -> bool:
    st = _proc_stat(pid)
    return st is not None and st[1] != "Z" and st[2] == start


def listening_sockets() -> dict[int, int]:
    """``{socket inode: port}`` of the TCP sockets in LISTEN state (IPv4 and IPv6)."""
    out = {}
    for f in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            for line in Path(f).read_text().splitlines()[1:]:
                cols = line.split()
                if cols[3] == "0A":
                    out[int(cols[9])] = int(cols[1].rsplit(":", 1)[1], 16)
        except OSError:
            pass
    return out


def pid_ports(pid: int, sockets: dict[int, int] | None = None) -> set[int]:
    """The TCP ports ``pid`` listens on (its open sockets in LISTEN state)."""
    sockets = listening_sockets() if sockets is None else sockets
    ports = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return ports
    for fd in fds:
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            port = sockets.get(int(link[8:-1]))
            if port is not None:
                ports.add(port)
    return ports


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def listen_port(cmd: list[str]) -> int | None:
    """The TCP port of a node command line's ``--listen tcp/HOST:PORT`` (None: none or port 0)."""
    for i, a in enumerate(cmd[:-1]):
        if a == "--listen":
            port = int(cmd[i + 1].rsplit(":", 1)[1])
            return port or None
    return None


def squat(port: int) -> socket.socket | None:
    """A plain socket bound to and listening on ``127.0.0.1:port``; None if the port is taken.

    ``SO_REUSEADDR``, as any server sets it: the port of a process killed a moment ago can then be
    taken although its closed connections linger (TIME_WAIT), as the node's own Zenoh could."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        s.bind(("127.0.0.1", port))
        s.listen(1)
        return s
    except OSError as exc:
        s.close()
        if exc.errno != errno.EADDRINUSE:
            raise
        return None


# ---------------------------------------------------------------------- the driver
@dataclass
class Counts:
    injected: dict[str, int] = field(default_factory=dict)
    squat_ports: list[int] = field(default_factory=list)
    squats_refused: int = 0
    lapses_withdrawn: int = 0
    kills_skipped: int = 0
    flood_bytes: int = 0
    launcher_rss_max_mb: float = 0.0

    def add(self, kind: str, n: int = 1) -> None:
        self.injected[kind] = self.injected.get(kind, 0) + n


class Driver:
    def __init__(self, args, run_dir: Path, faults: list[Fault]) -> None:
        self.args, self.run_dir, self.faults = args, run_dir, faults
        self.chaos_dir = run_dir / "chaos"
        self.counts = Counts()
        self.socks: list[socket.socket] = []
        self.seen: dict[int, int] = {}       # every process of the run: pid -> start time
        self.ports: set[int] = set()         # every port a process of the run listened on (command lines)
        self.launcher: subprocess.Popen | None = None
        self.start: float | None = None
        self.info: dict | None = None
        self._zsession = None
        self._next_scan = 0.0
        #: squatted ports that a process of the run listened on after the squat (sockets the squat
        #: holds are the driver's own, not the run's)
        self.ports_after_squat: set[int] = set()
        #: the squat before start: node, port, whether the port could be taken
        self.prestart: dict | None = None
        #: node -> the ports squatted right after its kills
        self.squatted_after_kill: dict[str, list[int]] = {}

    # -------------------------------------------------------------- the run
    def launch(self, scenario: Path, out_json: Path) -> None:
        self.chaos_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "dfusion", "run", str(scenario), "--speed", repr(self.args.speed),
               "--run-dir", str(self.run_dir), "--chaos-dir", str(self.chaos_dir), "--json", str(out_json), "-q",
               "--max-restarts", "20"]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        self.log = (self.run_dir.parent / "launcher.log").open("wb")
        self.launcher = subprocess.Popen(cmd, stdout=self.log, stderr=subprocess.STDOUT, env=env,
                                         start_new_session=True, cwd=str(ROOT))
        print("$ " + " ".join(cmd), flush=True)

    def watch(self) -> None:
        """Record the run's processes, their ports, the launcher's memory; read the start time."""
        scan = time.time() >= self._next_scan
        if scan:
            self._next_scan = time.time() + 0.5
            socks = listening_sockets()
            for pid, st in descendants(self.launcher.pid).items():
                if pid not in self.seen:
                    self.seen[pid] = st
                ports = pid_ports(pid, socks)
                self.ports |= ports
                if ports & set(self.counts.squat_ports) and pid != self.launcher.pid:
                    self.ports_after_squat |= ports & set(self.counts.squat_ports)
            self.ports |= pid_ports(self.launcher.pid, socks)
        self.counts.launcher_rss_max_mb = max(self.counts.launcher_rss_max_mb, rss_mb(self.launcher.pid))
        if self.info is None and (self.run_dir / "run.json").exists():
            try:
                self.info = json.loads((self.run_dir / "run.json").read_text())
            except ValueError:
                pass
        if self.start is None and (self.run_dir / "start").exists():
            try:
                self.start = float((self.run_dir / "start").read_text())
            except ValueError:
                pass

    def now(self) -> float:
        return -1e9 if self.start is None else (time.time() - self.start) * self.args.speed

    def pause(self, seconds: float) -> None:
        end = time.time() + seconds
        while time.time() < end and self.launcher.poll() is None:
            self.watch()
            time.sleep(0.05)

    def node_pid(self, name: str) -> int | None:
        try:
            pid = json.loads((self.run_dir / "pids.json").read_text()).get(name)
        except (OSError, ValueError):
            return None
        return pid if pid and _proc_stat(pid) is not None else None

    # -------------------------------------------------------------- faults
    def squat_before_start(self) -> None:
        """Bind one node's endpoint port the moment anything shows it (its command line, or its entry
        in the run directory's endpoint registry ``RUN_DIR/endpoints/NODE.json``), before the start."""
        target = random.Random(self.args.seed).choice([n for n, _, _ in NODES])
        deadline = time.time() + 60
        while self.start is None and time.time() < deadline and self.launcher.poll() is None:
            self.watch()
            port = None
            try:
                entry = json.loads((self.run_dir / "endpoints" / f"{target}.json").read_text())
                port = int(entry["endpoint"].rsplit(":", 1)[1]) or None
            except (OSError, ValueError, KeyError):
                pass
            if port is None and self.info is not None and target in self.info.get("endpoints", {}):
                port = int(self.info["endpoints"][target].rsplit(":", 1)[1]) or None   # ports chosen in advance
            pid = self.node_pid(target)
            port = port or (listen_port(_cmdline(pid)) if pid else None)
            if port is not None:
                self.prestart = {"node": target, "port": port, "taken": self._squat(port)}
                return
            time.sleep(0.005)
        self.prestart = {"node": target, "port": None, "taken": False}

    def _squat(self, port: int) -> bool:
        s = squat(port)
        if s is None:
            self.counts.squats_refused += 1
            print(f"  squat before start of port {port} refused: already bound (its node holds it)", flush=True)
            return False
        self.socks.append(s)
        self.counts.squat_ports.append(port)
        self.counts.add("squat")
        return True

    def inject(self, f: Fault) -> None:
        if f.kind == "flap":   # the scenario does it; the driver only counts it
            self.counts.add("flap")
            f.outcome = "scripted"
        elif f.kind == "lapse":
            self.lapse(f)
        elif f.kind == "lapse-round":
            self.lapse_round(f)
        elif f.kind.startswith("kill"):
            self.kill(f, squat_after=f.kind == "kill+squat")
        elif f.kind == "flood":
            self.flood(f)
        f.done = True

    def lapse(self, f: Fault) -> None:
        path = request_lapse(self.chaos_dir, f.target, f.pick)
        end = time.time() + 4.0
        while path.exists() and time.time() < end:
            self.pause(0.05)
        if path.exists():
            try:   # withdraw it: exactly one of the node (its read and unlink) and us wins the rename
                os.replace(path, path.with_suffix(".withdrawn"))
                self.counts.lapses_withdrawn += 1
                f.outcome = "withdrawn (node down or unlinked)"
                return
            except FileNotFoundError:
                pass
        self.counts.add("lapse")
        f.outcome = "applied"

    def lapse_round(self, f: Fault) -> None:
        """A lapse of a child's link requested of every node at once; withdrawn after 4 s where the
        node has no child."""
        paths = {n: request_lapse(self.chaos_dir, n, f.pick + i, child_only=True)
                 for i, (n, _, _) in enumerate(NODES)}
        end = time.time() + 4.0
        while any(p.exists() for p in paths.values()) and time.time() < end:
            self.pause(0.05)
        applied = []
        for n, path in paths.items():
            try:
                os.replace(path, path.with_suffix(".withdrawn"))
                self.counts.lapses_withdrawn += 1
            except FileNotFoundError:
                applied.append(n)
        self.counts.add("lapse", len(applied))
        f.outcome = f"applied at {','.join(applied) or 'none'} (the others have no child)"

    def kill(self, f: Fault, squat_after: bool) -> None:
        pid = self.node_pid(f.target)
        if pid is None:
            self.counts.kills_skipped += 1
            f.outcome = "skipped (not running)"
            return
        port = next(iter(sorted(pid_ports(pid))), None) or listen_port(_cmdline(pid))
        try:
            os.killpg(pid, signal.SIGKILL)
        except ProcessLookupError:
            self.counts.kills_skipped += 1
            f.outcome = "skipped (gone)"
            return
        self.counts.add("kill")
        f.outcome = f"pid {pid}"
        if squat_after and port is not None:
            t0 = time.time()
            while time.time() < t0 + 1.0:   # the port is free once the kernel closed the dead process's socket
                s = squat(port)
                if s is not None:
                    self.socks.append(s)
                    self.counts.squat_ports.append(port)
                    self.counts.add("squat")
                    self.squatted_after_kill.setdefault(f.target, []).append(port)
                    f.outcome += f", port {port} squatted"
                    break
                time.sleep(0.005)
            else:
                self.counts.squats_refused += 1
                f.outcome += f", port {port} not free"

    def flood(self, f: Fault) -> None:
        if self.info is None:
            f.outcome = "skipped (no run.json)"
            return
        import zenoh

        from dfusion.transport.zenoh import ZenohConfig, monitor_key, open_session

        if self._zsession is None:
            self._zsession = open_session(ZenohConfig(connect=(self.info["monitor_endpoint"],)))
        pub = self._zsession.declare_publisher(monitor_key(self.info["network"], f.target),
                                               congestion_control=zenoh.CongestionControl.BLOCK)
        t0 = time.time()
        while not pub.matching_status.matching and time.time() < t0 + 5.0:   # a put before the monitor's
            self.pause(0.02)                                                # subscription is known goes nowhere
        payload = random.Random(f.pick).randbytes(FLOOD_BYTES)
        sent, end = 0, time.time() + FLOOD_SECONDS
        while time.time() < end and self.launcher.poll() is None and pub.matching_status.matching:
            t0 = time.time()
            pub.put(payload)
            sent += 1
            self.watch()
            time.sleep(max(0.0, 1 / FLOOD_RATE - (time.time() - t0)))
        pub.undeclare()
        self.counts.add("flood", sent)
        self.counts.flood_bytes += sent * FLOOD_BYTES
        f.outcome = f"{sent} publications"

    def close(self) -> None:
        if self._zsession is not None:
            from dfusion.transport.zenoh import close_session

            close_session(self._zsession)
            self._zsession = None
        for s in self.socks:
            s.close()
        self.socks = []


def report(driver: Driver, faults: list[Fault], result: dict | None, leftover: list[int],
           ports_bound: list[int], rc: int | None) -> tuple[str, bool, list[dict]]:
    """The table, whether every goal holds, and the rows of the fault table."""
    c = driver.counts
    run = (result or {}).get("run", {})
    nodes = run.get("nodes", {})
    lapses = sum(v.get("chaos_lapses", 0) for v in nodes.values())
    sup = run.get("supervision", {})
    kills = sum(1 for e in sup.get("events", []) if e.get("reason") == "killed by SIGKILL")
    other_exits = [e.get("reason") for e in sup.get("events", []) if e.get("reason") != "killed by SIGKILL"]
    flood = sum(run.get("monitor_rejections", {}).values())
    changes = (result or {}).get("links", {}).get("changes", [])
    flaps_seen = 0
    for f in faults:
        if f.kind == "flap" and f.done:
            a, b = f.target.split("-")
            if any(f"{a} - {b} down" in row.get("what", []) and f.t - 1e-9 <= row["t"] <= f.t + 2.0
                   for row in changes):
                flaps_seen += 1
    # a squat is counted by the run when the node's endpoints (run.endpoints.hosts, in order) show the
    # squatted port and a later, fresh one: the restarted node listened elsewhere
    history = run.get("endpoints", {}).get("hosts", {})
    moved = 0
    for node, ports in driver.squatted_after_kill.items():
        used = [int(e.rsplit(":", 1)[1]) for e in history.get(node, [])]
        for p in ports:
            if p in used and used.index(p) < len(used) - 1 and p not in driver.ports_after_squat:
                moved += 1
    pre = driver.prestart or {}
    rows = [
        ("one-sided lapse", c.injected.get("lapse", 0), lapses, "sum of run.nodes.*.chaos_lapses"),
        ("SIGKILL", c.injected.get("kill", 0), kills, "run.supervision.events 'killed by SIGKILL'"),
        ("port squat after a kill", sum(map(len, driver.squatted_after_kill.values())), moved,
         "run.endpoints.hosts: the node's next endpoint is a fresh port"),
        ("link flap", c.injected.get("flap", 0), flaps_seen, "metrics.links.changes 'X - Y down'"),
        ("monitor flood (1 MiB)", c.injected.get("flood", 0), flood, "run.monitor_rejections (all reasons)"),
    ]
    gaps = {n: v.get("final_gap") for n, v in (result or {}).get("nodes", {}).items()}
    exact = bool(gaps) and all(g is not None and g <= 1e-9 for g in gaps.values())
    counted = all(d == r for _, d, r, _ in rows)
    clean = not leftover and not ports_bound
    lines = ["", f"| fault | injected (driver) | counted (run) | where counted |", "|---|---:|---:|---|"]
    lines += [f"| {k} | {d} | {r} | {w} |" for k, d, r, w in rows]
    if pre:
        lines += ["", f"squat before start: node {pre['node']}, port {pre['port']}: "
                  + ("TAKEN by the driver before the node bound it" if pre["taken"] else
                     "could not be taken (the node had bound it before anything showed it)"
                     if pre["port"] is not None else "no port shown before the start")]
    lines += ["", f"not injected: {c.lapses_withdrawn} lapse requests withdrawn (node down or without a link), "
              f"{c.kills_skipped} kills skipped (node not running), {c.squats_refused} squats refused (port bound)",
              f"other exits in run.supervision: {other_exits or 'none'}",
              f"flood: {c.flood_bytes / 2**20:.0f} MiB sent; launcher peak RSS {c.launcher_rss_max_mb:.0f} MB",
              "", "| node | incarnations | final gap | exact (<= 1e-9) |", "|---|---:|---:|---|"]
    for n, g in sorted(gaps.items()):
        inc = nodes.get(n, {}).get("incarnations", "?")
        lines.append(f"| {n} | {inc} | {g:.1e} | {'yes' if g is not None and g <= 1e-9 else 'NO'} |"
                     if g is not None else f"| {n} | {inc} | - | NO |")
    lines += ["", f"launcher exit status {rc}; processes of the run seen {len(driver.seen)}, still alive after it: "
              f"{leftover or 'none'}; ports of the run still bound: {ports_bound or 'none'}",
              f"goals: exact {'PASS' if exact else 'FAIL'}, every fault counted {'PASS' if counted else 'FAIL'}, "
              f"nothing left behind {'PASS' if clean else 'FAIL'}"]
    table = [{"fault": k, "injected": d, "counted": r, "where": w} for k, d, r, w in rows]
    return "\n".join(lines), exact and counted and clean and rc == 0, table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="wall minutes of the run proper (default 10)")
    ap.add_argument("--speed", type=float, default=1.0, help="scenario seconds per wall second (default 1)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the fault schedule (default 1)")
    ap.add_argument("--short", action="store_true", help="40 scenario seconds at x2 (the test's run)")
    ap.add_argument("--drop", type=float, default=0.0, help="drop probability of every link (default 0: lossless, where a one-sided lapse does the most harm)")
    ap.add_argument("--max-faults", type=int, default=200, help="faults at most (default 200)")
    ap.add_argument("--kinds", default=",".join([*KINDS, "squat"]),
                    help="fault kinds to inject, comma-separated (default all: " + ",".join([*KINDS, "squat"])
                    + "; squat is the squat before start); the others' slots stay empty (to find which kind breaks "
                    "a run)")
    ap.add_argument("--json", default=None, help="write the driver's counts, the schedule and the table here")
    ap.add_argument("--run-dir", default=None, help="keep everything here (default: a temporary directory)")
    args = ap.parse_args(argv)
    if args.short:
        args.minutes, args.speed = 40.0 / 2.0 / 60.0, 2.0
    duration = round(args.minutes * 60 * args.speed / DT) * DT
    quiet = 12.0 if args.short else 30.0
    gap = (2.5, 3.5) if args.short else (6.0, 12.0)
    faults = schedule(args.seed, duration, quiet, gap, args.max_faults)
    if args.short:   # every kind at least once, in a fixed order (no lapse round: the lapses come last)
        rng = random.Random(args.seed)
        for f, k in zip(faults, SHORT_KINDS):
            f.kind, f.target, f.pick, f.up_after = k, rng.choice([n for n, _, _ in NODES]), rng.randrange(1000), 0.0
            if k == "flap":
                a, b = rng.choice(LINKS)
                f.target, f.up_after = f"{a}-{b}", 2.0
        faults = faults[:len(SHORT_KINDS)]
    kinds = set(args.kinds.split(","))
    unknown = kinds - {*KINDS, "squat"}
    if unknown:
        ap.error(f"--kinds: unknown {sorted(unknown)}")
    faults = [f for f in faults if f.kind in kinds or (f.kind == "kill+squat" and "kill" in kinds)
              or (f.kind == "lapse-round" and "lapse" in kinds)]
    for f in faults:
        if f.kind == "kill+squat" and "kill+squat" not in kinds:
            f.kind = "kill"
    base = Path(args.run_dir or tempfile.mkdtemp(prefix="dfusion-chaos-")).resolve()
    base.mkdir(parents=True, exist_ok=True)
    scenario = base / "chaos.scenario.toml"
    scenario.write_text(scenario_toml(duration, faults, args.drop))
    out_json = base / "run.json"
    run_dir = base / "run"
    print(f"chaos run: seed {args.seed}, {duration:g} scenario s at x{args.speed:g}, {len(faults)} faults "
          f"({', '.join(f'{k} {sum(f.kind == k for f in faults)}' for k in [*KINDS, 'lapse-round'])}), in {base}",
          flush=True)
    driver = Driver(args, run_dir, faults)
    driver.launch(scenario, out_json)
    hard_end = time.time() + duration / args.speed + 240
    rc = None
    try:
        if "squat" in kinds:
            driver.squat_before_start()
        for f in faults:
            while driver.now() < f.t and driver.launcher.poll() is None and time.time() < hard_end:
                driver.watch()
                time.sleep(0.02)
            if driver.launcher.poll() is not None or time.time() >= hard_end:
                break
            driver.inject(f)
            print(f"  t={driver.now():7.1f} {f.kind:<10} {f.target:<4} {f.outcome}", flush=True)
        while driver.launcher.poll() is None and time.time() < hard_end:
            driver.watch()
            time.sleep(0.1)
        if driver.launcher.poll() is None:
            print("driver: the run did not end in time: stopping it", flush=True)
            os.killpg(driver.launcher.pid, signal.SIGTERM)
            try:
                driver.launcher.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(driver.launcher.pid, signal.SIGKILL)
                driver.launcher.wait()
        rc = driver.launcher.returncode
    finally:
        driver.close()
        if driver.launcher is not None and driver.launcher.poll() is None:
            os.killpg(driver.launcher.pid, signal.SIGKILL)
            driver.launcher.wait()
        for f in faults:
            for p in (lapse_path(driver.chaos_dir, f.target),):
                p.unlink(missing_ok=True)
    time.sleep(0.5)
    leftover = sorted(pid for pid, st in driver.seen.items() if alive(pid, st))
    ports = set(driver.ports)
    if driver.info is not None:
        ports |= {int(e.rsplit(":", 1)[1]) for e in [*driver.info.get("endpoints", {}).values(),
                                                     driver.info.get("monitor_endpoint", "x:0")]} - {0}
    ports_bound = sorted(ports & set(listening_sockets().values()))
    result = json.loads(out_json.read_text()) if out_json.exists() else None
    table, ok, rows = report(driver, faults, result, leftover, ports_bound, rc)
    print(table, flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({
            "seed": args.seed, "duration": duration, "speed": args.speed, "ok": ok, "table": table, "rows": rows,
            "counts": asdict(driver.counts), "faults": [asdict(f) for f in faults],
            "leftover": leftover, "ports_bound": ports_bound, "launcher_rc": rc,
            "final_gaps": {n: v.get("final_gap") for n, v in (result or {}).get("nodes", {}).items()},
        }, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
