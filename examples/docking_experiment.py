"""The docking paper's experiment in simulation: coarse MCL, precise scan matching, similarity-rate switching.

The paper (Yilmaz and Temeltas, *Robotica* 2024; ``docs/background.md#references``)
drives an AMR to a docking target: a particle filter (SA-MCL) localizes it coarsely
during the *delivery* stage, a scan matcher precisely during the *docking* stage, and a decision node switches between them with
hysteresis on the correntropy similarity rate between the current scan and the
reference scan taken at the target (upper bound 0.75, lower 0.65). Here, simulated:

* **Map**: a 14 x 8 m factory hall (``OccupancyGrid``, 5 cm cells) with four shelves,
  two pillars and a U-shaped docking bay in the right wall; four boxes (pallets, a cart)
  stand in the hall that no map has; the laser sees this world exactly (ray casting).
  The coarse localizer's map is a SLAM-like copy: 10 cm cells (the paper's resolution
  for large areas), stretched by 1 % about the hall's centre, shelves displaced by up
  to 15 cm. (With a perfect map the simulated MCL is accurate to 1 cm, far from the
  paper's 10-15 cm.)
* **Robot**: follows waypoints at 0.3 m/s (0.1 m/s for the last metre), turns in place
  at 0.5 rad/s; odometry with 3 % translation and 2 % + 0.5 deg/m rotation noise. Laser:
  720 beams over 360 deg (front + rear scanners), 8 m range (SICK LMS200's 8 m mode),
  1.5 cm noise; the reference scan at the target is recorded once with the same noise.
* **Cases** (the paper's Fig. 9): 1, a start close to the target but facing away; 2, a
  long drive from the far end; 3, a drive from the other corner ending with a backward
  docking (target heading pi).
* **Coarse**: :class:`~dfusion.localization.MonteCarloLocalization` (likelihood field,
  200-800 particles with KLD, 40 beams, ROS AMCL's default odometry noise), started
  around the true pose (20 cm, 5 deg).
* **Precise** ("SM"): point-to-line ICP (:class:`~dfusion.localization.ScanMatcher`) of
  the current scan against the *reference scan* taken at the target, started from the
  current pose estimate moved by odometry; the pose is ``target (+) match``.
* **Switching** ("SW"): :class:`~dfusion.policies.HysteresisSwitchingPolicy` (0.75 / 0.65)
  on :class:`~dfusion.localization.SimilarityRate` (grid lookup, built once per target),
  computed from the current scan and the transform implied by the previous output
  moved by odometry. Only the localizer the decision needs is run for the output; the
  MCL keeps running in the background in this simulation (so that a switch back, and
  the blended variant, have a coarse estimate; its cost is not counted in the docking
  region, as the paper deactivates it). Also: the same with a 1 s blended transition
  (:class:`~dfusion.policies.BlendedTransitionPolicy`, the paper's remedy (2) for jumps).

Outputs (the paper's Tables I and II): localization frequency from the measured compute
time per step of what each method runs (Table I); errors in x, y, xy [cm] and theta
[deg] (mean +- std) in the delivery region, the docking region (true distance to the
target below 1.5 m) and overall, and the docking error (pose error at the end) over the
trials (Table II); a PNG with one case's trajectory, similarity rate and errors.

Time step 0.2 s (5 Hz; 0.25 s with ``--quick``); trials per case 2 (1 with ``--quick``).

    .venv/bin/python examples/docking_experiment.py [--quick] [--trials N] [--out out/docking]
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


from dfusion.estimation import Estimate  # noqa: E402
from dfusion.errors import DfusionError  # noqa: E402
from dfusion.models import LaserConfig
from dfusion.localization import MonteCarloLocalization, scan_to_points, ScanMatcher
from dfusion.geometry import se2_between, se2_compose
from dfusion.maps import cast_rays, OccupancyGrid  # noqa: E402
from dfusion.geometry import wrap_angle  # noqa: E402
from dfusion.policies import BlendedTransitionPolicy, HysteresisSwitchingPolicy
from dfusion.localization import SimilarityRate

RES = 0.05
LASER = LaserConfig.uniform(720, 2 * math.pi, 8.0)     # SICK LMS200 in its 8 m mode
RANGE_NOISE = 0.015
DOCK_RADIUS = 1.5


SHELVES = ((2.5, 1.6), (2.5, 5.8), (6.5, 1.6), (6.5, 5.8))
#: Objects in the world that neither map nor reference scan has (pallets, a parked cart).
CLUTTER = ((4.6, 3.0, 0.5, 0.4), (8.8, 4.9, 0.4, 0.4), (1.6, 4.6, 0.6, 0.5), (9.6, 2.6, 0.5, 0.5))


def factory_map(res: float = RES, *, scale: float = 1.0, shelf_shift: float = 0.0, clutter: bool = False,
                seed: int = 0) -> OccupancyGrid:
    """14 x 8 m hall, shelves, pillars and a docking bay in the right wall (x = 14, y = 3.4 .. 4.6).

    ``scale``, ``shelf_shift`` and ``clutter`` make the difference between the world and a
    map of it: a SLAM-like map is stretched by ``scale`` about the hall's centre and has
    its shelves displaced by up to ``shelf_shift`` m (random, ``seed``); the world has
    ``CLUTTER`` boxes that no map has.
    """
    pad = 0.5
    W, H = int(round((14 + 2 * pad) / res)), int(round((8 + 2 * pad) / res))
    d = np.full((H, W), -1, dtype=np.int8)
    rng = np.random.default_rng(seed)

    def fill(x0, y0, x1, y1, v):
        x0, x1 = 7.0 + scale * (x0 - 7.0), 7.0 + scale * (x1 - 7.0)
        y0, y1 = 4.0 + scale * (y0 - 4.0), 4.0 + scale * (y1 - 4.0)
        j0, j1 = int(round((x0 + pad) / res)), int(round((x1 + pad) / res))
        i0, i1 = int(round((y0 + pad) / res)), int(round((y1 + pad) / res))
        d[max(i0, 0):max(i1, 0), max(j0, 0):max(j1, 0)] = v

    fill(-0.2, -0.2, 14.2, 8.2, 100)
    fill(0, 0, 14, 8, 0)
    for x0, y0 in SHELVES:                                                 # shelves 2.4 x 0.6 m
        dx, dy = rng.uniform(-shelf_shift, shelf_shift, 2) if shelf_shift else (0.0, 0.0)
        fill(x0 + dx, y0 + dy, x0 + dx + 2.4, y0 + dy + 0.6, 100)
    fill(10.8, 6.6, 11.2, 7.0, 100)                                       # pillars
    fill(10.8, 0.9, 11.2, 1.3, 100)
    fill(13.2, 3.3, 14.0, 3.4, 100)                                       # docking bay walls
    fill(13.2, 4.6, 14.0, 4.7, 100)
    fill(13.7, 3.8, 14.0, 4.2, 100)                                       # the station's back
    if clutter:
        for x, y, w, h in CLUTTER:
            fill(x, y, x + w, y + h, 100)
    return OccupancyGrid(d, res, (-pad, -pad, 0.0))


@dataclass
class Case:
    name: str
    start: tuple[float, float, float]
    waypoints: list[tuple[float, float]]
    target: tuple[float, float, float]
    backward_last: bool = False


CASES = [
    Case("case 1: near, facing away", (10.8, 5.8, math.pi), [(10.0, 5.2), (11.6, 4.0)], (12.9, 4.0, 0.0)),
    Case("case 2: long drive", (0.8, 1.0, 0.0), [(5.5, 1.0), (5.5, 4.0), (11.6, 4.0)], (12.9, 4.0, 0.0)),
    Case("case 3: backward docking", (0.8, 7.0, 0.0), [(5.5, 7.0), (5.5, 4.0), (11.4, 4.0)], (12.9, 4.0, math.pi),
         backward_last=True),
]


def trajectory(case: Case, dt: float) -> np.ndarray:
    """Poses (K, 3): turn in place, drive straight, ..., final approach (backward if asked)."""
    speed, slow, turn = 0.3, 0.1, 0.5
    pose = np.array(case.start, dtype=float)
    out = [pose.copy()]
    pts = [np.array(p, float) for p in case.waypoints] + [np.array(case.target[:2])]
    for n, p in enumerate(pts):
        last = n == len(pts) - 1
        d = p - pose[:2]
        L = float(np.hypot(*d))
        heading = math.atan2(d[1], d[0])
        if last and case.backward_last:
            heading = wrap_angle(heading + math.pi)
        while abs(wrap_angle(heading - pose[2])) > 1e-9:                    # turn in place
            dth = float(wrap_angle(heading - pose[2]))
            pose[2] = wrap_angle(pose[2] + math.copysign(min(abs(dth), turn * dt), dth))
            out.append(pose.copy())
        u = d / max(L, 1e-12)
        s = 0.0
        while s < L - 1e-9:
            v = slow if (last and L - s < 1.0) else speed
            step = min(v * dt, L - s)
            s += step
            pose[:2] = pose[:2] + step * u
            out.append(pose.copy())
    tgt = np.array(case.target, float)
    while abs(wrap_angle(tgt[2] - pose[2])) > 1e-9:                          # final alignment
        dth = float(wrap_angle(tgt[2] - pose[2]))
        pose[2] = wrap_angle(pose[2] + math.copysign(min(abs(dth), turn * dt), dth))
        out.append(pose.copy())
    return np.array(out)


@dataclass
class Run:
    """One method's estimates and per-step compute times over a trial."""

    est: list = field(default_factory=list)
    t_loc: list = field(default_factory=list)     # seconds of localization compute per step
    t_sw: list = field(default_factory=list)      # seconds of switching compute per step
    stage: list = field(default_factory=list)
    rho: list = field(default_factory=list)
    switches: int = 0


