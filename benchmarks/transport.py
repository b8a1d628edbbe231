"""dfusion over Zenoh between Python processes on loopback: latency, rate and message size.

All in one run (every figure from separate OS processes; latencies across
processes use ``time.monotonic``, i.e. Linux's system-wide CLOCK_MONOTONIC):

1. **Message bytes against the window length** (4-state target, one
   measurement per state): what a dfusion message weighs, the whole window (a
   node's first message to a neighbour) and in the steady state (the neighbour
   acknowledges what it received: the new block only).
2. **Raw Zenoh ping-pong** (the floor): this process puts a payload of the
   same size as a steady-state dfusion message, a second process echoes it from its
   subscriber callback; one-way = round trip / 2. Same session settings as
   dfusion (peer, loopback, express, DROP), and the same pause between
   messages as the per-hop measurement below: on a VM, a CPU idle for 10 ms
   runs the same code several times slower than a busy one (measured here:
   the in-process fusion work of a hop 5-7x, the raw one-way time 1.6x), so a
   floor measured at another pace is not the same floor. Both are measured at
   two paces: a busy link (a message every 3 ms) and an idle one (every 20 ms;
   a ``dfusion run`` node sends every 500 ms by default).
3. **dfusion per hop**: node ``a`` (this process) predicts, fuses a measurement,
   builds its message and sends it; node ``b`` (another process) wakes up,
   predicts to the sender's time if needed, fuses the message and reads its
   estimate. Latency = measurement at ``a`` to the changed estimate at ``b``,
   split into sender work, transit (put to the subscriber callback) and receiver
   work (callback to estimate). Then, as the protocol does, ``b`` answers with its
   own message (its acknowledgement of what it fused; outside the timed hop) and
   ``a`` fuses it before its next measurement, so ``a`` sends only what ``b`` has
   not acknowledged: the new block. Goal (issue 15): within 1.5 times the minimal hop
   (column ``hop/minimal``; the minimal hop's own sender and receiver work beside it);
   the earlier goal, within 3 times the raw one-way time at the same payload, is kept.
   The same hop is measured again with the consistency guard on both nodes
   (``GuardConfig()``, on in every scenario node), columns ``guard: ...``, with the
   receiver's guard counters (every message tested; measurements drawn from the nodes' own
   motion and sensor models, so the link stays healthy).
4. **End to end along a 5-node chain** (5 processes): a measurement at ``n1``
   until ``n5``'s estimate has it; each node forwards at once when a message
   changed its belief (event-driven relay), then acknowledges to the sender.
5. **Messages per second per link**: ``a`` predicts, fuses a measurement, builds
   and sends as fast as it can (fusing ``b``'s acknowledgements as they come);
   ``b`` receives, fuses and acknowledges as fast as it can. The link carries what
   the slower of the two sustains. (A node of ``dfusion run``
   sends one message per send period, 2 per second by default.)

Usage: python benchmarks/transport.py [--quick]
The machine is noisy (runs vary by up to 1.6x on a 2-core VM): compare ratios.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from dfusion.fusion import FusionNode, GuardConfig  # noqa: E402
from dfusion.models import ConstantVelocity, PositionSensor  # noqa: E402
from dfusion.transport.zenoh import free_tcp_endpoints, open_session, ZenohConfig, ZenohTransport  # noqa: E402

DT = 0.1
MOTION = ConstantVelocity(2, 0.1)
SENSOR = PositionSensor(2, 0.5)
PRIOR = (0.0, np.zeros(4), np.eye(4))
GOAL = 3.0
#: (name, pause between messages in seconds) for the raw floor and the per-hop latency alike.
PACES = (("busy", 0.003), ("idle", 0.020))


class Track:
    """A target that moves by the nodes' own motion model from their prior, measured with the
    sensor's noise (seeded): the consistency guard's test of every message passes as on a
    healthy network (false alarm 1e-3 per message), so a guarded link stays out of quarantine."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.t = PRIOR[0]
        self.x = self.rng.multivariate_normal(PRIOR[1], PRIOR[2])

    def z(self, t: float) -> np.ndarray:
        """The measurement at ``t`` (times in increasing order)."""
        dt = t - self.t
        if dt > 0:
            self.x = MOTION.F(dt) @ self.x + self.rng.multivariate_normal(np.zeros(4), MOTION.Q(dt))
            self.t = t
        return self.x[:2] + SENSOR.std * self.rng.normal(size=2)


