"""A busy receiver: bytes per message and the receiver's CPU when acknowledgements lag behind.

The hop of ``transport.py`` section 3 in one process (node ``a`` predicts, measures and sends;
node ``b`` predicts to the sender's time, fuses the message, reads its estimate and answers),
except that ``b`` works through a queue: it fuses each message ``lag`` messages after it was
sent, as a CPU-starved process does, and answers at once; ``a`` fuses the answers before its
next message. Acknowledgements then lag ``lag`` messages behind while they keep advancing.
With ``--lose K`` every K-th message is lost on the way.

Printed per window and lag: the median and 90th percentile of the message size (bytes), the
median of ``b``'s ``receive`` + ``estimate`` (us), and after the queue is drained and one more
exchange, the largest difference between ``b``'s estimate and ``a``'s (both hold the same
information then: ``b`` has nothing of its own), which must be at rounding level.

The resend backoff (``docs/fusion.md``) keeps such a link at one block per message; before it,
every message carried everything since the newest acknowledged one as soon as the lag passed
``ACK_LAG`` (2). Another checkout's code: ``cd /tmp && PYTHONPATH=/path/to/code
/path/to/.venv/bin/python /path/to/benchmarks/busy_receiver.py``.

Usage: python benchmarks/busy_receiver.py [--hops 400] [--windows 10,100] [--lags 0,2,3,5,10] [--lose 0]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import transport as T  # the hop of transport.py section 3: make_node, Track, the models

from dfusion.fusion import FusionNode


def run(W: int, lag: int, hops: int, lose: int = 0) -> dict[str, float]:
    track = T.Track(1)
    a = T.make_node("a", ["b"], W, fill=True, track=track)
    b = FusionNode("b", ["a"], T.MOTION, window=W, prior=T.PRIOR, epoch=7)
    queue: deque = deque()
    answers: deque = deque()
    sizes, cpu = [], []
    pc = time.perf_counter

    def deliver(t: float, data: bytes) -> None:
        if t > b.latest_time + 1e-9:
            b.predict(t)
        t0 = pc()
        b.receive(data)
        b.estimate()
        cpu.append(pc() - t0)
        answers.append(b.message_to("a", sent_at=t))
        b.settle()

    t = 0.0
    for i in range(hops):
        t = round((W + 1 + i) * T.DT, 9)
        a.predict(t)
        a.update(t, track.z(t), T.SENSOR)
        while answers:
            a.receive(answers.popleft())
        data = a.message_to("b", sent_at=t)
        a.settle()
        sizes.append(len(data))
        if not (lose and i % lose == lose - 1):
            queue.append((t, data))
        while len(queue) > lag:
            deliver(*queue.popleft())
    while queue:
        deliver(*queue.popleft())
    for _ in range(2):   # the times an acknowledgement showed lost, then the answer
        while answers:
            a.receive(answers.popleft())
        deliver(t, a.message_to("b", sent_at=t))
    gap = max(float(np.max(np.abs(x - y))) for x, y in zip(a.estimate(), b.estimate()))
    return {"median": float(np.median(sizes)), "p90": float(np.percentile(sizes, 90)),
            "cpu": float(np.median(cpu)) * 1e6, "gap": gap}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hops", type=int, default=400)
    ap.add_argument("--windows", default="10,100")
    ap.add_argument("--lags", default="0,2,3,5,10")
    ap.add_argument("--lose", type=int, default=0, help="lose every K-th message (0: none)")
    ap.add_argument("--quick", action="store_true", help="100 hops")
    args = ap.parse_args()
    hops = 100 if args.quick else args.hops
    print(f"busy receiver, {hops} messages per row, load average {os.getloadavg()[0]:.1f}"
          + (f", every {args.lose}th message lost" if args.lose else ""))
    rows = []
    for W in (int(w) for w in args.windows.split(",")):
        for lag in (int(x) for x in args.lags.split(",")):
            r = run(W, lag, hops, args.lose)
            rows.append([W, lag, f"{r['median']:.0f}", f"{r['p90']:.0f}", f"{r['cpu']:.0f}", f"{r['gap']:.1e}"])
    print(T.table(rows, ["window", "lag", "bytes median", "bytes p90", "b receive+estimate (us)",
                         "|b - a| after draining"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
