"""Three hosts on one machine (Linux network namespaces), a Zenoh router per host, mutual TLS.

Issue 25, item 3. Each host is a network namespace with one veth link (10.213.0.X/24) to a
bridge in a fourth namespace (the switch). Each host runs its site's router
(``python -m dfusion.run.router``, mutual TLS, connected to the routers of the sites before it)
and a host process of its nodes (``python -m dfusion.run.node_process --node A --node B --host
SITE --mode client --connect tls/ROUTER:7447``); host ``c`` also runs a relay node live, the
program of ``nodes/`` with a node file (``python nodes/relay.py cr.node.toml``), a client of the
same router: the deployment of ``docs/processes.md``, "Deployment on several hosts", on one
machine. During the run host ``c`` is cut off for 20 s
(``ip link set ... down`` on its veth) and brought back, and host ``b``'s process is SIGKILLed
and started again. Every node must end at the centralized estimate of the linear scenario,
computed here by filterpy's Kalman filter over every measurement the network took (those that
arrived while ``b`` was down are lost to everyone: the nodes report them), gaps <= 1e-9, never
more confident than it (nothing counted twice), and no process may be left behind.

Needs root and ``ip netns`` (CI runs as root); skipped with the reason otherwise. Traffic stays
inside the namespaces the test makes; they are deleted in a ``finally`` even on failure.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")
KalmanFilter = pytest.importorskip("filterpy.kalman").KalmanFilter

ROOT = Path(__file__).resolve().parents[2]
SUBNET = "10.213.0"
PORT = 7447
SITES = {"a": ("a1", "a2"), "b": ("b1", "b2"), "c": ("c1",)}   # host processes; host c also runs the live relay
RELAY = "cr"
START_AHEAD = 8.0                    # seconds from launching every process to the common start
CUT_AT, CUT_FOR = 2.0, 20.0          # host c off the network from scenario time 2 s to 22 s
KILL_AT, RESTART_AFTER = 6.0, 1.0    # host b SIGKILLed at 6 s, started again 1 s later
DURATION = 26.0

# A linear scenario (constant velocity, position sensors): the tree a1 - a2 - b1 - b2 and
# a2 - cr - c1 spans the three sites (cr: a relay without a sensor, run live by nodes/relay.py);
# the window (150 states of 0.2 s = 30 s) spans the run, so the 20 s cut is recovered exactly
# once the link is back.
SCENARIO = f"""
duration = {DURATION}
dt = 0.2
seed = 11
window = 150

[target]
motion = "constant_velocity"
q = 0.05
initial_mean = [0.0, 0.0, 1.0, 0.5]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]
""" + "".join(f"""
[[nodes]]
name = "{name}"
sensor = "position"
std = {std}
rate = 2.5
send_period = 0.4
""" for name, std in (("a1", 0.5), ("a2", 0.9), ("b1", 0.7), ("b2", 0.6), ("c1", 0.8))) + f"""
[[nodes]]
name = "{RELAY}"
sensor = "none"
send_period = 0.4
""" + "".join(f"""
[[links]]
between = ["{x}", "{y}"]
latency = 0.01
""" for x, y in (("a1", "a2"), ("a2", "b1"), ("b1", "b2"), ("a2", RELAY), (RELAY, "c1")))


def _ip(*args: str) -> None:
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")


def _why_not() -> str | None:
    """The reason this machine cannot run the test, or None."""
    if not sys.platform.startswith("linux"):
        return "needs Linux network namespaces"
    if os.geteuid() != 0:
        return "needs root to make network namespaces and veth links (CI runs as root)"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    if shutil.which("openssl") is None:
        return "needs the openssl command (test certificates)"
    probe = f"dfprobe{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except (RuntimeError, OSError) as exc:
        return f"ip netns is not available here: {exc}"
    try:
        _ip("netns", "del", probe)
    except RuntimeError:
        pass
    return None


@dataclass(frozen=True)
class Hosts:
    switch: str                 # the namespace of the bridge
    ns: dict[str, str]          # site -> its namespace
    addr: dict[str, str]        # site -> its address
    port: dict[str, str]        # site -> its veth on the bridge


@contextmanager
def hosts(sites) -> Iterator[Hosts]:
    """A namespace per site, each with a veth to a bridge in a switch namespace; all deleted at exit."""
    tag = f"dfh{os.getpid() % 100000}"
    made: list[str] = []
    try:
        switch = f"{tag}sw"
        _ip("netns", "add", switch)
        made.append(switch)
        _ip("-n", switch, "link", "set", "lo", "up")
        _ip("-n", switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", switch, "link", "set", "br0", "up")
        ns, addr, port = {}, {}, {}
        for i, site in enumerate(sites, 1):
            ns[site], addr[site], port[site] = f"{tag}{site}", f"{SUBNET}.{i}", f"v{site}"
            _ip("netns", "add", ns[site])
            made.append(ns[site])
            _ip("-n", ns[site], "link", "set", "lo", "up")
            _ip("-n", switch, "link", "add", port[site], "type", "veth", "peer", "name", "eth0", "netns", ns[site])
            _ip("-n", switch, "link", "set", port[site], "master", "br0", "up")
            _ip("-n", ns[site], "addr", "add", f"{addr[site]}/24", "dev", "eth0")
            _ip("-n", ns[site], "link", "set", "eth0", "up")
        yield Hosts(switch, ns, addr, port)
    finally:
        for name in reversed(made):
            pids = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True).stdout.split()
            for pid in pids:   # never expected (every process is stopped first): no namespace is left busy
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            subprocess.run(["ip", "netns", "del", name], capture_output=True)


def _liveliness_events(logs: Path):
    """``(node, "lost" | "is back", neighbour, UNIX time)`` of every liveliness line of the hosts' logs."""
    pattern = re.compile(r"^(\S+ \S+) \w+ (?:\[site-\w\] )?dfusion.transport.zenoh: (\w+): neighbour (\w+) (lost|is back)")
    for path in sorted([*logs.glob("host-*.log"), *logs.glob("relay-*.log")]):
        for line in path.read_text().splitlines():
            m = pattern.match(line)
            if m:
                when = datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()   # local time, as logged
                yield m[2], m[4], m[3], when