def make_node(name: str, neighbors, window: int, fill: bool, guard: bool = False,
              track: Track | None = None) -> FusionNode:
    """A node whose window is full (with one measurement per state of ``track`` if ``fill``),
    with the consistency guard (``GuardConfig()``, as scenario nodes have it) if ``guard``."""
    node = FusionNode(name, neighbors, MOTION, window=window, prior=PRIOR, epoch=(hash(name) & 0xFFFF) + 1,
                      guard=GuardConfig() if guard else None)
    track = track or Track(len(name))
    for k in range(1, window + 1):
        node.predict(k * DT)
        if fill:
            node.update(k * DT, track.z(k * DT), SENSOR)
    return node


def stats_us(x) -> dict[str, float]:
    a = np.asarray(x, float) * 1e6
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "n": int(a.size)}


# ---------------------------------------------------------------------- child processes
def child(cfg: dict) -> None:
    role = cfg["role"]
    if role == "pong":
        return _pong(cfg)
    name, nbrs, W = cfg["name"], cfg["neighbors"], cfg["window"]
    minimal = MinimalHop(W, seed=1) if role == "minimal" else None   # a sink that runs the minimal hop
    node = None if minimal else make_node(name, nbrs, W, fill=cfg.get("fill", False), guard=cfg.get("guard", False))
    zc = ZenohConfig(listen=[cfg["listen"]], connect=cfg["connect"])
    with ZenohTransport(cfg["network"], {name: nbrs}, zc) as tr:
        print("ready", flush=True)   # the caller opens its own session after every child is ready
        out: dict = {"arrivals": {}, "done": []}
        stop = threading.Event()
        threading.Thread(target=lambda: (sys.stdin.readline(), stop.set(), tr.wake()), daemon=True).start()
        count = 0
        first = last = None
        tr.quiet_loss = True   # the others leave when the benchmark ends
        while not stop.is_set():
            if not tr.wait(0.05):
                continue
            for d in tr.receive(name):
                if minimal:
                    minimal.receive(d.data)
                    changed = 1
                else:
                    if d.t_sent > node.latest_time + 1e-9:
                        node.predict(d.t_sent)
                    changed = node.receive(d.data)
                    node.estimate()
                t1 = time.monotonic()
                count += 1
                first = first or t1
                last = t1
                if role in ("sink", "minimal"):
                    out["arrivals"][repr(d.t_sent)] = (d.t_arrival, t1)
                elif role == "relay" and changed:
                    for nb in nbrs:
                        if nb != d.src:
                            tr.send(name, nb, node.message_to(nb), d.t_sent)
                    if cfg.get("last"):
                        out["arrivals"][repr(d.t_sent)] = (d.t_arrival, t1)
                if node is not None and changed:   # the protocol's acknowledgement: a message back (after the timing)
                    tr.send(name, d.src, node.message_to(d.src), d.t_sent)
            if node is not None:
                node.settle()   # idle: the bookkeeping the messages left for later (FusionNode.settle)
        out.update(count=count, first=first, last=last, dropped=tr.stats.total.dropped,
                   guard=None if node is None or node.guard is None else node.guard.summary())
        print(json.dumps(out), flush=True)


