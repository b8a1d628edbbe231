#!/usr/bin/env python
"""Benchmarks of node filters: the WSN particle filter (dfusion.pf.WSNTracker).

Usage::

    python benchmarks/nodes.py [--dataset DIR] [--repeats 3] [--steps 200]

1. Update time of the WSN particle filter for 1,000, 5,000 and 20,000 particles
   with the 12 receivers and the 0.2 m occupancy grid of the BLE RSSI dataset
   (from the slice in tests/data/ble_rssi). One *step* is what a node does for one
   round of readings: predict over dt = 0.5 s (random walk, q = 0.5 m^2/s, every
   move checked against the map), weight with 12 RSSI readings, resample when
   ESS < N/2. Readings are simulated from the path-loss model along a walk in an
   aisle. Reported: median and 90th percentile per step (best median of
   ``--repeats`` runs), and the predict / update split. Goal: a step at most 3 ms
   at 5,000 particles.
2. With ``--dataset DIR`` (the full dataset): the accuracy table of
   examples/ble_rssi_tracking.py on every track (PF vs weighted centroid).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from dfusion.datasets import BLERSSIDataset, PathLossCalibration
from dfusion.pf import WSNTracker

ROOT = Path(__file__).resolve().parent.parent
SLICE = ROOT / "tests" / "data" / "ble_rssi"
GOAL_MS = 3.0
GOAL_N = 5000


def _walk(n: int, dt: float) -> np.ndarray:
    """A walk along the aisle y = 8.5 m and back (0.4 m/s), then up the aisle x = 11.6 m."""
    s = 0.4 * dt * np.arange(n)
    x = 1.0 + np.abs(((s / 17.0) % 2) - 1) * 17.0
    return np.column_stack([x, np.full(n, 8.5)])


def bench_wsn(n_particles: int, steps: int, repeats: int, with_map: bool = True) -> dict:
    ds = BLERSSIDataset(SLICE)
    cal = PathLossCalibration.from_json(json.loads((SLICE / "path_loss.json").read_text()), ds.receiver_macs)
    sensors = cal.sensors(ds.receiver_positions)
    grid = ds.load_grid(0.2) if with_map else None
    dt = 0.5
    truth = _walk(steps + 20, dt)
    rng = np.random.default_rng(0)
    readings = np.array([[s.h(p)[0] for s in sensors] for p in truth]) + rng.standard_normal((len(truth), 12)) * cal.std
    best = None
    for rep in range(repeats):
        t = WSNTracker(sensors, n_particles, q=0.5, grid=grid, bounds=None if with_map else ds.limits, seed=rep)
        t.initialize(mean=truth[0], cov=np.eye(2))
        for k in range(20):  # warm-up (allocations, caches)
            t.step(dt, readings[k])
        tp, tu = np.empty(steps), np.empty(steps)
        for k in range(steps):
            a = time.perf_counter()
            t.predict(dt)
            b = time.perf_counter()
            t.update(readings[20 + k])
            c = time.perf_counter()
            tp[k], tu[k] = b - a, c - b
        tot = tp + tu
        res = {"particles": n_particles, "map": with_map, "median_ms": 1e3 * np.median(tot),
               "p90_ms": 1e3 * np.percentile(tot, 90), "predict_ms": 1e3 * np.median(tp),
               "update_ms": 1e3 * np.median(tu), "resamples": t.pf.n_resamples,
               "error_m": float(np.linalg.norm(t.estimate() - truth[19 + steps]))}
        if best is None or res["median_ms"] < best["median_ms"]:
            best = res
    return best


def timing_table(steps: int, repeats: int) -> tuple[str, bool]:
    rows = [bench_wsn(n, steps, repeats, True) for n in (1000, 5000, 20000)]
    rows.append(bench_wsn(GOAL_N, steps, repeats, False))
    head = f"{'particles':>9s} {'map':>4s} {'step med':>9s} {'step p90':>9s} {'predict':>8s} {'update':>8s}"
    lines = ["WSN particle filter, 12 receivers, one step = predict(0.5 s) + update(12 readings) + resampling",
             head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['particles']:9d} {'yes' if r['map'] else 'no':>4s} {r['median_ms']:7.2f}ms "
                     f"{r['p90_ms']:7.2f}ms {r['predict_ms']:6.2f}ms {r['update_ms']:6.2f}ms")
    goal = next(r for r in rows if r["particles"] == GOAL_N and r["map"])
    ok = goal["median_ms"] <= GOAL_MS
    lines.append(f"goal: step <= {GOAL_MS} ms at {GOAL_N} particles (with map): "
                 f"{goal['median_ms']:.2f} ms -> {'PASS' if ok else 'FAIL'}")
    return "\n".join(lines), ok


def accuracy_table(dataset: Path, particles: int) -> str:
    spec = importlib.util.spec_from_file_location("ble_rssi_tracking", ROOT / "examples" / "ble_rssi_tracking.py")
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    ds = BLERSSIDataset(dataset)
    cache: dict = {}
    res = [ex.evaluate_track(ds, p, cache=cache, particles=particles) for p in ds.track_paths()]
    rows = res + ([ex.pooled(res)] if len(res) > 1 else [])
    return (f"BLE RSSI tracks ({particles} particles, defaults of examples/ble_rssi_tracking.py; "
            "leave-one-track-out calibration)\n" + ex.format_table(rows))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, help="full BLE RSSI dataset directory: also print the accuracy table")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--particles", type=int, default=5000, help="particles for the accuracy table")
    args = ap.parse_args(argv)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs, "
          f"load average {load:.2f}")
    table, _ = timing_table(args.steps, args.repeats)
    print(table)
    if args.dataset:
        print()
        print(accuracy_table(args.dataset, args.particles))
    return 0


if __name__ == "__main__":
    sys.exit(main())