def make_mcl(grid, start, rng) -> MonteCarloLocalization:
    mcl = MonteCarloLocalization(grid, LASER, min_particles=200, max_particles=800, max_beams=40, rng=rng)
    mcl.initialize_gaussian(start, np.diag([0.2**2, 0.2**2, math.radians(5) ** 2]), n=800, t=0.0)
    return mcl


def pose_cov(res) -> np.ndarray:
    return np.asarray(res.covariance, float)


def run_trial(case: Case, grid, coarse_grid, dt: float, seed: int):
    rng = np.random.default_rng(seed)
    truth = trajectory(case, dt)
    K = len(truth)
    target = np.array(case.target, float)
    ref_r = cast_rays(grid, target[None], LASER.angles, LASER.max_range)[0]
    ref_r = np.where(ref_r < LASER.max_range, ref_r + rng.normal(0, RANGE_NOISE, ref_r.shape), ref_r)
    ref = scan_to_points(ref_r, LASER.angles, LASER.max_range)      # recorded once at the target
    matcher = ScanMatcher(ref, "point_to_line", max_correspondence_distance=0.5, max_iterations=20,
                          trim_fraction=0.1, tolerance=1e-4)
    simrate = SimilarityRate(ref, nearest="grid")
    scans = cast_rays(grid, truth, LASER.angles, LASER.max_range)
    scans = np.where(scans < LASER.max_range, scans + rng.normal(0, RANGE_NOISE, scans.shape), scans)
    odo = [truth[0].copy()]
    for k in range(1, K):
        dlt = se2_between(truth[k - 1], truth[k])
        trans = math.hypot(dlt[0], dlt[1])
        noise = rng.normal(0, [0.03 * trans + 1e-4, 0.03 * trans + 1e-4, 0.02 * abs(dlt[2]) + math.radians(0.5) * trans])
        odo.append(se2_compose(odo[-1], dlt + noise))
    odo = np.array(odo)

    def sm_match(pts, guess):
        """Precise pose from a guess of the global pose: target (+) ICP(scan -> reference)."""
        t0 = time.perf_counter()
        try:
            r = matcher.match(pts, se2_between(target, guess))
            pose, cov = se2_compose(target, r.pose), pose_cov(r)
        except DfusionError:
            pose, cov = guess, np.eye(3)
        return pose, cov, time.perf_counter() - t0

    runs = {"SA-MCL (coarse only)": Run(), "SM (precise only)": Run(), "MCL + SM, switching": Run(),
            "MCL + SM, switching + 1 s blend": Run()}
    mcl_only = make_mcl(coarse_grid, truth[0], rng)
    mcl_bg = make_mcl(coarse_grid, truth[0], rng)
    sm_pose = truth[0].copy()
    hyst = HysteresisSwitchingPolicy("precise", "coarse", 0.75, 0.65)
    blend = BlendedTransitionPolicy(HysteresisSwitchingPolicy("precise", "coarse", 0.75, 0.65), duration=1.0,
                                    angle_indices=[2])
    out_prev = {"sw": truth[0].copy(), "bl": truth[0].copy()}
    for k in range(K):
        t = k * dt
        pts = scan_to_points(scans[k], LASER.angles, LASER.max_range)
        # ---- coarse only
        t0 = time.perf_counter()
        mcl_only.predict(t, odo[k])
        mcl_only.update(t, scans[k])
        e = mcl_only.estimate()
        r = runs["SA-MCL (coarse only)"]
        r.t_loc.append(time.perf_counter() - t0)
        r.est.append(e.mean)
        # ---- precise only (from the true start, odometry as the guess)
        inc = se2_between(odo[k - 1], odo[k]) if k else np.zeros(3)
        sm_pose, _, ts = sm_match(pts, se2_compose(sm_pose, inc))
        r = runs["SM (precise only)"]
        r.t_loc.append(ts)
        r.est.append(sm_pose)
        # ---- switching (and the blended variant): coarse in the background
        t0 = time.perf_counter()
        mcl_bg.predict(t, odo[k])
        mcl_bg.update(t, scans[k])
        eb = mcl_bg.estimate()
        t_mcl = time.perf_counter() - t0
        coarse = Estimate("coarse", t, eb.mean, eb.cov, eb.reliability)
        for key, label, pol in (("sw", "MCL + SM, switching", hyst), ("bl", "MCL + SM, switching + 1 s blend", blend)):
            r = runs[label]
            inner = pol if isinstance(pol, HysteresisSwitchingPolicy) else pol.inner
            guess = se2_compose(out_prev[key], inc)
            t0 = time.perf_counter()
            rho = simrate(pts, se2_between(target, guess))
            stage = inner.next_stage(rho)
            t_sw = time.perf_counter() - t0
            srcs = [coarse]
            t_sm = 0.0
            if stage == "high" or inner.stage == "high" or (key == "bl" and pol.blending):
                # the precise localizer runs, started from the previous output moved by odometry
                p, c, t_sm = sm_match(pts, guess)
                srcs.append(Estimate("precise", t, p, c, 1.0))
            t0 = time.perf_counter()
            inner.set_signal(rho)
            out = pol.decide(Estimate("fused", t, guess, np.eye(3), 0.0), srcs)
            t_sw += time.perf_counter() - t0
            out_prev[key] = np.asarray(out.mean, float)
            r.est.append(out_prev[key])
            r.t_loc.append(t_sm if inner.stage == "high" else t_mcl)
            r.t_sw.append(t_sw)
            r.stage.append(inner.stage)
            r.rho.append(rho)
            r.switches = len(inner.switches)
    return truth, runs