def _pong(cfg: dict) -> None:
    z = open_session(ZenohConfig(listen=[cfg["listen"]], connect=cfg["connect"]))
    try:
        pub = z.declare_publisher(f"{cfg['network']}/pong", express=True)
        z.declare_subscriber(f"{cfg['network']}/ping", lambda s: pub.put(s.payload))
        print("ready", flush=True)
        sys.stdin.readline()
    finally:
        z.close()


class MinimalHop:
    """Both ends of the minimal hop (3b. in the module docstring), window ``W``: the sender's
    message carries the newest ``blocks`` blocks (a steady-state dfusion message: the new one)."""

    def __init__(self, W: int, seed: int = 0, blocks: int = 1) -> None:
        rng = np.random.default_rng(seed)
        self.n = n = 4
        self.total = rng.normal(size=(W, n, n))
        self.total_vec = rng.normal(size=(W, n))
        self.channel = rng.normal(size=(W, n, n))
        self.channel_vec = rng.normal(size=(W, n))
        self.times = np.arange(W) * DT
        self.H, self.Rinv, self.Lam = np.eye(2, n), 4.0 * np.eye(2), np.eye(n)
        self.P = np.eye(n)
        self.iu = np.triu_indices(n)
        self.blocks = blocks

    def send(self, z: np.ndarray) -> bytes:
        self.total[-1] += self.Lam
        self.total_vec[-1] += self.H.T @ (self.Rinv @ z)
        new = slice(-self.blocks, None)
        d, dv = self.total[new] - self.channel[new], self.total_vec[new] - self.channel_vec[new]
        return msgpack.packb({"src": "a", "dst": "b", "seq": 1, "times": self.times[new].tobytes(),
                              "info": d[:, self.iu[0], self.iu[1]].tobytes(), "vec": dv.tobytes()})

    def receive(self, data: bytes) -> np.ndarray:
        d = msgpack.unpackb(data)
        info, vec = np.frombuffer(d["info"]), np.frombuffer(d["vec"])
        if not (np.isfinite(info).all() and np.isfinite(vec).all()):
            raise ValueError("non-finite")
        return np.linalg.solve(self.P + np.eye(self.n), vec[-self.n:])


class Child:
    def __init__(self, cfg: dict) -> None:
        self.p = subprocess.Popen([sys.executable, __file__, "--child", json.dumps(cfg)], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, start_new_session=True)

    def ready(self, timeout: float = 60) -> None:
        line = self.p.stdout.readline().strip()
        if line != "ready":
            raise RuntimeError(f"child not ready: {line!r}")

    def finish(self) -> dict:
        self.p.stdin.write("stop\n")
        self.p.stdin.flush()
        out, _ = self.p.communicate(timeout=30)
        lines = [ln for ln in out.splitlines() if ln.strip()]
        return json.loads(lines[-1]) if lines else {}

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()


def with_children(cfgs, body):
    kids = [Child(c) for c in cfgs]
    try:
        for k in kids:
            k.ready()
        return body(kids)
    finally:
        for k in kids:
            k.kill()


# ---------------------------------------------------------------------- measurements
def message_sizes(windows) -> dict[int, tuple[int, int]]:
    """Per window: (bytes of the whole window, bytes in the steady state: the new block, acknowledged)."""
    out = {}
    for W in windows:
        a = make_node("a", ["b"], W, fill=True)
        b = FusionNode("b", ["a"], MOTION, window=W, prior=PRIOR, epoch=7)
        full = a.message_to("b")
        b.predict(a.latest_time)
        b.receive(full)
        a.receive(b.message_to("a"))   # b acknowledges
        t = round((W + 1) * DT, 9)
        a.predict(t)
        a.update(t, np.ones(2), SENSOR)
        out[W] = (len(full), len(a.message_to("b")))
    return out


def drain(tr: ZenohTransport, node: FusionNode) -> None:
    """Fuse what arrived for ``node`` (its neighbours' acknowledgements)."""
    for d in tr.receive(node.name):
        node.receive(d.data)


