"""Time one cycle of the delayed-state EIF against filterpy's KalmanFilter.

Run from the repository root::

    .venv/bin/python benchmarks/estimation.py            # about 1 minute
    .venv/bin/python benchmarks/estimation.py --quick    # a few seconds

Model: ``ConstantVelocity(dim=d)`` (state dimension ``n = 2d``, d = 2 and 3) with a
``PositionSensor(dim=d)``, one state every 0.1 s. Every filter is warmed up until its
window is full, so each timed cycle also marginalizes the oldest state.

Table 1, the steady-state cycle: ``predict(t)``, ``update(t, z)`` at the newest state,
``estimate()``, for windows of 10, 50 and 200 states, beside filterpy's
``KalmanFilter.predict() + update(z)`` on the same model, timed in the same run.

Table 2, what costs O(window): a *late* cycle (``predict(t)``, ``update`` of the state
half a window back, ``estimate()``) and ``estimate(t)`` of the state half a window back
(RTS backward pass over half the window; nothing changed since the last call).

Timing: ``time.perf_counter`` around batches of cycles, with the garbage collector off;
the configurations are interleaved batch by batch (so slow drifts of the machine hit them
all alike) and the median over batches of the time per cycle is reported.
"""
from __future__ import annotations

import argparse
import gc
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import filterpy  # noqa: E402
from filterpy.kalman import KalmanFilter  # noqa: E402

from dfusion import DelayedStateEIF  # noqa: E402
from dfusion.models import ConstantVelocity, PositionSensor  # noqa: E402

DT = 0.1
Q_PSD = 0.5
STD = 0.5
WINDOWS = (10, 50, 200)
AXES = (2, 3)  # ConstantVelocity dim: state dimension 4 and 6

#: Goals checked at the end (DESIGN: the cycle must not grow with the window).
GOAL_WINDOW_RATIO = 20.0   # cycle(window 200) <= 20 x cycle(window 10)
GOAL_FILTERPY_RATIO = 5.0  # cycle(window 50) <= 5 x filterpy predict+update


class Case:
    """One timed configuration: ``run(k)`` performs ``k`` cycles."""

    def __init__(self, name: str, run) -> None:
        self.name = name
        self.run = run
        self.samples: list[float] = []  # seconds per cycle, one per batch

    @property
    def median(self) -> float:
        return statistics.median(self.samples)


def make_eif(d: int, window: int, rng: np.random.Generator):
    f = DelayedStateEIF(ConstantVelocity(dim=d, q=Q_PSD), window=window)
    f.initialize(0.0, np.zeros(2 * d), np.eye(2 * d))
    sensor = PositionSensor(dim=d, std=STD)
    state = {"k": 0}

    def step_newest() -> None:
        state["k"] += 1
        t = state["k"] * DT
        f.predict(t)
        f.update(t, rng.normal(0.0, 1.0, d), sensor)
        f.estimate()

    # warm up: fill the window (plus a few, so that marginalization happens every cycle)
    for _ in range(window + 5):
        step_newest()
    assert len(f) == window and f.marginalized > 0
    return f, sensor, state, step_newest


def cycle_newest(d: int, window: int, rng) -> Case:
    f, sensor, state, step = make_eif(d, window, rng)
    zs = rng.normal(0.0, 1.0, (4096, d))

    def run(k: int) -> None:
        for i in range(k):
            state["k"] += 1
            t = state["k"] * DT
            f.predict(t)
            f.update(t, zs[i & 4095], sensor)
            f.estimate()

    return Case(f"newest w={window} n={2 * d}", run)


def cycle_late(d: int, window: int, rng) -> Case:
    f, sensor, state, _ = make_eif(d, window, rng)
    zs = rng.normal(0.0, 1.0, (4096, d))
    back = window // 2

    def run(k: int) -> None:
        for i in range(k):
            state["k"] += 1
            f.predict(state["k"] * DT)
            f.update((state["k"] - back) * DT, zs[i & 4095], sensor)  # a window state
            f.estimate()

    return Case(f"late w={window} n={2 * d}", run)