def errors(truth: np.ndarray, est: np.ndarray) -> np.ndarray:
    d = est - truth
    return np.column_stack([np.abs(d[:, 0]) * 100, np.abs(d[:, 1]) * 100, np.hypot(d[:, 0], d[:, 1]) * 100,
                            np.degrees(np.abs(wrap_angle(d[:, 2])))])


def ms(x) -> str:
    x = np.asarray(x)
    return f"{x.mean():.2f} +- {x.std():.2f}" if x.size else "-"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one trial per case at dt = 0.25 s")
    ap.add_argument("--trials", type=int, default=None, help="trials per case (default 2, quick 1)")
    ap.add_argument("--dt", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("out/docking"))
    a = ap.parse_args(argv)
    trials = a.trials or (1 if a.quick else 2)
    dt = a.dt or (0.25 if a.quick else 0.2)
    t_start = time.perf_counter()
    grid = factory_map(clutter=True)                                   # the world
    coarse_grid = factory_map(0.10, scale=1.01, shelf_shift=0.15, seed=7)   # the coarse localizer's map
    methods = ["SA-MCL (coarse only)", "SM (precise only)", "MCL + SM, switching", "MCL + SM, switching + 1 s blend"]
    regions = {m: {"delivery": [], "docking": [], "overall": []} for m in methods}
    docking = {m: [] for m in methods}
    rates = {m: {"delivery": [], "docking": [], "overall": []} for m in methods}
    switch_info = []
    example = None
    for ci, case in enumerate(CASES):
        for tr in range(trials):
            truth, runs = run_trial(case, grid, coarse_grid, dt, a.seed * 1000 + ci * 100 + tr)
            dist = np.hypot(*(truth[:, :2] - np.array(case.target[:2])).T)
            dock = dist < DOCK_RADIUS
            for m in methods:
                r = runs[m]
                E = errors(truth, np.array(r.est))
                regions[m]["delivery"].append(E[~dock])
                regions[m]["docking"].append(E[dock])
                regions[m]["overall"].append(E)
                docking[m].append(E[-1])
                tot = np.array(r.t_loc) + (np.array(r.t_sw) if r.t_sw else 0.0)
                rates[m]["delivery"].append(tot[~dock])
                rates[m]["docking"].append(tot[dock])
                rates[m]["overall"].append(tot)
            sw = runs["MCL + SM, switching"]
            st = np.array(sw.stage)
            first = int(np.argmax(st == "high")) if (st == "high").any() else -1
            switch_info.append((case.name, tr, sw.switches, float(dist[first]) if first >= 0 else float("nan"),
                                float(np.mean(sw.t_sw) * 1e3)))
            if example is None and ci == 1:
                example = (case, truth, runs)

    print(f"{len(CASES)} cases x {trials} trial(s), dt = {dt} s, laser 720 beams; docking region: within "
          f"{DOCK_RADIUS} m of the target\n")
    print("Switching: first switch to precise localization (distance to the target) and switches per trial")
    for name, tr, n, d, tsw in switch_info:
        print(f"  {name}, trial {tr}: {n} switches, first at {d:.2f} m, decision {tsw:.2f} ms per step")
    print()
    print("Table I (simulated): localization frequency [Hz] from the measured compute time per step")
    print("| method | delivery region | docking region | overall | compute per step |")
    print("|---|---|---|---|---|")
    for m in methods:
        row = [m]
        for reg in ("delivery", "docking", "overall"):
            t = np.concatenate(rates[m][reg])
            row.append(f"{1.0 / t.mean():.0f}" if t.size else "-")
        t = np.concatenate(rates[m]["overall"]) * 1e3
        row.append(f"{t.mean():.1f} ms")
        print("| " + " | ".join(row) + " |")
    print()
    print("Table II (simulated): localization error, mean +- std [cm] or [deg]")
    print("| region | error | " + " | ".join(methods) + " |")
    print("|---|---|" + "---|" * len(methods))
    for reg in ("delivery", "docking", "overall"):
        for j, lab in enumerate(("x", "y", "xy", "theta")):
            cells = [ms(np.concatenate(regions[m][reg])[:, j]) for m in methods]
            print(f"| {reg if j == 0 else ''} | {lab} | " + " | ".join(cells) + " |")
    for j, lab in enumerate(("x", "y", "xy", "theta")):
        cells = [ms(np.array(docking[m])[:, j]) for m in methods]
        print(f"| docking (final pose, {len(docking[methods[0]])} trials) | {lab} | " + " | ".join(cells) + " |")
    print("\nPaper, Table II, docking region xy: SA-MCL 14.05 +- 7.11 cm, SA-MCL + SM 0.71 +- 0.63 cm; overall xy "
          "14.51 +- 7.02 / 10.81 +- 5.13 cm; Table I: 15.1 Hz / 9.4 Hz overall, SW ~3 ms")
    if example is not None:
        plot(a.out, *example, grid)
        print(f"\nplot: {a.out / 'docking.png'}")
    print(f"({time.perf_counter() - t_start:.1f} s)")
    return 0