def raw_pingpong(size: int, n: int, pause: float) -> dict:
    net = f"bench{os.getpid()}"
    ea, eb = free_tcp_endpoints(2)

    def body(kids):
        z = open_session(ZenohConfig(listen=[ea], connect=[eb]))
        try:
            got = threading.Event()
            z.declare_subscriber(f"{net}/pong", lambda s: got.set())
            pub = z.declare_publisher(f"{net}/ping", express=True)
            payload = bytes(size)
            deadline = time.monotonic() + 10
            while not got.is_set():   # until the link is up
                pub.put(payload)
                got.wait(0.05)
                if time.monotonic() > deadline:
                    raise RuntimeError("no pong")
            rtts = []
            for i in range(n + 20):
                got.clear()
                t0 = time.monotonic()
                pub.put(payload)
                if not got.wait(2.0):
                    continue
                if i >= 20:
                    rtts.append(time.monotonic() - t0)
                time.sleep(pause)
            return stats_us(np.array(rtts) / 2)
        finally:
            z.close()

    return with_children([{"role": "pong", "network": net, "listen": eb, "connect": [ea]}], body)


def per_hop(W: int, n: int, pause: float, minimal: bool = False, guard: bool = False) -> dict:
    """dfusion's hop (3.), or with ``minimal`` the minimal hop (3b.), from this process to a child;
    ``guard``: both nodes with the consistency guard (``GuardConfig()``, as in scenarios)."""
    net = f"hop{os.getpid()}w{W}{'m' if minimal else ''}{'g' if guard else ''}"
    ea, eb = free_tcp_endpoints(2)
    track = Track(1)
    a = MinimalHop(W) if minimal else make_node("a", ["b"], W, fill=True, guard=guard, track=track)

    def body(kids):
        t0s, tsend = {}, {}
        with ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea], connect=[eb])) as tr:
            while not tr.alive("b"):
                tr.wait(0.01)
            for i in range(n + 10):
                t = round((W + 1 + i) * DT, 9)
                z = track.z(t)
                if not minimal:
                    drain(tr, a)   # b's acknowledgements, before the timed hop
                t0 = time.monotonic()
                if minimal:
                    data = a.send(z)
                else:
                    a.predict(t)
                    a.update(t, z, SENSOR)
                    data = a.message_to("b", sent_at=t)
                t_put = time.monotonic()
                tr.send("a", "b", data, t)
                t0s[repr(t)], tsend[repr(t)] = t0, t_put
                time.sleep(pause)
                if not minimal:   # idle, after the hop (not beside its transit on 2 cores): the bookkeeping
                    a.settle()    # the message left for later (FusionNode.settle)
            time.sleep(0.3)
            res = kids[0].finish()
        arr = res["arrivals"]
        keys = [k for k in list(t0s)[10:] if k in arr]
        total = [arr[k][1] - t0s[k] for k in keys]
        send = [tsend[k] - t0s[k] for k in keys]
        transit = [arr[k][0] - tsend[k] for k in keys]
        recv = [arr[k][1] - arr[k][0] for k in keys]
        return {"bytes": len(data), "total": stats_us(total), "sender": stats_us(send),
                "transit": stats_us(transit), "receiver": stats_us(recv), "lost": n - len(keys),
                "guard": res.get("guard")}

    cfg = {"role": "minimal" if minimal else "sink", "name": "b", "neighbors": ["a"], "window": W,
           "network": net, "listen": eb, "connect": [ea], "guard": guard}
    return with_children([cfg], body)


