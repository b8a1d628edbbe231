"""Time one cycle of the delayed-state EIF against filterpy's KalmanFilter.

Run from the repository root::

    .venv/bin/python benchmarks/estimation.py            # 30-60 s, capped under 2 minutes
    .venv/bin/python benchmarks/estimation.py --quick    # about 10 s

Model: ``ConstantVelocity(dim=d)`` (state dimension ``n = 2d``, d = 2 and 3) with a
``PositionSensor(dim=d)``, one state every 0.1 s. Every filter is warmed up until its
window is full, so each timed cycle also marginalizes the oldest state.

Table 1, the steady-state cycle: ``predict(t)``, ``update(t, z)`` at the newest state,
``estimate()``, for windows of 10, 50 and 200 states, beside filterpy's
``KalmanFilter.predict() + update(z)`` on the same model, timed in the same run.

Table 2, what costs O(window): a *late* cycle (``predict(t)``, ``update`` of the state
half a window back, ``estimate()``) and ``estimate(t)`` of the state half a window back
(RTS backward pass over half the window; nothing changed since the last call).

Timing: ``time.perf_counter`` around batches of cycles, with the garbage collector off.
The configurations are interleaved: each *round* runs one short batch of every
configuration, so a change of machine load hits them all alike. Times are the median over
rounds of the time per cycle; ratios are the median over rounds of the ratio of two batches
of the same round (more robust than the ratio of medians when other processes share the
CPU). The printed spread is the interquartile range of those per-round ratios.

Exit status: 0, unless ``--strict`` is given and a goal printed at the end is not met (1).
"""
from __future__ import annotations

import argparse
import gc
import os
import platform
import statistics
import sys
import time

import numpy as np


import filterpy  # noqa: E402
from filterpy.kalman import KalmanFilter  # noqa: E402

from dfusion.estimation import DelayedStateEIF  # noqa: E402
from dfusion.models import ConstantVelocity, PositionSensor  # noqa: E402

DT = 0.1
Q_PSD = 0.5
STD = 0.5
WINDOWS = (10, 50, 200)
AXES = (2, 3)  # ConstantVelocity dim: state dimension 4 and 6

#: Goals checked at the end (the cycle must not grow with the window: docs/estimation.md).
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
    zs = rng.normal(0.0, 1.0, (4096, d, 1))  # (d, 1) columns: docs/background.md sec. 9, filterpy pitfalls

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


def measure(cases: list[Case], rounds: int, target: float, budget: float) -> None:
    """Run ``rounds`` rounds (at least 3, fewer if ``budget`` seconds run out)."""
    sizes = [calibrate(c, target) for c in cases]
    t_start = time.perf_counter()
    for r in range(rounds):
        if r >= 3 and time.perf_counter() - t_start > budget:
            print(f"(time budget reached: {r} rounds instead of {rounds})")
            break
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


def ratio(a: Case, b: Case) -> tuple[float, float, float]:
    """Median and quartiles over rounds of ``a / b`` (batches of the same round)."""
    r = sorted(x / y for x, y in zip(a.samples, b.samples))
    q = statistics.quantiles(r, n=4) if len(r) > 1 else [r[0]] * 3
    return statistics.median(r), q[0], q[2]


def us(s: float) -> str:
    return f"{s * 1e6:9.1f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer and shorter rounds (a few seconds)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strict", action="store_true", help="exit with status 1 when a goal is not met")
    args = ap.parse_args(argv)
    rounds, target, budget = (7, 0.01, 8.0) if args.quick else (21, 0.025, 40.0)
    rng = np.random.default_rng(args.seed)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"dfusion DelayedStateEIF vs filterpy {filterpy.__version__} KalmanFilter; numpy {np.__version__}, "
          f"Python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs, "
          f"load average {load:.2f} at start")
    print(f"{rounds} interleaved rounds, batches of ~{target * 1e3:.0f} ms; "
          "times: median microseconds per cycle; ratios: median of per-round ratios\n")

    newest = {(d, w): cycle_newest(d, w, rng) for d in AXES for w in WINDOWS}
    late = {(d, w): cycle_late(d, w, rng) for d in AXES for w in WINDOWS}
    past = {(d, w): estimate_past(d, w, rng) for d in AXES for w in WINDOWS}
    fp = {d: filterpy_cycle(d, rng) for d in AXES}
    t_start = time.perf_counter()
    measure([*fp.values(), *newest.values()], rounds, target, budget)
    measure([*late.values(), *past.values()], rounds, target, budget)
    elapsed = time.perf_counter() - t_start

    print("Table 1. Cycle at the newest state: predict + update + estimate() (window full, marginalizes)")
    print(f"{'n':>3} {'filterpy':>9} {'w=10':>9} {'w=50':>9} {'w=200':>9} {'w200/w10':>9} "
          f"{'w10/fp':>7} {'w50/fp':>7} {'w200/fp':>7}")
    for d in AXES:
        f = fp[d]
        c = [newest[(d, w)] for w in WINDOWS]
        print(f"{2 * d:>3} {us(f.median)} {us(c[0].median)} {us(c[1].median)} {us(c[2].median)} "
              f"{ratio(c[2], c[0])[0]:9.2f} {ratio(c[0], f)[0]:7.2f} {ratio(c[1], f)[0]:7.2f} "
              f"{ratio(c[2], f)[0]:7.2f}")

    print("\nTable 2. O(window) operations, half a window back")
    print(f"{'n':>3} {'operation':<36} {'w=10':>9} {'w=50':>9} {'w=200':>9} {'w200/w10':>9}")
    for d in AXES:
        for label, table in (("late cycle (predict+update+estimate)", late), ("estimate(t)", past)):
            c = [table[(d, w)] for w in WINDOWS]
            print(f"{2 * d:>3} {label:<36} {us(c[0].median)} {us(c[1].median)} {us(c[2].median)} "
                  f"{ratio(c[2], c[0])[0]:9.2f}")

    print("\nGoals (ratio: median of per-round ratios [interquartile range]; goals use the median)")
    ok = True
    for d in AXES:
        for text, (r, lo, hi), goal in (
            (f"n={2 * d}: cycle window 200 <= {GOAL_WINDOW_RATIO:g} x window 10",
             ratio(newest[(d, 200)], newest[(d, 10)]), GOAL_WINDOW_RATIO),
            (f"n={2 * d}: cycle window 50 <= {GOAL_FILTERPY_RATIO:g} x filterpy",
             ratio(newest[(d, 50)], fp[d]), GOAL_FILTERPY_RATIO),
        ):
            passed = r <= goal
            ok &= passed
            print(f"  {'PASS' if passed else 'FAIL'}  {text}: {r:.2f}x  [{lo:.2f}, {hi:.2f}]")
    print("  (for comparison, ratio of the fastest batches, least disturbed by other processes: "
          + ", ".join(f"n={2 * d} w50/fp {min(newest[(d, 50)].samples) / min(fp[d].samples):.2f}x" for d in AXES)
          + ")")
    print(f"\n(timed part {elapsed:.1f} s)")
    return 0 if ok or not args.strict else 1


if __name__ == "__main__":
    sys.exit(main())