def central_estimate(sc, lost: set[tuple[str, float]]):
    """filterpy's Kalman filter over every measurement of the world but the lost ones, in time
    order, predicted to the end: the centralized estimate (closed-form constant-velocity F and Q,
    Bar-Shalom et al., "Estimation with Applications to Tracking and Navigation", 6.2.2)."""
    from dfusion.sim.world import simulate_world

    q = sc.target.motion.q

    def FQ(dt: float):
        F = np.eye(4)
        F[:2, 2:] = dt * np.eye(2)
        I = np.eye(2)
        return F, q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])

    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x = np.asarray(sc.target.initial_mean, float).reshape(4, 1)
    kf.P = np.asarray(sc.target.initial_cov, float).copy()
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    t_prev, used = 0.0, 0
    world = simulate_world(sc)
    for m in sorted(world.measurements, key=lambda m: m.t):
        if (m.node, round(m.t, 6)) in lost:
            continue
        if m.t > t_prev:
            kf.F, kf.Q = FQ(m.t - t_prev)
            kf.predict()
            t_prev = m.t
        kf.R = sc.nodes[m.node].sensor.R
        kf.update(np.asarray(m.z, float).reshape(2, 1))
        used += 1
    if sc.duration > t_prev:
        kf.F, kf.Q = FQ(sc.duration - t_prev)
        kf.predict()
    return kf.x.ravel(), kf.P, used, len(world.measurements)


