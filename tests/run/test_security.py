"""The security suite: a real ``dfusion run`` on loopback under attack by a stranger.

One run of the linear 3-node chain ``a - b - c`` with a network key (``Launcher`` in a
thread, every node a process). An attacker with its own Zenoh session, connected to
every node and to the launcher's monitor, listens to the run (no TLS: it hears every
message) and publishes, one kind after another, on the key of the link ``b -> a`` and
on the monitor's keys: garbage, truncated, bit-flipped, oversized, wrong-key, no-key
and forged-sender frames, replays (of this run, of ``b``'s previous incarnation after a
restart, of another run with the same key) and forged monitor publications. Every
kind must be rejected and counted by node ``a`` (its rejection counters by reason, as
published to the monitor) or by the monitor, no node may end elsewhere than on the
centralized estimate (final gaps <= 1e-9, the window spans the run), and no process may
die (the only exit is the planned restart of ``b``).

The flood test sends 100,000 garbage frames at node ``a`` from one publisher as fast as
it can (Zenoh's blocking congestion control: the receiver sets the pace) and measures
what it costs ``a``.

Run with ``-s`` to see the tables (they are also logged).
"""
from __future__ import annotations

import json
import logging
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from dfusion.fusion import FusionNode  # noqa: E402
from dfusion.run.common import Status  # noqa: E402
from dfusion.run.launcher import Launcher, RunOptions  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402
from dfusion.transport.zenoh import ZenohConfig, close_session, link_key, monitor_key, open_session  # noqa: E402
from dfusion.wire import FrameKey  # noqa: E402

from tests.run.test_processes import chain3  # noqa: E402

log = logging.getLogger(__name__)

#: Frames per kind (each waits for node a's next counters, published once a second).
N = 20
GAP = 1e-9


def _start(launcher: Launcher) -> tuple[threading.Thread, dict]:
    box: dict = {}
    thread = threading.Thread(target=lambda: box.setdefault("result", launcher.run()), daemon=True)
    thread.start()
    deadline = time.monotonic() + 90
    while launcher.start is None or launcher.now() < 0.3 or launcher.monitor is None:
        assert thread.is_alive(), "the launcher stopped early"
        assert time.monotonic() < deadline, "the run never started"
        time.sleep(0.02)
    return thread, box


class Attacker:
    """A Zenoh session connected to every node and to the monitor that records what it hears."""

    def __init__(self, launcher: Launcher) -> None:
        self.net = launcher.network
        self.muted = False
        self.heard: dict[str, list[tuple[float, bytes]]] = {"b/a": [], "b/c": [], "monitor/a": []}
        self.z = open_session(ZenohConfig(connect=tuple(launcher.host_endpoints.values())
                                          + (launcher.monitor_endpoint,)))
        self._subs = [
            self.z.declare_subscriber(link_key(self.net, "b", "a"), self._rec("b/a")),
            self.z.declare_subscriber(link_key(self.net, "b", "c"), self._rec("b/c")),
            self.z.declare_subscriber(monitor_key(self.net, "a"), self._rec("monitor/a")),
        ]
        self.pubs = {
            "b/a": self.z.declare_publisher(link_key(self.net, "b", "a"), congestion_control=zenoh.CongestionControl.BLOCK),
            "monitor/a": self.z.declare_publisher(monitor_key(self.net, "a"),
                                                  congestion_control=zenoh.CongestionControl.BLOCK),
            "monitor/c": self.z.declare_publisher(monitor_key(self.net, "c"),
                                                  congestion_control=zenoh.CongestionControl.BLOCK),
        }

    def _rec(self, what: str):
        def on(sample) -> None:
            if not self.muted:   # its own publications come back to it: stop listening before attacking
                self.heard[what].append((time.monotonic(), sample.payload.to_bytes()))
        return on

    def send(self, where: str, frames: list[bytes], pause: float = 0.005) -> int:
        for f in frames:
            self.pubs[where].put(f)
            if pause:
                time.sleep(pause)
        return len(frames)

    def close(self) -> None:
        close_session(self.z)