def chain(W: int, n: int, length: int = 5) -> dict:
    net = f"chain{os.getpid()}w{W}"
    names = [f"n{i}" for i in range(1, length + 1)]
    eps = dict(zip(names, free_tcp_endpoints(length)))
    cfgs = []
    for i, name in enumerate(names[1:], 1):
        nbrs = [names[i - 1]] + ([names[i + 1]] if i + 1 < length else [])
        cfgs.append({"role": "relay", "name": name, "neighbors": nbrs, "window": W, "network": net,
                     "listen": eps[name], "connect": [eps[x] for x in nbrs], "last": i == length - 1})
    src = make_node("n1", ["n2"], W, fill=True)

    def body(kids):
        t0s = {}
        with ZenohTransport(net, {"n1": ["n2"]}, ZenohConfig(listen=[eps["n1"]], connect=[eps["n2"]])) as tr:
            while not tr.alive("n2"):
                tr.wait(0.01)
            time.sleep(1.0)   # peers see only direct neighbours' tokens: give the inner links time (and warm up)
            rng = np.random.default_rng(2)
            for i in range(n + 5):
                t = round((W + 1 + i) * DT, 9)
                drain(tr, src)
                t0 = time.monotonic()
                src.predict(t)
                src.update(t, rng.normal(size=2), SENSOR)
                tr.send("n1", "n2", src.message_to("n2", sent_at=t), t)
                t0s[repr(t)] = t0
                time.sleep(0.03)
            time.sleep(0.5)
            results = [k.finish() for k in kids]
        arr = results[-1]["arrivals"]
        keys = [k for k in list(t0s)[5:] if k in arr]
        return {"total": stats_us([arr[k][1] - t0s[k] for k in keys]), "lost": n - len(keys)}

    return with_children(cfgs, body)


def throughput(W: int, seconds: float) -> dict:
    net = f"tput{os.getpid()}w{W}"
    ea, eb = free_tcp_endpoints(2)
    a = make_node("a", ["b"], W, fill=True)

    def body(kids):
        with ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea], connect=[eb])) as tr:
            while not tr.alive("b"):
                tr.wait(0.01)
            rng = np.random.default_rng(3)
            sent, k = 0, W + 1
            t_start = time.monotonic()
            while time.monotonic() - t_start < seconds:
                t = round(k * DT, 9)
                drain(tr, a)
                a.predict(t)
                a.update(t, rng.normal(size=2), SENSOR)
                tr.send("a", "b", a.message_to("b", sent_at=t), t)
                sent += 1
                k += 1
            t_sent = time.monotonic() - t_start
            time.sleep(0.5)
            res = kids[0].finish()
        span = (res["last"] - res["first"]) if res.get("count", 0) > 1 else float("nan")
        return {"sent_per_s": sent / t_sent, "fused_per_s": (res["count"] - 1) / span if span == span else 0.0,
                "received": res["count"], "sent": sent}

    cfg = {"role": "sink", "name": "b", "neighbors": ["a"], "window": W, "network": net, "listen": eb,
           "connect": [ea]}
    return with_children([cfg], body)


