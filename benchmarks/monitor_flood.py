"""A flood at the launcher's monitor: the launcher's memory and the nodes' results.

``dfusion run`` of the 3-node linear chain (``tests/run/test_processes.py``'s scenario,
window over the whole run: the nodes end exact), once without a flood (the reference,
same run of this script) and once per flood: after the start, flooder processes connect
to the monitor's endpoint (``RUN_DIR/run.json``), as any local program can, and publish
payloads as fast as Zenoh takes them on ``dfusion/NET/monitor/a``, for ``--seconds``:

* 1 MiB publications (issue 23: the launcher grew from 115 MB to 1.3-1.6 GB in 8 s and
  3.5 GB in 20 s when the monitor's queue was bounded in count only); longer than any
  node's publication (``dfusion.run.common.status_limit``), dropped as they arrive;
* publications just under that limit: each is copied and queued (the queue's byte bound,
  ``dfusion.run.monitor.MAX_PENDING_BYTES``) and rejected as unauthenticated.

Goal: the launcher's peak resident memory (``VmHWM``) under 300 MB with the flood, and every
node finished with its final gap <= 1e-9 (exact). Also shown: the publications the monitor
shed (queue full), rejected on arrival (forged: malformed or unauthenticated), and the grid
steps of which the monitor recorded no estimate (filled with the previous one; the nodes'
results do not depend on them).

    .venv/bin/python benchmarks/monitor_flood.py              # 20 s floods, about 2 minutes
    .venv/bin/python benchmarks/monitor_flood.py --quick      # 4 s floods
    .venv/bin/python benchmarks/monitor_flood.py --strict     # exit status 1 if a goal fails
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dfusion.run.common import status_limit  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402
from tests.helpers.flood import run_with_flood  # noqa: E402
from tests.run.test_processes import CHAIN3  # noqa: E402

GOAL_MB = 300.0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="4 s floods")
    p.add_argument("--seconds", type=float, default=None, help="flood duration (default 20, --quick 4)")
    p.add_argument("--flooders", type=int, default=2, help="flooder processes per flood")
    p.add_argument("--strict", action="store_true")
    args = p.parse_args()
    seconds = args.seconds or (4.0 if args.quick else 20.0)
    print(f"load average {os.getloadavg()[0]:.2f}; floods of {seconds:g} s by {args.flooders} processes")
    rows, ok = [], True
    with tempfile.TemporaryDirectory(prefix="dfusion-flood-") as tmp:
        tmp = Path(tmp)
        path = tmp / "chain3.scenario.toml"
        path.write_text(CHAIN3.format(duration=seconds + 8.0, window=10 * int(seconds + 10)))
        limit = status_limit(load_scenario(path))
        cases = [("none (reference)", 0), ("1 MiB", 1 << 20), (f"{limit - 64} B (under the limit)", limit - 64)]
        for label, size in cases:
            run = run_with_flood(path, tmp / f"run{size}", size=max(size, 1), flood_s=seconds,
                                 flooders=args.flooders if size else 0)
            m, rm = run.metrics, run.metrics["run"]
            q = rm["monitor_queue"]
            gap = max(v["final_gap"] for v in m["nodes"].values())
            missing = sum(v["steps_missing"] for v in rm["nodes"].values())
            finished = all(v["finished"] for v in rm["nodes"].values())
            good = run.rss_peak_mb < GOAL_MB and gap <= 1e-9 and finished and not rm["failures"]
            ok &= good
            rows.append((label, run.sent, run.sent * size / 2**30, run.rss_before_mb, run.rss_peak_mb,
                         q["oversized"], q["shed"], q["peak_bytes"] / 2**20,
                         sum(v for r, v in rm["monitor_rejections"].items() if r not in ("oversized", "queue-full")),
                         gap, missing, good))
    head = ("flood", "sent", "GiB", "RSS before [MB]", "peak RSS [MB]", "oversized", "shed", "queue peak [MiB]",
            "on arrival", "max final gap", "steps missing", "goal")
    fmt = "{:<28} {:>8} {:>6} {:>15} {:>13} {:>9} {:>7} {:>16} {:>10} {:>13} {:>13} {:>5}"
    print(f"publication limit of the scenario: {limit} bytes; goal: peak RSS < {GOAL_MB:g} MB, gaps <= 1e-9")
    print(fmt.format(*head))
    for r in rows:
        print(fmt.format(r[0], r[1], f"{r[2]:.1f}", f"{r[3]:.0f}", f"{r[4]:.0f}", r[5], r[6], f"{r[7]:.2f}", r[8],
                         f"{r[9]:.1e}", r[10], "PASS" if r[11] else "FAIL"))
    return 1 if args.strict and not ok else 0


if __name__ == "__main__":
    raise SystemExit(main())