def _counters(launcher: Launcher, node: str) -> dict[str, int]:
    """Node ``node``'s rejection counters by reason (and duplicates), as its current incarnation
    last published them to the monitor."""
    rec = launcher.monitor.records[node]
    if not rec.epochs:
        return {}
    st = dict(rec.stats.get(rec.epochs[-1], {}))
    return {k: v for k, v in st.items() if (k.startswith("rejected_") and k != "rejected_on_arrival")
            or k == "duplicates"}


def _delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: v - before.get(k, 0) for k, v in after.items() if v - before.get(k, 0)}


def _wait_counted(launcher: Launcher, node: str, before: dict[str, int], expected: int,
                  timeout: float = 8.0) -> dict[str, int]:
    """Wait until ``expected`` more rejections/duplicates are published by ``node``; the change by reason."""
    deadline = time.monotonic() + timeout
    while True:
        d = _delta(_counters(launcher, node), before)
        if sum(d.values()) >= expected or time.monotonic() > deadline:
            return d
        time.sleep(0.05)


def _wait_monitor(launcher: Launcher, before: dict[str, int], expected: int, timeout: float = 5.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout
    while True:
        d = _delta(dict(launcher.monitor.rejections), before)
        if sum(d.values()) >= expected or time.monotonic() > deadline:
            return d
        time.sleep(0.02)


def _fake(sc, net: str, key: bytes | None, run: str, t: float) -> FusionNode:
    """A node that calls itself b, with an absurdly confident measurement 100 m off."""
    fake = FusionNode("b", ["a", "c"], sc.target.motion, window=400,
                      prior=(0.0, sc.target.initial_mean, sc.target.initial_cov),
                      network_key=key, network=net, run=run)
    fake.predict(t)
    fake.update(t, [100.0, -100.0], sc.nodes["b"].sensor)
    return fake


def _table(rows: list[tuple[str, str, int, dict[str, int]]], title: str) -> str:
    lines = [title, f"{'kind':<36} {'target':<8} {'sent':>5}  rejected and counted, by reason"]
    for kind, target, sent, got in rows:
        lines.append(f"{kind:<36} {target:<8} {sent:>5}  " + ", ".join(f"{r} {c}" for r, c in sorted(got.items())))
    return "\n".join(lines)


def test_a_stranger_is_rejected_and_counted_for_every_kind_of_attack(tmp_path):
    scenario = chain3(tmp_path, duration=30.0, window=400)   # the window spans the run: exact estimates
    sc = load_scenario(scenario)
    key = os.urandom(32).hex().encode()
    key_file = tmp_path / "network.key"
    key_file.write_bytes(key + b"\n")
    run_dir = tmp_path / "run"
    opts = RunOptions(scenario=str(scenario), speed=1.0, run_dir=str(run_dir), network_key_file=str(key_file))
    launcher = Launcher(opts)
    thread, box = _start(launcher)
    rng = random.Random(7)
    rows: list[tuple[str, str, int, dict[str, int]]] = []
    expected: dict[str, set[str]] = {}
    mon_rows: list[tuple[str, str, int, dict[str, int]]] = []
    mon_expected: dict[str, set[str]] = {}
    att = Attacker(launcher)
    net = launcher.network
    try:
        while len(att.heard["b/a"]) < 8 or len(att.heard["b/c"]) < 8 or len(att.heard["monitor/a"]) < N:
            assert thread.is_alive() and launcher.now() < 8.0, {k: len(v) for k, v in att.heard.items()}
            time.sleep(0.05)
        att.muted = True
        heard = {k: [f for _, f in v] for k, v in att.heard.items()}   # genuine frames only

        def n_of(frames: list[bytes]) -> list[bytes]:
            return [frames[i % len(frames)] for i in range(N)]

        def attack(kind: str, frames: list[bytes], reasons: set[str]) -> None:
            before = _counters(launcher, "a")
            sent = att.send("b/a", frames)
            got = _wait_counted(launcher, "a", before, sent)
            rows.append((kind, "node a", sent, got))
            expected[kind] = reasons

        genuine = n_of(heard["b/a"])
        attack("garbage", [os.urandom(rng.randint(1, 400)) for _ in range(N)],
               {"rejected_malformed", "rejected_version"})   # a random first byte may look like msgpack (v1)
        attack("truncated", [f[:rng.randint(1, len(f) - 1)] for f in genuine[:N]],
               {"rejected_corrupt", "rejected_malformed"})

        def flip(f: bytes) -> bytes:
            b = bytearray(f)
            i = rng.randrange(4, len(b) - 20)   # the body: the checksum must catch it
            b[i] ^= 1 << rng.randrange(8)
            return bytes(b)

        attack("bit-flipped", [flip(f) for f in genuine[:N]], {"rejected_corrupt"})
        attack("oversized (5 MiB)", [os.urandom(5 << 20) for _ in range(3)], {"rejected_oversized"})
        t = launcher.now()
        wrong = _fake(sc, net, os.urandom(32).hex().encode(), launcher.run_id, t)
        attack("wrong key", [wrong.message_to("a", sent_at=t) for _ in range(N)], {"rejected_unauthenticated"})
        nokey = _fake(sc, net, None, "", t)
        attack("no key", [nokey.message_to("a", sent_at=t) for _ in range(N)], {"rejected_unauthenticated"})
        other_run = _fake(sc, net, key, "another-run", t)   # the same network key, another run
        attack("replayed from another run", [other_run.message_to("a", sent_at=t) for _ in range(N)],
               {"rejected_unauthenticated"})
        # forged sender: b's genuine messages to c (valid MAC) published as b -> a
        attack("forged sender (b->c frames as b->a)", n_of(heard["b/c"]), {"rejected_misaddressed"})
        # replays of this run: b's genuine messages to a, applied seconds ago
        attack("replayed (same run)", n_of(heard["b/a"]), {"duplicates"})

        # forged monitor publications
        def forge(kind: str, where: str, frames: list[bytes], reasons: set[str]) -> None:
            before = dict(launcher.monitor.rejections)
            sent = att.send(where, frames)
            got = _wait_monitor(launcher, before, sent)
            mon_rows.append((kind, "monitor", sent, got))
            mon_expected[kind] = reasons

        rec = launcher.monitor.records["a"]
        k = max(rec.last_k, 1)
        fake_status = Status("a", rec.epochs[-1] + 1, "run", k, k * sc.dt, np.array([100.0, -100.0, 0.0, 0.0]),
                             np.eye(4) * 1e-6)
        forge("monitor: garbage", "monitor/a", [os.urandom(rng.randint(1, 300)) for _ in range(N)],
              {"malformed", "version"})
        forge("monitor: no key", "monitor/a", [fake_status.encode(None)] * N, {"unauthenticated"})
        forge("monitor: wrong key", "monitor/a",
              [fake_status.encode(FrameKey(os.urandom(32), net, launcher.run_id))] * N, {"unauthenticated"})
        forge("monitor: replayed from another run", "monitor/a",
              [fake_status.encode(FrameKey(key, net, "another-run"))] * N, {"unauthenticated"})
        forge("monitor: forged sender (a's as c's)", "monitor/c", n_of(heard["monitor/a"]),
              {"forged-sender"})

        # b's previous incarnation, replayed after b was SIGKILLed (here) and restarted (by the launcher)
        killed_at = launcher.now()
        assert killed_at < sc.duration - 8, f"the attacks took too long (scenario time {killed_at:.1f})"
        os.kill(launcher.procs["b"].popen.pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        b = launcher.monitor.records["b"]
        # back, and a has heard it: its new incarnation sent a few messages (to a and c), and a moved on
        while not (len(b.epochs) >= 2 and b.stats.get(b.epochs[-1], {}).get("messages_sent", 0) >= 4
                   and launcher.monitor.records["a"].last_k * sc.dt > launcher.now() - 0.5):
            assert thread.is_alive() and time.monotonic() < deadline, "b did not come back"
            time.sleep(0.05)
        time.sleep(0.5)
        attack("replayed (previous incarnation)", n_of(heard["b/a"]), {"rejected_previous-incarnation"})
        attacked_until = launcher.now()
        thread.join(timeout=90)
        assert not thread.is_alive()
    finally:
        att.close()
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    result = box["result"]
    assert result is not None
    m = result.metrics
    text = _table(rows, "security suite: frames published by a stranger on the link b -> a "
                        "(node a's counters as published to the monitor)")
    text += "\n" + _table(mon_rows, "forged monitor publications (the monitor's counters)")
    gaps = {n: v["final_gap"] for n, v in m["nodes"].items()}
    text += (f"\nfinal gaps to the centralized estimate: " + ", ".join(f"{n} {g:.1e}" for n, g in gaps.items())
             + f"; incarnations: " + ", ".join(f"{n} {v['incarnations']}" for n, v in m["run"]["nodes"].items())
             + f"; attacks until scenario time {attacked_until:.1f} of {sc.duration:.0f}")
    print("\n" + text)
    log.info("%s", text)
    for kind, target, sent, got in rows + mon_rows:
        want = (expected | mon_expected)[kind]
        assert sent > 0 and set(got) <= want and sum(got.values()) == sent, (kind, sent, got, want)
    assert m["run"]["monitor_rejected"] == sum(sent for _, _, sent, _ in mon_rows)
    for name, g in gaps.items():
        assert g <= GAP, (name, g)
    sup = m["run"]["supervision"]   # no process died but b, killed by the test, and restarted by the launcher
    assert [(e["node"], e["reason"], e["restarted"]) for e in sup["events"]] == [("b", "killed by SIGKILL", True)], sup
    assert {n: v["incarnations"] for n, v in m["run"]["nodes"].items()} == {"a": 1, "b": 2, "c": 1}
    on_arrival = m["run"]["nodes"]["a"]["rejected_on_arrival"]
    # everything but the misaddressed, duplicate and previous-incarnation frames is dropped in the callback
    assert on_arrival == sum(sum(v for r, v in got.items() if r not in (
        "rejected_misaddressed", "duplicates", "rejected_previous-incarnation")) for _, _, _, got in rows)
    assert m["traffic"]["rejected_on_arrival"] == on_arrival


#: The flooder: one Zenoh session, one publisher (blocking congestion control: as fast as the
#: receiver takes them), garbage without a DF header (malformed); prints its start and end
#: (time.monotonic, the same clock as the test's on Linux).
FLOODER = """
import sys, time, numpy as np, zenoh
from dfusion.transport.zenoh import ZenohConfig, open_session, close_session
endpoint, key, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
rng = np.random.default_rng(1)
frames = [b"\\0" + rng.bytes(int(k)) for k in rng.integers(16, 200, 1000)]
z = open_session(ZenohConfig(connect=(endpoint,)))
pub = z.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
time.sleep(1.0)
t0 = time.monotonic()
for i in range(n):
    pub.put(frames[i % 1000])
t1 = time.monotonic()
print(t0, t1, flush=True)
sys.stdin.read()   # keep the session (and what it still has to send) until the test is done
close_session(z)
"""


def test_a_flood_of_garbage_costs_a_node_little(tmp_path):
    """100,000 garbage frames at node a from one publisher, as fast as a takes them."""
    FLOOD = int(os.environ.get("DFUSION_FLOOD", "100000"))
    scenario = chain3(tmp_path, duration=30.0, window=400)
    sc = load_scenario(scenario)
    send_period = sc.nodes["b"].send_period
    run_dir = tmp_path / "run"
    launcher = Launcher(RunOptions(scenario=str(scenario), speed=1.0, run_dir=str(run_dir), keep_run_dir=True))
    thread, box = _start(launcher)
    samples: list[tuple[float, float, int, int]] = []   # wall, a's lag (s), a's messages received, a's rejected
    att = Attacker(launcher)
    stop = threading.Event()

    def watch() -> None:
        rec = launcher.monitor.records["a"]
        while not stop.is_set():
            st = rec.stats.get(rec.epochs[-1], {}) if rec.epochs else {}
            lag = launcher.now() - rec.last_k * sc.dt
            samples.append((time.monotonic(), lag, st.get("messages_received", 0), st.get("rejected_on_arrival", 0)))
            time.sleep(0.05)

    watcher = threading.Thread(target=watch, daemon=True)
    try:
        while launcher.now() < 3.0:
            assert thread.is_alive()
            time.sleep(0.05)
        watcher.start()
        # the flooder is a process of its own (in this one it would take the GIL from the launcher's monitor)
        flooder = subprocess.Popen([sys.executable, "-c", FLOODER, launcher.endpoints["a"],
                                    link_key(launcher.network, "b", "a"), str(FLOOD)],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = flooder.stdout.readline()
            assert line, flooder.communicate(timeout=10)
            t0, t1 = (float(x) for x in line.split())
            # the flood ends when a has taken the last frame (its counters, published once a second)
            deadline = time.monotonic() + 60
            while not samples or samples[-1][3] < FLOOD:
                assert time.monotonic() < deadline and thread.is_alive(), samples[-1:]
                time.sleep(0.02)
            t_end = samples[-1][0]
            lag_end = launcher.now() - launcher.monitor.records["a"].last_k * sc.dt
            time.sleep(1.5)
            lag_after = launcher.now() - launcher.monitor.records["a"].last_k * sc.dt
        finally:
            flooder.stdin.close()
            flooder.wait(timeout=10)
        stop.set()
        thread.join(timeout=90)
        assert not thread.is_alive()
    finally:
        stop.set()
        att.close()
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    result = box["result"]
    assert result is not None
    m = result.metrics
    a = m["run"]["nodes"]["a"]
    during = [s for s in samples if t0 <= s[0] <= t_end]
    received_during = (during[-1][2] - during[0][2]) if len(during) >= 2 else 0
    a_log = (run_dir / "logs" / "a.log").read_text()
    log_lines = len(a_log.splitlines())
    # the first rejection on a line of its own, then summary lines with the counts (rate-limited)
    summarized = sum(int(x.replace(",", "")) for x in re.findall(r"([\d,]+) messages rejected since", a_log))
    rate = FLOOD / (t1 - t0)
    worst_lag = max((s[1] for s in during), default=float("nan"))
    text = (f"flood: {FLOOD:,} garbage frames at node a, published in {t1 - t0:.2f} s ({rate:,.0f}/s, one "
            f"publisher process, blocking congestion control), all taken by a {t_end - t0:.2f} s after the first "
            f"(within the 1 s of its counters); a rejected {a['rejected_on_arrival']:,} on arrival ({a['rejections']}); "
            f"genuine messages fused by a during the flood: {received_during} (counters published once a second); "
            f"a's step lag: worst {worst_lag:.2f} s during the flood (publication latency included), "
            f"{lag_end:.2f} s when a had taken them all, {lag_after:.2f} s 1.5 s later (send period {send_period} s); "
            f"a's own largest lag behind its clock in the run {a['max_lag_wall_s']:.2f} s; a's log: {log_lines} lines; traffic: {m['traffic']['network']['delivered']} delivered, "
            f"{m['traffic']['rejected_on_arrival']:,} rejected on arrival (not delivered); final gap of a "
            f"{m['nodes']['a']['final_gap']:.1e}")
    print("\n" + text)
    log.info("%s", text)
    (tmp_path / "flood.json").write_text(json.dumps({"flood": FLOOD, "seconds": t1 - t0, "lag_end": lag_end}))
    assert a["rejected_on_arrival"] == FLOOD and a["rejections"] == {"malformed": FLOOD}
    assert received_during > 0
    assert lag_end < send_period and lag_after < send_period
    assert log_lines < 100
    assert a_log.count("rejected a message (malformed)") == 1 and summarized == FLOOD - 1, a_log
    assert m["traffic"]["rejected_on_arrival"] == FLOOD
    # forged traffic is not counted as delivered: every delivered copy is a genuine one
    delivered = m["traffic"]["network"]["delivered"]
    assert delivered <= m["messages"] and delivered == m["traffic"]["fused"] + m["traffic"]["rejected"] \
        + m["traffic"]["ignored"]
    assert m["traffic"]["rejected"] == 0
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= GAP, (name, v["final_gap"])