def test_three_hosts_with_routers_and_mutual_tls_survive_a_cut_and_a_kill(tmp_path):
    reason = _why_not()
    if reason:
        pytest.skip(reason)
    from dfusion.run.certs import make_test_pki
    from dfusion.scenario import load_scenario

    scenario = tmp_path / "hosts.scenario.toml"
    scenario.write_text(SCENARIO)
    sc = load_scenario(scenario)
    key = tmp_path / "network.key"
    key.write_bytes(os.urandom(32))
    certs = tmp_path / "certs"
    procs: dict[str, subprocess.Popen] = {}
    every: list[subprocess.Popen] = []
    timeline: dict[str, float] = {}

    with hosts(SITES) as h:
        for site in SITES:   # one CA; each site's certificate valid for its address
            make_test_pki(certs, [site], hosts=[h.addr[site]])

        def spawn(what: str, site: str, args: list[str]) -> subprocess.Popen:
            log = open(tmp_path / f"{what}.log", "ab")
            run = args if args[0].endswith(".py") else ["-m", *args]
            p = subprocess.Popen(["ip", "netns", "exec", h.ns[site], sys.executable, *run],
                                 stdout=log, stderr=log, stdin=subprocess.DEVNULL,
                                 env={**os.environ, "PYTHONPATH": str(ROOT)})
            log.close()
            every.append(p)
            return p

        tls = lambda site: ["--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / f"{site}.pem"),  # noqa: E731
                            "--tls-key", str(certs / f"{site}.key")]
        router = {s: f"tls/{h.addr[s]}:{PORT}" for s in SITES}
        start = time.time() + START_AHEAD   # scenario time 0 on every host (one clock here; NTP across machines)

        def relay_file(h: Hosts) -> Path:
            """The live relay's node file (docs/ros.md, "Live use"): client of host c's router, mutual TLS."""
            path = tmp_path / f"{RELAY}.node.toml"
            path.write_text(f"""
name = "{RELAY}"
kind = "relay"
scenario = "{scenario}"
network = "hosts"
duration = {DURATION}
run_id = "hosts-test"
[zenoh]
mode = "client"
connect = ["{router['c']}"]
[security]
network_key_file = "{key}"
tls_ca = "{certs / 'ca.pem'}"
tls_cert = "{certs / 'c.pem'}"
tls_key = "{certs / 'c.key'}"
[ros]
latency = 0.0
[outputs]
""")
            return path

        def results_of(site: str) -> Path:   # a directory of NAME.json for several nodes, else the file
            nodes = SITES[site]
            return tmp_path / "results" if len(nodes) > 1 else tmp_path / "results" / f"{nodes[0]}.json"

        def host_process(site: str) -> subprocess.Popen:
            nodes = [x for n in SITES[site] for x in ("--node", n)]
            return spawn(f"host-{site}", site, [
                "dfusion.run.node_process", "--scenario", str(scenario), *nodes, "--host", f"site-{site}",
                "--network", "hosts", "--mode", "client", "--connect", router[site], *tls(site),
                "--network-key-file", str(key), "--run-id", "hosts-test", "--start-time", f"{start:.6f}",
                "--state-dir", str(tmp_path / f"state-{site}"), "--result", str(results_of(site)),
                "--parent-pid", str(os.getpid()), "--round-timeout", "5"])

        try:
            for site in SITES:   # each pair of routers linked once: a site connects to the sites before it
                others = [x for s in SITES if s < site for x in ("--connect", router[s])]
                procs[f"router-{site}"] = spawn(f"router-{site}", site, [
                    "dfusion.run.router", "--listen", router[site], *others, *tls(site),
                    "--parent-pid", str(os.getpid())])
            for site in SITES:
                procs[f"host-{site}"] = host_process(site)
            procs["relay-c"] = spawn("relay-c", "c", [str(ROOT / "nodes" / "relay.py"), str(relay_file(h)),
                                                     "--start-time", f"{start:.6f}",
                                                     "--result", str(tmp_path / "results" / f"{RELAY}.json")])

            def at(t: float) -> None:
                time.sleep(max(0.0, start + t - time.time()))

            at(CUT_AT)
            _ip("-n", h.switch, "link", "set", h.port["c"], "down")
            timeline["cut"] = time.time() - start
            at(KILL_AT)
            procs["host-b"].send_signal(signal.SIGKILL)
            procs["host-b"].wait(10)
            timeline["kill"] = time.time() - start
            at(KILL_AT + RESTART_AFTER)
            procs["host-b"] = host_process("b")
            timeline["restart"] = time.time() - start
            at(CUT_AT + CUT_FOR)
            _ip("-n", h.switch, "link", "set", h.port["c"], "up")
            timeline["back"] = time.time() - start
            for name in [f"host-{site}" for site in SITES] + ["relay-c"]:
                rc = procs[name].wait(DURATION + 60 - (time.time() - start))
                assert rc == 0, f"{name} exited with {rc}: {(tmp_path / f'{name}.log').read_text()[-3000:]}"
            timeline["finished"] = time.time() - start
            for site in SITES:
                procs[f"router-{site}"].send_signal(signal.SIGTERM)
            for site in SITES:
                assert procs[f"router-{site}"].wait(10) == 0
        finally:
            for p in every:
                if p.poll() is None:
                    p.kill()
                    p.wait()
        # no process left behind: every process the test started has exited, none is in a namespace
        assert all(p.poll() is not None for p in every)
        for name in (h.switch, *h.ns.values()):
            assert subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True).stdout.split() == []

    results = {n: json.loads((tmp_path / "results" / f"{n}.json").read_text()) for n in sc.nodes}
    lost = {(n, round(t, 6)) for n, r in results.items() for t in r["lost"]}
    mean, P, used, total = central_estimate(sc, lost)
    # the faults happened: b's nodes came back late and replayed their log, c's link was down for 20 s
    for n in SITES["b"]:
        assert results[n]["started"] >= KILL_AT and results[n]["stats"]["measurements_replayed"] > 0, results[n]
    assert timeline["back"] - timeline["cut"] >= CUT_FOR - 0.5, timeline
    assert results["a2"]["stats"]["skipped_not_alive"] > 0 and results[RELAY]["stats"]["skipped_not_alive"] > 0
    assert 0 < total - used < total / 10, (used, total)   # what arrived while b was down, nothing else
    gaps = {}
    for n, r in results.items():
        assert r["phase"] == "final" and r["t"] == pytest.approx(DURATION)
        m, C = np.asarray(r["mean"]), np.asarray(r["cov"])
        gaps[n] = max(np.abs(m - mean).max(), np.abs(C - P).max())
        # never more confident than the centralized filter (nothing double counted)
        assert np.linalg.eigvalsh(C - P).min() >= -1e-9, n
    # the cut was seen on both sides within the lease (3 s; 3 leases allowed), and healed once the link was back
    # the first event after the fault: a node that ends later also logs its neighbour lost at the end
    events = sorted(_liveliness_events(tmp_path), key=lambda e: e[3])
    first = lambda n, what, other, after: min(  # noqa: E731
        (t - start - after for x, w, o, t in events if (x, w, o) == (n, what, other) and t - start >= after - 0.5),
        default=float("inf"))
    lost_after = [first(x, "lost", y, timeline["cut"]) for x, y in (("a2", RELAY), (RELAY, "a2"))]
    back_after = [first(x, "is back", y, timeline["back"]) for x, y in (("a2", RELAY), (RELAY, "a2"))]
    assert max(lost_after) < 9.0 and max(back_after) < 9.0, (lost_after, back_after)
    print(f"hosts: timeline {timeline}; cut seen after {lost_after} s, healed {back_after} s after the link came "
          f"back; gaps {({n: f'{g:.1e}' for n, g in gaps.items()})}; measurements {used} of {total}")
    assert max(gaps.values()) <= 1e-9, gaps


