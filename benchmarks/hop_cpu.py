"""CPU of one hop in one process, stage by stage, against the minimal hop measured beside it.

The hop of ``benchmarks/transport.py`` section 3 without the transport: node ``a`` predicts,
fuses a measurement and builds its message (the *sender*); node ``b`` predicts to the
sender's time, fuses the message and reads its estimate (the *receiver*), as runs do: the
frame's checksum and MAC checked on arrival (``FusionNode.check_frame``, stage ``b.check``; a run's
transport does it in its thread) and the message received with ``receive(data, checked=True)``,
which does not compute them again; then, outside
the timing, ``b`` acknowledges, ``a`` fuses the acknowledgement and both nodes do the
bookkeeping they left for later (``FusionNode.settle``, as an idle node does; skipped
for code without it). Same nodes as transport.py (4-state constant velocity, a full
window with one measurement per state, steady state: one new block per message).

Each hop is followed by the minimal hop of transport.py (``MinimalHop``: msgpack and one
small solve per side, about 10 numpy calls) with the same measurement, so that both see
the same machine: on a shared 2-core VM absolute times vary 2-3x from minute to minute,
the ratios far less. Printed: medians over the hops (us) and each part divided by the
median minimal hop.

Each window is measured with the consistency guard off and on (``GuardConfig()`` on both
nodes, as scenario nodes have it: the receiver tests every message against its belief);
measurements are drawn from the nodes' own motion and sensor models (``transport.Track``), so
the guarded link stays healthy (its test counters are printed: messages tested, failed,
quarantines). ``--profile`` prints cProfile's top functions of the receiver's ``receive``
instead (``--sort tottime`` or ``cumulative``), for finding what to cut.

Usage: python benchmarks/hop_cpu.py [--hops N] [--windows 10,100] [--guard off,on] [--profile]
Another checkout's code: run that checkout's interpreter on this script
(``/path/to/other/.venv/bin/python benchmarks/hop_cpu.py``): it imports ``dfusion`` from
that interpreter and ``transport.py`` from beside this file.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import transport as T  # the same hop as transport.py section 3: make_node, MinimalHop, the models

from dfusion.fusion import FusionNode, GuardConfig

STAGES = ("a.predict", "a.update", "a.message_to", "b.check", "b.predict", "b.receive", "b.estimate", "minimal")


def arrival_check(node: FusionNode):
    """``(check, receive)`` of a receiver as runs use it: the transport runs the node's
    ``check_frame`` (checksum, MAC) on every copy as it arrives and hands the node the copies
    that passed with ``receive(data, checked=True)``, which does not compute them again
    (``dfusion.run.node_process``). For code without it: no check, ``receive(data)``."""
    import inspect
    if hasattr(node, "check_frame") and "checked" in inspect.signature(node.receive).parameters:
        return node.check_frame, (lambda data: node.receive(data, checked=True))
    return (lambda data: None), node.receive


def settle(node: FusionNode) -> None:
    """The node's deferred bookkeeping (``FusionNode.settle``), if the code has it."""
    getattr(node, "settle", lambda: None)()


def hop(a, b, t: float, z, sensor, profile=None) -> tuple[float, ...]:
    """One hop at ``t`` with measurement ``z`` (a node of any checkout: ``hop_ab.py`` runs two):
    the seconds of each stage of :data:`STAGES` but the minimal hop; then, outside the timing,
    ``b``'s acknowledgement and both nodes' deferred bookkeeping. ``profile``: a cProfile
    profile enabled around ``b.receive``."""
    pc = time.perf_counter
    t0 = pc()
    a.predict(t)
    t1 = pc()
    a.update(t, z, sensor)
    t2 = pc()
    data = a.message_to("b", sent_at=t)
    t3 = pc()
    settle(a)   # idle after the send (transport.py does the same)
    check, receive = arrival_check(b)
    t4 = pc()
    check(data)   # (in a run: in the transport's thread, as the frame arrives)
    t4b = pc()
    if t > b.latest_time + 1e-9:
        b.predict(t)
    t5 = pc()
    if profile is not None:
        profile.enable()
        receive(data)
        profile.disable()
    else:
        receive(data)
    t6 = pc()
    b.estimate()
    t7 = pc()
    a.receive(b.message_to("a", sent_at=t))   # the acknowledgement, outside the timing
    settle(b)
    settle(a)
    return t1 - t0, t2 - t1, t3 - t2, t4b - t4, t5 - t4b, t6 - t5, t7 - t6