def estimate_past(d: int, window: int, rng) -> Case:
    f, _, state, _ = make_eif(d, window, rng)
    t_half = (state["k"] - window // 2) * DT
    assert f.index_of(t_half) is not None

    def run(k: int) -> None:
        for _ in range(k):
            f.estimate(t_half)

    return Case(f"estimate(t) w={window} n={2 * d}", run)


def filterpy_cycle(d: int, rng) -> Case:
    n = 2 * d
    kf = KalmanFilter(dim_x=n, dim_z=d)
    kf.x = np.zeros((n, 1))
    kf.P = np.eye(n)
    mo = ConstantVelocity(dim=d, q=Q_PSD)
    kf.F, kf.Q = mo.F(DT), mo.Q(DT)
    kf.H = np.hstack([np.eye(d), np.zeros((d, d))])
    kf.R = STD**2 * np.eye(d)
    zs = rng.normal(0.0, 1.0, (4096, d, 1))  # (d, 1) columns: see ZENOH_NOTES, filterpy pitfalls

    def run(k: int) -> None:
        for i in range(k):
            kf.predict()
            kf.update(zs[i & 4095])

    run(50)
    return Case(f"filterpy n={n}", run)


def calibrate(case: Case, target: float) -> int:
    """Number of cycles per batch so that one batch takes about ``target`` seconds."""
    k = 1
    while True:
        t0 = time.perf_counter()
        case.run(k)
        el = time.perf_counter() - t0
        if el >= target / 10 or k >= 1 << 16:
            return max(1, int(k * target / max(el, 1e-9)))
        k *= 4


def measure(cases: list[Case], batches: int, target: float) -> None:
    sizes = [calibrate(c, target) for c in cases]
    for _ in range(batches):
        for c, k in zip(cases, sizes):
            gc.collect()
            gc.disable()
            try:
                t0 = time.perf_counter()
                c.run(k)
                el = time.perf_counter() - t0
            finally:
                gc.enable()
            c.samples.append(el / k)


def us(s: float) -> str:
    return f"{s * 1e6:9.1f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer and shorter batches (a few seconds)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    batches, target = (5, 0.02) if args.quick else (9, 0.12)
    rng = np.random.default_rng(args.seed)

    print(f"dfusion DelayedStateEIF vs filterpy {filterpy.__version__} KalmanFilter; numpy {np.__version__}, "
          f"Python {platform.python_version()}, {platform.machine()}")
    print(f"median over {batches} batches of ~{target * 1e3:.0f} ms each; times in microseconds per cycle\n")

    newest = {(d, w): cycle_newest(d, w, rng) for d in AXES for w in WINDOWS}
    late = {(d, w): cycle_late(d, w, rng) for d in AXES for w in WINDOWS}
    past = {(d, w): estimate_past(d, w, rng) for d in AXES for w in WINDOWS}
    fp = {d: filterpy_cycle(d, rng) for d in AXES}
    t_start = time.perf_counter()
    measure([*fp.values(), *newest.values()], batches, target)
    measure([*late.values(), *past.values()], batches, target)
    elapsed = time.perf_counter() - t_start

    print("Table 1. Cycle at the newest state: predict + update + estimate() (window full, marginalizes)")
    print(f"{'n':>3} {'filterpy':>9} {'w=10':>9} {'w=50':>9} {'w=200':>9} {'w200/w10':>9} "
          f"{'w10/fp':>7} {'w50/fp':>7} {'w200/fp':>7}")
    for d in AXES:
        f = fp[d].median
        t = [newest[(d, w)].median for w in WINDOWS]
        print(f"{2 * d:>3} {us(f)} {us(t[0])} {us(t[1])} {us(t[2])} {t[2] / t[0]:9.2f} "
              f"{t[0] / f:7.2f} {t[1] / f:7.2f} {t[2] / f:7.2f}")

    print("\nTable 2. O(window) operations, half a window back")
    print(f"{'n':>3} {'operation':<34} {'w=10':>9} {'w=50':>9} {'w=200':>9} {'w200/w10':>9}")
    for d in AXES:
        for label, table in (("late cycle (predict+update+estimate)", late), ("estimate(t)", past)):
            t = [table[(d, w)].median for w in WINDOWS]
            print(f"{2 * d:>3} {label:<36} {us(t[0])} {us(t[1])} {us(t[2])} {t[2] / t[0]:9.2f}")

    print("\nGoals")
    ok = True
    for d in AXES:
        r1 = newest[(d, 200)].median / newest[(d, 10)].median
        r2 = newest[(d, 50)].median / fp[d].median
        for text, r, goal in (
            (f"n={2 * d}: cycle window 200 <= {GOAL_WINDOW_RATIO:g} x window 10", r1, GOAL_WINDOW_RATIO),
            (f"n={2 * d}: cycle window 50 <= {GOAL_FILTERPY_RATIO:g} x filterpy", r2, GOAL_FILTERPY_RATIO),
        ):
            passed = r <= goal
            ok &= passed
            print(f"  {'PASS' if passed else 'FAIL'}  {text}: {r:.2f}x")
    spread = max(
        (max(c.samples) - min(c.samples)) / c.median
        for c in [*fp.values(), *newest.values(), *late.values(), *past.values()]
    )
    print(f"\n(timed part {elapsed:.1f} s; largest batch spread (max-min)/median: {spread:.0%})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