# ---------------------------------------------------------------------- report
def table(rows, header) -> str:
    rows = [header] + [[str(c) for c in r] for r in rows]
    w = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w[i]) if i else c.ljust(w[i]) for i, c in enumerate(r)) for r in rows]
    lines.insert(1, "-" * len(lines[0]))
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer samples and window lengths")
    args = ap.parse_args()
    windows = [10, 100] if args.quick else [10, 50, 100]
    n = 100 if args.quick else 300
    t_all = time.monotonic()

    sizes = message_sizes([10, 25, 50, 100, 200])
    print("1. message bytes against the window length (4-state target, one measurement per state)")
    print(table([[W, b, f"{b / W:.1f}", steady] for W, (b, steady) in sizes.items()],
                ["window", "whole window", "bytes/state", "steady (new block, acknowledged)"]))

    print("\n2-3. per hop: a measurement at a -> b's estimate, against the raw Zenoh one-way time (ping-pong / 2)\n"
          "     measured at the same pace (pause between messages) for both")
    rows, verdict, transport_ok = [], {}, True
    hops = {}
    for pace, pause in PACES:
        verdict[pace] = True
        for W in windows:
            raw = raw_pingpong(sizes[W][1], n, pause)   # the payload of the steady-state hop
            hop = per_hop(W, n, pause)
            low = per_hop(W, n, pause, minimal=True)
            gh = per_hop(W, n, pause, guard=True)
            hops[pace, W] = hop
            ratio = hop["total"]["median"] / raw["median"]
            ok = ratio <= GOAL
            verdict[pace] &= ok
            t_ratio = hop["transit"]["median"] / raw["median"]
            transport_ok &= t_ratio <= GOAL
            g = gh["guard"] or {}
            rows.append([f"{pace} ({pause * 1e3:g} ms)", W, hop["bytes"], f"{raw['median']:.0f}",
                         f"{hop['total']['median']:.0f}", f"{hop['total']['p90']:.0f}",
                         f"{hop['sender']['median']:.0f}", f"{hop['transit']['median']:.0f}",
                         f"{hop['receiver']['median']:.0f}", f"{ratio:.2f}", "PASS" if ok else "FAIL",
                         f"{t_ratio:.2f}", f"{low['total']['median']:.0f}",
                         f"{low['total']['median'] / raw['median']:.2f}",
                         f"{low['sender']['median']:.0f}", f"{low['receiver']['median']:.0f}",
                         f"{hop['total']['median'] / low['total']['median']:.2f}",
                         f"{gh['total']['median']:.0f}", f"{gh['receiver']['median']:.0f}",
                         f"{gh['total']['median'] / low['total']['median']:.2f}",
                         f"{g.get('tests', 0)}/{g.get('failures', 0)}/{g.get('quarantines', 0)}"])
    print(table(rows, ["pace", "window", "bytes", "raw 1-way us", "hop us", "hop p90", "sender", "transit",
                       "receiver", "hop/raw", f"<= {GOAL:g}x", "transit/raw", "minimal hop us", "minimal/raw",
                       "min. sender", "min. receiver", "hop/minimal", "guard: hop us", "receiver",
                       "hop/minimal", "tests/fail/quar."]))
    print("sender = predict + update + message_to (FusionNode); transit = put to the receiver's subscriber callback\n"
          "(ZenohTransport); receiver = callback to estimate: wake-up, predict, decode + receive (FusionNode);\n"
          "minimal hop = about 10 numpy calls per side, no validation, channel join, window or filter (3b.):\n"
          "what this machine charges for any Python hop at that pace and payload; guard: the same hop with the\n"
          "consistency guard on both nodes (GuardConfig(), as scenario nodes have it), with the receiver's guard\n"
          "counters (messages tested / failed / quarantines)")

    print("\n4. end to end along a 5-node chain (5 processes, event-driven relay, a message every 30 ms)")
    rows = []
    for W in windows:
        c = chain(W, n // 2)
        per = c["total"]["median"] / 4
        rows.append([W, f"{c['total']['median']:.0f}", f"{c['total']['p90']:.0f}", f"{per:.0f}",
                     f"{hops['idle', W]['total']['median']:.0f}", c["lost"]])
    print(table(rows, ["window", "n1->n5 us", "p90", "per hop", "single hop, idle (3.)", "lost"]))

    print("\n5. messages per second on one link (sender: predict+update+message_to+send; receiver: receive+fuse)")
    rows = []
    for W in windows:
        r = throughput(W, 1.0 if args.quick else 2.0)
        rows.append([W, f"{r['sent_per_s']:.0f}", f"{r['fused_per_s']:.0f}", f"{r['received']}/{r['sent']}"])
    print(table(rows, ["window", "sent/s", "fused/s", "received/sent"]))
    verdicts = ", ".join(f"{p} link {'PASS' if ok else 'FAIL'}" for p, ok in verdict.items())
    print(f"\nper-hop goal (<= {GOAL:g}x raw one-way): {verdicts}; transport part alone "
          f"(transit <= {GOAL:g}x raw one-way): {'PASS' if transport_ok else 'FAIL'}; total {time.monotonic() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        child(json.loads(sys.argv[2]))
    else:
        sys.exit(main())
