"""The hop of ``hop_cpu.py`` for two checkouts of dfusion in one process, interleaved: is a change slower?

``hop_cpu.py`` measures one checkout against the minimal hop of the same run; comparing two
checkouts means two processes at different minutes of a shared machine, whose load moves
medians by several per cent. This script imports the checkout under test as ``dfusion`` and
a copy of the other (``--base``, a directory holding ``dfusion/``) renamed to ``dfusion_base``,
builds the same two-node hop in each (same seed, same measurements: the two lanes compute the
same numbers), and alternates blocks of hops between the lanes, so both see the same machine.
Printed per stage: the median (us) of each lane and their ratio (new / base), with the ratio's
spread over the blocks (the median per block, its 10th and 90th percentiles).

Usage: python benchmarks/hop_ab.py --base /path/to/other/checkout [--hops 2000] [--windows 10,100]
       [--guard off,on] [--block 20]
"""
from __future__ import annotations

import argparse
import importlib
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hop_cpu as H  # the hop itself: the same stages, timed the same way
import transport as T  # the measurements (Track), the time step

STAGES = H.STAGES[:-1]


def renamed_copy(base: Path, into: Path) -> None:
    """``base/dfusion`` copied to ``into/dfusion_base`` with its imports renamed."""
    dst = into / "dfusion_base"
    shutil.copytree(base / "dfusion", dst, ignore=shutil.ignore_patterns("__pycache__"))
    pattern = re.compile(r"\bdfusion(?=[. ]|$)", re.M)
    for path in dst.rglob("*.py"):
        path.write_text(pattern.sub("dfusion_base", path.read_text()))


class Lane:
    """One checkout's hop (``hop_cpu.hop``): node ``a`` (a full window, one measurement per state)
    sends to ``b``; measurements from ``transport.Track`` (seeded: both lanes get the same)."""

    def __init__(self, pkg: str, W: int, guard: bool, seed: int = 1) -> None:
        fusion = importlib.import_module(pkg + ".fusion")
        models = importlib.import_module(pkg + ".models")
        motion, self.sensor = models.ConstantVelocity(2, 0.1), models.PositionSensor(2, 0.5)
        prior = (0.0, np.zeros(4), np.eye(4))
        self.track = T.Track(seed)
        self.a = fusion.FusionNode("a", ["b"], motion, window=W, prior=prior, epoch=3,
                                   guard=fusion.GuardConfig() if guard else None)
        self.b = fusion.FusionNode("b", ["a"], motion, window=W, prior=prior, epoch=7,
                                   guard=fusion.GuardConfig() if guard else None)
        for k in range(1, W + 1):
            self.a.predict(k * T.DT)
            self.a.update(k * T.DT, self.track.z(k * T.DT), self.sensor)
        self.k = W
        self.times: dict[str, list[float]] = {s: [] for s in STAGES}

    def hop(self, record: bool) -> None:
        self.k += 1
        t = round(self.k * T.DT, 9)
        stages = H.hop(self.a, self.b, t, self.track.z(t), self.sensor)
        if record:
            for s, dt in zip(STAGES, stages):
                self.times[s].append(dt)


def compare(W: int, guard: bool, hops: int, block: int, warm: int = 50) -> list[tuple]:
    lanes = {"base": Lane("dfusion_base", W, guard), "new": Lane("dfusion", W, guard)}
    for _ in range(warm):
        for lane in lanes.values():
            lane.hop(False)
    order = ["base", "new"]
    for i in range(hops // block):
        for name in order if i % 2 == 0 else order[::-1]:
            for _ in range(block):
                lanes[name].hop(True)
    a, b = lanes["base"], lanes["new"]
    assert np.array_equal(a.b.estimate()[0], b.b.estimate()[0]), "the two lanes computed different estimates"
    rows = []
    parts = {"sender": STAGES[:3], "receiver": STAGES[3:]}
    for name in list(STAGES) + list(parts):
        def per_hop(lane):
            if name in parts:
                return np.sum([lane.times[s] for s in parts[name]], axis=0)
            return np.asarray(lane.times[name])
        x, y = per_hop(a), per_hop(b)
        ratios = np.median(y.reshape(-1, block), axis=1) / np.median(x.reshape(-1, block), axis=1)
        rows.append((W, "on" if guard else "off", name, np.median(x) * 1e6, np.median(y) * 1e6,
                     np.median(y) / np.median(x), np.percentile(ratios, 10), np.percentile(ratios, 90)))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", required=True, type=Path, help="a checkout (the directory holding dfusion/)")
    ap.add_argument("--hops", type=int, default=2000)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--windows", default="10,100")
    ap.add_argument("--guard", default="off,on")
    args = ap.parse_args()
    if args.hops % (2 * args.block):
        ap.error("--hops must be a multiple of twice --block")
    with tempfile.TemporaryDirectory() as tmp:
        renamed_copy(args.base.resolve(), Path(tmp))
        sys.path.insert(0, tmp)
        import dfusion
        print(f"hop CPU, {args.hops} hops per lane in blocks of {args.block}, interleaved in one process; "
              f"new = {Path(dfusion.__file__).parent.parent}, base = {args.base}")
        print(f"{'window':>6} {'guard':>5} {'stage':>12} {'base us':>8} {'new us':>7} {'new/base':>8} "
              f"{'per block p10':>13} {'p90':>6}")
        for W in [int(w) for w in args.windows.split(",")]:
            for guard in [g == "on" for g in args.guard.split(",")]:
                for r in compare(W, guard, args.hops, args.block):
                    print(f"{r[0]:>6} {r[1]:>5} {r[2]:>12} {r[3]:8.1f} {r[4]:7.1f} {r[5]:8.3f} {r[6]:13.3f} {r[7]:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
