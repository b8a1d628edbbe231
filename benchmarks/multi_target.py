"""Multi-target tracking on the plaza: dfusion's centralized tracker (JPDA, GNN) beside Stone Soup's.

On identical detections (``dfusion.sim.plaza``: 40 x 30 m, people crossing, births and
deaths at the edges, 10 Hz, std 0.3 m, P_D 0.9, 3 false detections per frame per plaza
area), for each seed and camera layout (one view of the whole plaza; three cameras with
overlapping views, fed one scan per camera in turn):

* dfusion ``MultiTargetTracker`` with JPDA (EHM) and with GNN, M-of-N two-point initiation,
  miss / staleness deletion;
* Stone Soup 1.9.1 ``JPDAwithEHM`` with ``MultiTargetMixtureTracker`` and
  ``GNNWith2DAssignment`` with ``MultiTargetTracker`` (its tutorials' components:
  ``PDAHypothesiser`` / ``DistanceHypothesiser``, ``MultiMeasurementInitiator``,
  ``CovarianceBasedDeleter``), with the same motion model, noise, P_D, clutter density and gate.

Metrics per frame after every scan of the frame: GOSPA (c = 2 m, p = 1, alpha = 2) and its
parts, CLEAR MOT / IDF1 (match within 1 m), CPU time (``time.process_time``) of the
tracker per frame. A second table: dfusion's CPU per frame against the number of people.

Stone Soup is not a dependency of dfusion: this script installs it into the running
interpreter's environment with pip (``stonesoup==1.9.1``) when it is missing.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import gc
import importlib
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dfusion.metrics import gospa, identity_metrics
from dfusion.models import ConstantVelocity
from dfusion.sim.plaza import CameraView, PlazaConfig, PlazaWorld, plaza_cameras, simulate_plaza
from dfusion.tracking import (GNN, JPDA, AnyDeleter, MissDeleter, MofNInitiator, MultiTargetTracker, RegionDeleter,
                              StaleDeleter, TrackHistory)
from dfusion.viz import plot_identity_timeline, plot_tracks_topdown, record_tracks_mcap

#: One setting for the family (chosen once on seed 0 of the one-view layout, never per seed).
Q = 0.05                # acceleration noise spectral density of every tracker's motion model (m^2/s^3)
GATE = 0.99
VELOCITY_STD = 1.5      # prior std of a person's velocity per axis (m/s), for both libraries' initiators
C, P_ORDER, MATCH = 2.0, 1.0, 1.0
STONESOUP = "stonesoup==1.9.1"
NODE = "central"        # the one (centralized) node of every tracker's history


def ensure_stonesoup() -> None:
    try:
        importlib.import_module("stonesoup")
    except ImportError:
        print(f"installing {STONESOUP} (benchmark only, not a dfusion dependency) ...", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", STONESOUP], check=True)
        importlib.invalidate_caches()


# --- trackers: each maps a world to its tracks over time (a TrackHistory) and CPU seconds per frame ------------


def run_dfusion(world: PlazaWorld, association: str) -> tuple[TrackHistory, np.ndarray]:
    motion = ConstantVelocity(2, Q)
    c = world.config
    whole = CameraView("plaza", 0.0, c.width, 0.0, c.height)

    def plaza(x: np.ndarray) -> bool:
        return whole.contains(x)

    tracker = MultiTargetTracker(motion, JPDA() if association == "jpda" else GNN(),
                                 MofNInitiator(motion, m=3, n=5, gate=GATE, velocity_std=VELOCITY_STD),
                                 AnyDeleter(MissDeleter(5), StaleDeleter(0.45), RegionDeleter(plaza)), origin="central")
    history, cpu = TrackHistory(), np.zeros(len(world.times))
    for k in range(len(world.times)):
        scans = world.scans(k)
        t0 = time.process_time()
        for scan in scans:
            tracker.step(scan)
        cpu[k] = time.process_time() - t0
        history.record(NODE, float(world.times[k]), tracker.estimates())
    return history, cpu


def run_stonesoup(world: PlazaWorld, association: str) -> tuple[TrackHistory, np.ndarray]:
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.dataassociator.probability import JPDAwithEHM
    from stonesoup.deleter.error import CovarianceBasedDeleter
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.simple import MultiTargetMixtureTracker, MultiTargetTracker as SSMultiTargetTracker
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import KalmanUpdater

    c = world.config
    transition = CombinedLinearGaussianTransitionModel([SSConstantVelocity(Q), SSConstantVelocity(Q)])
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.eye(2) * c.std**2)
    predictor = KalmanPredictor(transition)
    updater = KalmanUpdater(measurement)
    epoch = _dt.datetime(2026, 1, 1)
    stamps = [epoch + _dt.timedelta(seconds=float(t)) for t in world.times]

    def scans():
        for k, frames in enumerate(world.frames):
            for f in frames:
                yield stamps[k], {Detection(z.reshape(2, 1), timestamp=stamps[k], measurement_model=measurement)
                                  for z in f.z}

    deleter = CovarianceBasedDeleter(covar_trace_thresh=1.0, mapping=[0, 2])
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([0.0, VELOCITY_STD**2, 0.0, VELOCITY_STD**2])),
        measurement_model=measurement, deleter=UpdateTimeStepsDeleter(3 * len(c.cameras)),
        data_associator=GNNWith2DAssignment(DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=3)),
        updater=updater, min_points=3)
    if association == "jpda":
        hyp = PDAHypothesiser(predictor, updater, c.clutter_density, prob_detect=c.detection, prob_gate=GATE)
        tracker = MultiTargetMixtureTracker(initiator=initiator, deleter=deleter, detector=scans(),
                                            data_associator=JPDAwithEHM(hyp), updater=updater)
    else:
        hyp = DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=3)
        tracker = SSMultiTargetTracker(initiator=initiator, deleter=deleter, detector=scans(),
                                       data_associator=GNNWith2DAssignment(hyp), updater=updater)
    it = iter(tracker)
    per_frame = len(c.cameras)
    history, cpu = TrackHistory(), np.zeros(len(world.times))
    order = [0, 2, 1, 3]      # Stone Soup's [x, vx, y, vy] -> [x, y, vx, vy]
    for k in range(len(world.times)):
        t0 = time.process_time()
        for _ in range(per_frame):
            _, tracks = next(it)
        cpu[k] = time.process_time() - t0
        history.record(NODE, float(world.times[k]),
                       [(x.id, np.asarray(x.state_vector, float).ravel()[order],
                         np.asarray(x.covar, float)[np.ix_(order, order)]) for x in sorted(tracks, key=lambda x: x.id)])
    return history, cpu


TRACKERS = {
    "dfusion JPDA": lambda w: run_dfusion(w, "jpda"),
    "dfusion GNN": lambda w: run_dfusion(w, "gnn"),
    "Stone Soup JPDA (EHM)": lambda w: run_stonesoup(w, "jpda"),
    "Stone Soup GNN": lambda w: run_stonesoup(w, "gnn"),
}


@dataclass
class Row:
    layout: str
    seed: int
    tracker: str
    gospa: float
    loc: float
    missed: float
    false: float
    idf1: float
    mota: float
    switches: int
    cpu_ms: float
    targets: float


def evaluate(layout: str, seed: int, name: str, world: PlazaWorld) -> tuple[Row, TrackHistory]:
    gc.collect()
    history, cpu = TRACKERS[name](world)
    frames = history.frames(NODE, world.truth_paths(), world.times)
    parts = np.array([[g.distance, g.localization, g.missed, g.false] for g in
                      (gospa(f.truth, f.tracks, C, P_ORDER) for f in frames)])
    ids = identity_metrics(frames, MATCH)
    mean = parts.mean(axis=0)
    return Row(layout, seed, name, *mean, ids.idf1, ids.mota, ids.switches, 1e3 * float(np.mean(cpu)),
               float(np.mean([len(t) for t in world.truth]))), history


def save_figures(directory: Path, layout: str, name: str, world: PlazaWorld, history: TrackHistory) -> None:
    """The top-down view, the identity timeline and the MCAP recording of one run (``--figures``)."""
    c = world.config
    stem = f"{name.split(' (')[0].replace(' ', '-').lower()}_{layout.replace(' ', '-')}_seed{c.seed}"
    truth = world.truth_paths()
    what = f"{name}, {layout}, seed {c.seed}, {c.duration:.0f} s"
    views = c.cameras if len(c.cameras) > 1 else ()          # one view is the whole plaza: its outline
    paths = [plot_tracks_topdown(history, truth, directory / f"topdown_{stem}.png", views=views,
                                 region=(0.0, c.width, 0.0, c.height), title=f"{what}: tracks and truth, top-down"),
             plot_identity_timeline(history, truth, directory / f"timeline_{stem}.png", threshold=MATCH,
                                    title=f"{what}: identity timeline (a track is on a person within {MATCH:g} m)")[0],
             record_tracks_mcap(history, directory / f"tracks_{stem}.mcap", truth, views=views)]
    print("wrote " + ", ".join(str(p) for p in paths))


def accuracy_table(rows: list[Row]) -> None:
    print("| layout | seed | tracker | GOSPA (m) | localization | missed | false | IDF1 | MOTA | switches | CPU/frame (ms) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r.layout} | {r.seed} | {r.tracker} | {r.gospa:.3f} | {r.loc:.3f} | {r.missed:.3f} | {r.false:.3f} | "
              f"{r.idf1:.3f} | {r.mota:.3f} | {r.switches} | {r.cpu_ms:.2f} |")


def summary(rows: list[Row], strict: bool) -> bool:
    ok = True
    goals = []
    print("\n| layout | tracker | mean GOSPA (m) | GOSPA / Stone Soup JPDA (per seed) | IDF1 (min) | switches (total) | CPU/frame (ms) | CPU / Stone Soup JPDA |")
    print("|---|---|---|---|---|---|---|---|")
    for layout in dict.fromkeys(r.layout for r in rows):
        ref = {r.seed: r for r in rows if r.layout == layout and r.tracker == "Stone Soup JPDA (EHM)"}
        for name in TRACKERS:
            rs = [r for r in rows if r.layout == layout and r.tracker == name]
            if not rs:
                continue
            ratios = [r.gospa / ref[r.seed].gospa for r in rs if r.seed in ref]
            cpu_ratio = np.median([r.cpu_ms / ref[r.seed].cpu_ms for r in rs if r.seed in ref]) if ref else float("nan")
            print(f"| {layout} | {name} | {np.mean([r.gospa for r in rs]):.3f} | "
                  f"{' / '.join(f'{x:.2f}' for x in ratios)} | {min(r.idf1 for r in rs):.3f} | "
                  f"{sum(r.switches for r in rs)} | {np.mean([r.cpu_ms for r in rs]):.2f} | {cpu_ratio:.2f} |")
            if name == "dfusion JPDA" and ref:
                good_gospa = max(ratios) <= 0.95
                good_switches = all(r.switches <= ref[r.seed].switches for r in rs)
                ok &= good_gospa and good_switches
                goals.append(f"goal ({layout}): dfusion JPDA GOSPA <= 0.95 x Stone Soup JPDA on every seed: "
                      f"{'PASS' if good_gospa else 'FAIL'}; identity switches <= Stone Soup JPDA's on every seed "
                      f"({' / '.join(f'{r.switches} vs {ref[r.seed].switches}' for r in rs)}): "
                      f"{'PASS' if good_switches else 'FAIL'}")
    print("\n".join(["", *goals]))
    return ok


def scaling_table(people: list[int], duration: float, seed: int) -> bool:
    print("\n| people (set) | targets present (mean) | tracker | CPU/frame (ms) | CPU per target (ms) |")
    print("|---|---|---|---|---|")
    per_target = {}
    for n in people:
        world = simulate_plaza(PlazaConfig(n_people=n, duration=duration, seed=seed))
        present = float(np.mean([len(t) for t in world.truth]))
        for name in ("dfusion JPDA", "dfusion GNN"):
            gc.collect()
            _, cpu = TRACKERS[name](world)
            ms = 1e3 * float(np.mean(cpu))
            per_target.setdefault(name, []).append(ms / max(present, 1.0))
            print(f"| {n} | {present:.1f} | {name} | {ms:.2f} | {ms / max(present, 1.0):.3f} |")
    ok = True
    for name, v in per_target.items():
        growth = v[-1] / min(v)
        good = growth <= 1.5
        ok &= good
        print(f"goal: {name} CPU per target at {people[-1]} people <= 1.5 x its smallest (at most linear): "
              f"{growth:.2f} {'PASS' if good else 'FAIL'}")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, 10 s, small scaling table")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--people", type=int, default=8)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--cameras", type=int, nargs="+", default=[1, 3], help="camera layouts (1, 3 or 6 views)")
    ap.add_argument("--no-stonesoup", action="store_true", help="dfusion only")
    ap.add_argument("--strict", action="store_true", help="exit status 1 when a goal is not met")
    ap.add_argument("--figures", type=Path, metavar="DIR",
                    help="save the top-down view, the identity timeline (PNG) and the tracks (MCAP) of every "
                         "dfusion tracker on seed 0 of each layout to DIR")
    args = ap.parse_args()
    seeds = 1 if args.quick else args.seeds
    duration = 10.0 if args.quick else args.duration
    print(f"load average at start: {os.getloadavg()[0]:.2f}; python {sys.version.split()[0]}, numpy {np.__version__}")
    if not args.no_stonesoup:
        ensure_stonesoup()
        import stonesoup
        print(f"stonesoup {stonesoup.__version__}")
    else:
        for name in [n for n in TRACKERS if n.startswith("Stone Soup")]:
            del TRACKERS[name]
    rows = []
    for ncam in args.cameras:
        layout = "1 view" if ncam == 1 else f"{ncam} cameras"
        for seed in range(seeds):
            world = simulate_plaza(PlazaConfig(n_people=args.people, duration=duration, seed=seed,
                                               cameras=plaza_cameras(ncam)))
            for name in TRACKERS:
                row, history = evaluate(layout, seed, name, world)
                rows.append(row)
                if args.figures is not None and seed == 0 and name.startswith("dfusion"):
                    save_figures(args.figures, layout, name, world, history)
    print(f"\n{args.people} people set, {duration:.0f} s, 10 Hz, std 0.3 m, P_D 0.9, 3 false per frame per plaza area; "
          f"mean targets present {np.mean([r.targets for r in rows]):.1f}; GOSPA c = {C} m, p = {P_ORDER:g}, "
          f"alpha = 2; match within {MATCH} m\n")
    accuracy_table(rows)
    ok = summary(rows, args.strict)
    ok &= scaling_table([2, 5, 10] if args.quick else [1, 5, 10, 20, 30], 5.0 if args.quick else 20.0, 0)
    return 1 if (args.strict and not ok) else 0


if __name__ == "__main__":
    sys.exit(main())