def test_router_forwards_between_clients_with_mutual_tls_and_stops_cleanly(tmp_path):
    """``python -m dfusion.run.router`` on loopback (no root needed): two client sessions with
    certificates of the CA exchange a message through it (the first opened before the router
    answers: a client waits for its router); a session with another CA's certificate cannot
    connect; SIGTERM ends it with status 0; an endpoint it cannot bind is one line, status 2."""
    import socket
    import threading

    import zenoh

    from dfusion.transport.zenoh import TlsFiles, ZenohConfig, close_session, open_session
    from tests.helpers.pki import make_pki

    pki = make_pki(tmp_path, names=("router", "a", "b"))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tls/127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    router = subprocess.Popen([sys.executable, "-m", "dfusion.run.router", "--listen", ep, "--tls-dir", str(pki.dir),
                               "--parent-pid", str(os.getpid())], env=env, stderr=subprocess.PIPE, text=True)
    sessions = []
    try:
        got, arrived = [], threading.Event()
        a = open_session(ZenohConfig(mode="client", connect=(ep,), tls=pki.member("a")))
        sessions.append(a)
        a.declare_subscriber("dfusion/t/x", lambda sample: (got.append(sample.payload.to_bytes()), arrived.set()))
        b = open_session(ZenohConfig(mode="client", connect=(ep,), tls=pki.member("b")))
        sessions.append(b)
        deadline = time.monotonic() + 20
        while not arrived.wait(0.2):   # the clients connect in the background: publish until it arrives
            assert router.poll() is None, router.communicate()
            assert time.monotonic() < deadline, "nothing came through the router"
            b.put("dfusion/t/x", b"through the router")
        assert got[0] == b"through the router"
        # a certificate of another CA: the router refuses the connection, the client cannot open
        foreign = ZenohConfig(mode="client", connect=(ep,), client_wait_ms=1000,
                              tls=TlsFiles(str(pki.dir / "ca.pem"), str(pki.foreign / "x.pem"),
                                           str(pki.foreign / "x.key")))
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            sessions.append(open_session(foreign))
    finally:
        for s in sessions:
            close_session(s)
        router.send_signal(signal.SIGTERM)
        try:
            rc = router.wait(10)
        finally:
            if router.poll() is None:
                router.kill()
                router.wait()
    assert rc == 0, router.stderr.read()
    with socket.socket() as taken:   # a port someone holds
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        bad = subprocess.run([sys.executable, "-m", "dfusion.run.router", "--listen",
                              f"tcp/127.0.0.1:{taken.getsockname()[1]}"], env=env, capture_output=True, text=True,
                             timeout=30)
    errors = [line for line in bad.stderr.splitlines() if "ERROR" in line]
    assert bad.returncode == 2 and len(errors) == 1 and "cannot open the router" in errors[0], bad.stderr
