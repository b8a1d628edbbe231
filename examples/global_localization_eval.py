#!/usr/bin/env python
r"""Global localization in a repetitive corridor, evaluated with the survey's protocol.

Usage::

    python examples/global_localization_eval.py [--quick] [--json OUT] [--plot OUT.png]
                                                [--waypoints W] [--trials T] [--seed S]

Zhang et al.'s survey of global localization in repetitive environments
("Infrastructure-Free Global Localization in Repetitive Environments: An Overview",
sec. IV.B) evaluates a localizer by repeated global localizations from waypoints
(10 waypoints x 10 tests), with three criteria:

* **robustness** -- the *success rate*: the fraction of tests in which the robot
  localized itself correctly;
* **efficiency** -- the *correct-localization distance* (CLD): how far the robot travelled
  until it was correctly localized; a test whose CLD exceeds 10 m is a failure;
* **accuracy** -- the *CDF of the absolute localization error*; an error above 10 m is a
  failure.

Here (all simulated, deterministic by ``--seed``):

* the map is :meth:`dfusion.maps.OccupancyGrid.repetitive_corridor` (30 m x 2 m, identical
  alcoves every 3 m on both sides: only the two ends tell places apart), and for
  comparison :meth:`~dfusion.maps.OccupancyGrid.corridor` (the same size with five
  randomly placed recesses);
* ``W`` waypoints are drawn along the corridor (seeded); from each, ``T`` tests start with
  the robot at the waypoint facing +x or -x (random) and driving along the corridor in
  0.25 m steps (turning round 1 m before an end), ``--run-length`` metres in all (12 m);
* the robot's laser (``--beams`` over 270 degrees, Gaussian noise 2 cm, exact ray
  casting) scans at every step; odometry has 2 % scale noise and 0.01 rad of heading
  noise per step;
* :class:`~dfusion.localization.MonteCarloLocalization` (likelihood field, KLD
  sampling up to ``--particles``, Augmented-MCL recovery 0.001 / 0.1) starts from the
  uniform prior over the free space (:meth:`initialize_global`);
* a test is **correctly localized** at the first step from which the estimate stays within
  0.5 m and 0.2 rad of the truth until the end of the run; its CLD is the distance
  travelled up to that step; a test with no such step, or a CLD above 10 m, fails;
* the **error** of a test is the position error of the estimate after 10 m of travel
  (the survey's CDF of the absolute error; a failure when above 10 m).

Configurations (``--configs``): ``repetitive-8m`` (repetitive corridor, 8 m laser range:
the ends are out of sight from most of the corridor), ``repetitive-30m`` (the same map,
30 m range) and ``corridor-8m`` (random recesses, 8 m range). ``--quick`` runs a small
setting (2 waypoints x 2 tests, 4,000 particles, repetitive-30m and corridor-8m) for the
test suite. The tables are printed; ``--json`` writes every number, ``--plot`` a PNG with
the three panels of the survey's Fig. 4 (success rate per waypoint, CLD box plot, error
CDF). Results: ``docs/robots.md``.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from dfusion.maps.buildings import corridor, repetitive_corridor


from dfusion.models import LaserConfig, OdometryMotionModel  # noqa: E402
from dfusion.localization import MonteCarloLocalization  # noqa: E402
from dfusion.geometry import se2_between, se2_compose  # noqa: E402
from dfusion.maps import cast_rays, OccupancyGrid  # noqa: E402
from dfusion.geometry import wrap_angle  # noqa: E402

CONFIGS = {
    "repetitive-8m": ("repetitive", 8.0),
    "repetitive-30m": ("repetitive", 30.0),
    "corridor-8m": ("corridor", 8.0),
}
STEP = 0.25          # m per step
FAIL_DISTANCE = 10.0  # m: CLD and error threshold of the survey
POS_TOL, HEAD_TOL = 0.5, 0.2  # correct localization


def make_map(kind: str) -> OccupancyGrid:
    if kind == "repetitive":
        return repetitive_corridor(length=30.0, width=2.0, period=3.0)
    return corridor(length=30.0, width=2.0, openings=5, seed=3)


def drive(start: np.ndarray, steps: int, length: float, rng: np.random.Generator) -> np.ndarray:
    """True poses: along the corridor in STEP increments, turning round 1 m before an end."""
    poses = [start.copy()]
    x = start.copy()
    for _ in range(steps):
        ahead = x[0] + STEP * math.cos(x[2])
        if ahead < 1.0 or ahead > length - 1.0:
            x = np.array([x[0], x[1], float(wrap_angle(x[2] + math.pi))])  # turn in place
        else:
            x = np.array([ahead, x[1] + 0.02 * rng.standard_normal(), x[2]])
        poses.append(x)
    return np.array(poses)


def odometry(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    out = [poses[0].copy()]
    for a, b in zip(poses[:-1], poses[1:]):
        d = se2_between(a, b)
        d[:2] *= 1.0 + 0.02 * rng.standard_normal()
        d[2] += 0.01 * rng.standard_normal()
        out.append(se2_compose(out[-1], d))
    return np.array(out)


def run_test(grid: OccupancyGrid, laser: LaserConfig, start: np.ndarray, args, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    steps = int(round(args.run_length / STEP))
    truth = drive(start, steps, 30.0, rng)
    odom = odometry(truth, rng)
    scans = cast_rays(grid, truth, laser.angles, laser.max_range) + 0.02 * rng.standard_normal((truth.shape[0], laser.angles.size))
    mcl = MonteCarloLocalization(
        grid, laser, motion=OdometryMotionModel(0.05, 0.05, 0.05, 0.05), min_particles=300,
        max_particles=args.particles, max_beams=60, alpha_slow=0.001, alpha_fast=0.1, rng=seed,
    )
    mcl.predict(0.0, odom[0])
    mcl.initialize_global(t=0.0)
    est = np.empty_like(truth)
    for k in range(truth.shape[0]):
        if k:
            mcl.predict(float(k), odom[k])
        mcl.update(float(k), scans[k])
        est[k] = mcl.estimate().mean
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    pos_err = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    head_err = np.abs(wrap_angle(est[:, 2] - truth[:, 2]))
    return {**score(dist, pos_err, head_err), "steps": int(truth.shape[0])}


def score(dist: np.ndarray, pos_err: np.ndarray, head_err: np.ndarray) -> dict:
    """The survey's criteria for one test, from the distance travelled and the errors per step.

    Correctly localized at the first step from which the estimate stays within
    ``POS_TOL`` / ``HEAD_TOL`` until the end; CLD = distance travelled up to that step
    (``None``: never); success = CLD <= 10 m; error = position error after 10 m of travel
    (at the last step if the run is shorter).
    """
    ok = (pos_err < POS_TOL) & (head_err < HEAD_TOL)
    bad = np.flatnonzero(~ok)
    first = 0 if bad.size == 0 else int(bad[-1]) + 1  # first step after which it stays correct
    cld = float(dist[first]) if first < ok.size else math.inf
    k10 = int(min(np.searchsorted(dist, FAIL_DISTANCE), dist.size - 1))
    return {"cld": cld if math.isfinite(cld) else None, "success": bool(cld <= FAIL_DISTANCE),
            "error": float(pos_err[k10]), "final_error": float(pos_err[-1])}


def evaluate(name: str, args, rng_wp: np.random.Generator) -> dict:
    kind, max_range = CONFIGS[name]
    grid = make_map(kind)
    laser = LaserConfig.uniform(args.beams, math.radians(270.0), max_range)
    xs = rng_wp.uniform(2.0, 28.0, size=args.waypoints)
    tests = []
    for w, x0 in enumerate(xs):
        for j in range(args.trials):
            seed = args.seed * 100003 + w * 1009 + j
            r = np.random.default_rng(seed + 7)
            start = np.array([x0, 1.0 + r.uniform(-0.3, 0.3), 0.0 if r.random() < 0.5 else math.pi])
            res = run_test(grid, laser, start, args, seed)
            res["waypoint"] = w
            tests.append(res)
    success = np.array([t["success"] for t in tests])
    cld = np.array([math.inf if t["cld"] is None else t["cld"] for t in tests])
    err = np.array([t["error"] for t in tests])
    per_wp = [float(np.mean([t["success"] for t in tests if t["waypoint"] == w])) for w in range(args.waypoints)]
    ok_cld = cld[success]
    return {
        "map": kind,
        "laser_range": max_range,
        "waypoints_x": xs.tolist(),
        "tests": tests,
        "success_rate": float(success.mean()),
        "success_rate_per_waypoint": per_wp,
        "cld_mean": float(ok_cld.mean()) if ok_cld.size else None,
        "cld_median": float(np.median(ok_cld)) if ok_cld.size else None,
        "error_median": float(np.median(err)),
        "error_p90": float(np.percentile(err, 90)),
        "error_below_0.5m": float(np.mean(err < POS_TOL)),
        "error_failures": int(np.sum(err > FAIL_DISTANCE)),
    }


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import MaxNLocator

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    names = list(results)
    colors = {name: f"C{i}" for i, name in enumerate(names)}
    e_all = np.concatenate([[t["error"] for t in r["tests"]] for r in results.values()])
    e_lo = max(1e-3, 0.5 * float(np.min(e_all))) if e_all.size else 1e-3
    e_hi = max(2.0 * FAIL_DISTANCE, 1.2 * float(np.max(e_all))) if e_all.size else 2.0 * FAIL_DISTANCE
    for name, r in results.items():
        per = r["success_rate_per_waypoint"]
        cum = np.cumsum(per) / np.arange(1, len(per) + 1)
        ax[0].plot(np.arange(1, len(per) + 1), 100 * cum, marker="o", color=colors[name],
                   label=f"{name} ({100 * r['success_rate']:.0f} %)")
        # empirical CDF from 0 at the left edge to 1 at the largest error
        e = np.sort([t["error"] for t in r["tests"]])
        x = np.concatenate([[e_lo], e, [e_hi]])
        y = np.concatenate([[0.0], np.arange(1, e.size + 1) / e.size, [1.0]])
        ax[2].step(x, y, where="post", color=colors[name], label=name)
    ax[0].set(xlabel="waypoint", ylabel="cumulative success rate (%)", ylim=(-2, 105), title="robustness")
    ax[0].xaxis.set_major_locator(MaxNLocator(integer=True))
    # CLD of the successful tests: box plot and the individual tests (jittered)
    rng = np.random.default_rng(0)
    data, labels = [], []
    for i, (name, r) in enumerate(results.items(), start=1):
        cld = [t["cld"] for t in r["tests"] if t["success"]]
        labels.append(f"{name}\n{len(cld)}/{len(r['tests'])} successful")
        data.append(cld if cld else [np.nan])
        if cld:
            ax[1].plot(i + rng.uniform(-0.12, 0.12, len(cld)), cld, "o", ms=4, alpha=0.6, color=colors[name])
        else:
            ax[1].text(i, 0.5 * FAIL_DISTANCE, "no success", ha="center", va="center", color="0.4")
    ax[1].boxplot(data, showmeans=True, showfliers=False, widths=0.5, medianprops={"color": "k"})
    ax[1].axhline(FAIL_DISTANCE, color="k", lw=0.8, ls="--")
    ax[1].text(0.55, FAIL_DISTANCE, f" fail beyond {FAIL_DISTANCE:g} m", va="bottom", fontsize=8)
    ax[1].set_xticks(range(1, len(results) + 1), labels, fontsize=8)
    ax[1].set(ylabel="correct-localization distance (m)", ylim=(0, 1.1 * FAIL_DISTANCE + 0.5),
              xlim=(0.5, len(results) + 0.5), title="efficiency (successful tests)")
    ax[2].set(xscale="log", xlabel="absolute position error after 10 m (m)", ylabel="fraction of tests (CDF)",
              title="accuracy", xlim=(e_lo, e_hi), ylim=(0, 1.02))
    ax[2].axvline(FAIL_DISTANCE, color="k", lw=0.8, ls="--")
    ax[2].axvline(POS_TOL, color="0.5", lw=0.8, ls=":")
    ax[2].text(FAIL_DISTANCE, 0.03, f" {FAIL_DISTANCE:g} m", fontsize=8)
    ax[2].text(POS_TOL, 0.03, f" {POS_TOL:g} m (correct)", fontsize=8, color="0.4")
    for a in (ax[0], ax[2]):
        a.legend(fontsize=8, loc="best")
        a.grid(alpha=0.3)
    ax[1].grid(alpha=0.3, axis="y")
    n_tests = {len(r["tests"]) for r in results.values()}
    fig.suptitle(f"global localization, {'/'.join(map(str, sorted(n_tests)))} tests per configuration", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small setting for the test suite")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--waypoints", type=int, default=10)
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--particles", type=int, default=20000)
    ap.add_argument("--beams", type=int, default=109)
    ap.add_argument("--run-length", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS))
    args = ap.parse_args(argv)
    if args.quick:
        args.waypoints, args.trials, args.particles = 2, 2, 4000
        args.configs = ["repetitive-30m", "corridor-8m"]
    t0 = time.perf_counter()
    rng_wp = np.random.default_rng(args.seed)
    results = {}
    for name in args.configs:
        results[name] = evaluate(name, args, np.random.default_rng(rng_wp.integers(1 << 31)))
    n = args.waypoints * args.trials
    print(f"global localization, {args.waypoints} waypoints x {args.trials} tests, up to {args.particles:,} particles, "
          f"{args.run_length:g} m runs; success: error < {POS_TOL} m / {HEAD_TOL} rad from some step on, CLD <= {FAIL_DISTANCE:g} m")
    print(f"{'configuration':<16}{'success':>9}{'CLD mean':>10}{'CLD med':>9}{'err med':>9}{'err 90%':>9}{'err<0.5m':>10}")
    for name, r in results.items():
        cm = "-" if r["cld_mean"] is None else f"{r['cld_mean']:.2f}"
        cd = "-" if r["cld_median"] is None else f"{r['cld_median']:.2f}"
        print(f"{name:<16}{100 * r['success_rate']:>8.0f}%{cm:>10}{cd:>9}{r['error_median']:>9.3f}"
              f"{r['error_p90']:>9.3f}{100 * r['error_below_0.5m']:>9.0f}%")
    elapsed = time.perf_counter() - t0
    print(f"{n} tests per configuration, {elapsed:.1f} s")
    out = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
           "results": results, "seconds": elapsed}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    if args.plot:
        plot(results, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