def plot(out: Path, case: Case, truth, runs, grid) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.5))
    ax = axes[0]
    H, W = grid.shape
    ax.imshow(grid.data, origin="lower", cmap="gray_r",
              extent=[grid.origin[0], grid.origin[0] + W * grid.resolution, grid.origin[1], grid.origin[1] + H * grid.resolution])
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.5, label="ground truth")
    for m, st in (("SA-MCL (coarse only)", "C0--"), ("SM (precise only)", "C1:"), ("MCL + SM, switching", "C2-")):
        e = np.array(runs[m].est)
        ax.plot(e[:, 0], e[:, 1], st, lw=1, label=m)
    ax.plot(*case.target[:2], "r*", ms=10, label="target")
    ax.set_title(case.name)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    # below the map: inside it the legend hides the start of the drive
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, frameon=False)
    sw = runs["MCL + SM, switching"]
    t = np.arange(len(sw.rho))
    ax = axes[1]
    ax.plot(t, sw.rho, "C2-", label="similarity rate")
    ax.axhline(0.75, color="k", ls="--", lw=0.8, label="upper bound 0.75 (to precise)")
    ax.axhline(0.65, color="k", ls=":", lw=0.8, label="lower bound 0.65 (to coarse)")
    ax.fill_between(t, 0, 1, where=np.array(sw.stage) == "high", color="C2", alpha=0.15, label="precise active")
    ax.set_ylim(0, 1)
    ax.set_xlabel("step")
    ax.set_ylabel("similarity rate")
    ax.set_title("Fig. 12(a) (simulated): similarity rate and stage")
    ax.legend(fontsize=7, loc="upper left")
    ax = axes[2]
    dist = np.hypot(*(truth[:, :2] - np.array(case.target[:2])).T)
    for m, st in (("SA-MCL (coarse only)", "C0--"), ("SM (precise only)", "C1:"), ("MCL + SM, switching", "C2-"),
                  ("MCL + SM, switching + 1 s blend", "C3-.")):
        E = errors(truth, np.array(runs[m].est))
        ax.semilogy(dist, np.maximum(E[:, 2], 1e-2), st, lw=1, label=m)
    ax.invert_xaxis()
    ax.set_xlabel("distance to the target [m]")
    ax.set_ylabel("position error [cm]")
    ax.set_title("errors on the way to the target")
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "docking.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