def run(W: int, hops: int, guard: bool = False, warm: int = 50, profile=None) -> tuple[dict[str, float], dict]:
    """Medians (us) per stage, and the receiver's guard summary (empty without a guard)."""
    track = T.Track(1)
    a = T.make_node("a", ["b"], W, fill=True, guard=guard, track=track)
    b = FusionNode("b", ["a"], T.MOTION, window=W, prior=T.PRIOR, epoch=7, guard=GuardConfig() if guard else None)
    mini = T.MinimalHop(W)
    times: dict[str, list[float]] = {s: [] for s in STAGES}
    pc = time.perf_counter
    for i in range(hops + warm):
        t = round((W + 1 + i) * T.DT, 9)
        z = track.z(t)
        stages = hop(a, b, t, z, T.SENSOR, profile if i >= warm else None)
        t8 = pc()
        mini.receive(mini.send(z))
        t9 = pc()
        if i >= warm:
            for s, dt in zip(STAGES, stages + (t9 - t8,)):
                times[s].append(dt)
    summary = b.guard.summary() if getattr(b, "guard", None) is not None else {}
    return {s: float(np.median(v)) * 1e6 for s, v in times.items()}, summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hops", type=int, default=2000)
    ap.add_argument("--windows", default="10,100")
    ap.add_argument("--guard", default="off,on", help="off, on or off,on")
    ap.add_argument("--profile", action="store_true", help="cProfile of the receiver's receive (per --guard)")
    ap.add_argument("--sort", default="tottime", help="cProfile sort key (tottime, cumulative)")
    args = ap.parse_args()
    windows = [int(w) for w in args.windows.split(",")]
    guards = [g == "on" for g in args.guard.split(",")]
    if args.profile:
        import cProfile
        import pstats
        for W in windows:
            for guard in guards:
                pr = cProfile.Profile()
                run(W, args.hops, guard=guard, profile=pr)
                print(f"\nwindow {W}: b.receive, guard {'on' if guard else 'off'}, {args.hops} hops")
                pstats.Stats(pr).sort_stats(args.sort).print_stats(30)
        return 0
    print(f"hop CPU in one process, medians of {args.hops} hops (us; x = / minimal hop of the same run)")
    head = ["window", "guard", "sender", "x", "receiver", "x", "both", "x", "minimal"] + list(STAGES[:-1]) + [
        "tests/fail/quar."]
    rows = []
    for W in windows:
        for guard in guards:
            m, g = run(W, args.hops, guard)
            snd = m["a.predict"] + m["a.update"] + m["a.message_to"]
            rcv = m["b.check"] + m["b.predict"] + m["b.receive"] + m["b.estimate"]
            mn = m["minimal"]
            rows.append([W, "on" if guard else "off", f"{snd:.0f}", f"{snd / mn:.2f}", f"{rcv:.0f}", f"{rcv / mn:.2f}",
                         f"{snd + rcv:.0f}", f"{(snd + rcv) / mn:.2f}", f"{mn:.0f}"]
                        + [f"{m[s]:.0f}" for s in STAGES[:-1]]
                        + [f"{g['tests']}/{g['failures']}/{g['quarantines']}" if g else "-"])
    print(T.table(rows, head))
    print("sender = a.predict + a.update + a.message_to; receiver = b.check + b.predict + b.receive + b.estimate\n"
          "(b.check: the arrival check of a run's transport, checksum and MAC; b.receive then with checked=True);\n"
          "minimal = MinimalHop send + receive (benchmarks/transport.py 3b.); guard on: GuardConfig() on both\n"
          "nodes, with the receiver's counters (messages tested / failed / quarantines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
