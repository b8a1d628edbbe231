#!/usr/bin/env python
"""Track a BLE beacon with the WSN particle filter on the position-annotated BLE RSSI dataset.

Usage::

    python examples/ble_rssi_tracking.py TRACK_FILE [--dataset DIR] [--json OUT]
    python examples/ble_rssi_tracking.py --all --dataset DIR [--json OUT]

``TRACK_FILE`` is a ``trk/*_all_sensors.mbd`` file of the dataset (GitHub
``philotuxo/Position-Annotated-BLE-RSSI-Dataset``, CC0; see docs/wsn.md for the
citation). ``DIR`` is the dataset directory (``cnf/``, ``occ/``, ``trk/``); by
default the directory that holds ``TRACK_FILE``'s ``trk/`` folder. The dataset is
not bundled: give its path. ``tests/data/ble_rssi`` is a one-track slice.

For each track the tracker (dfusion.localization.WSNTracker) runs packet by packet and, in
the same run and at the same instants, a causal weighted-centroid baseline
(RSSI averaged over the last ``--window`` s per receiver, weights
``10^(rssi/10)``). Both are compared with the ground truth of every row.

Measurement model (``--model``): ``radio-map`` (default) is a per-receiver
log-distance fit with azimuthal harmonics (a directional gain) plus a kernel-smoothed map
of its residuals over the floor, with a spatial spread and a split-normal (left-skewed)
noise law (dfusion.localization.radio_map; docs/wsn.md sec. 3); ``path-loss`` is the log-distance
fit alone. Calibration is never taken from the track being evaluated:
``--path-loss FILE`` / ``--radio-map FILE`` if given (refused if the file lists the
track); otherwise fitted on the *other* tracks in ``DIR/trk`` (leave-one-track-out);
otherwise ``DIR/path_loss.json`` / ``DIR/radio_map.npz``.

Radio-map settings (harmonic order and ridge, kernel bandwidth, prior weight) that are
not given on the command line are chosen for each evaluated track from a grid
(``dfusion.datasets.ble_rssi.MAP_SETTINGS_GRID``) by leave-one-track-out predictive
density *among its calibration tracks* (each calibration track predicted by a map of the
others); the noise law is fitted to those held-out residuals. The evaluated track takes
no part in either, so the reported errors are those of a nested leave-one-track-out
evaluation. With a single calibration track there is nothing to cross-validate: the
settings then default to ``SINGLE_TRACK_MAP`` with Gaussian noise.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from dfusion.datasets import BLERSSIDataset, find_dataset_root
from dfusion.localization import calibrate_path_loss, PathLossCalibration, run_tracker, weighted_centroid
from dfusion.metrics import error_stats
from dfusion.localization import calibrate_radio_map, MAP_SETTINGS_GRID, select_radio_map_settings
from dfusion.errors import DfusionError
from dfusion.models import RSSISensor
from dfusion.localization import RadioMap, WSNTracker

#: Defaults of the tracker (see docs/wsn.md for how they were chosen). A radio-map setting of
#: None is chosen per evaluated track from MAP_SETTINGS_GRID (see the module docstring).
DEFAULTS = dict(particles=5000, motion="random_walk", q=0.5, grid_cell=0.2, window=2.0, seed=0,
                model="radio-map", map_order=None, map_ridge=None, map_bandwidth=None, map_prior_weight=None,
                map_noise="split-normal")
#: Radio-map settings when only one calibration track is available (no cross-validation possible).
SINGLE_TRACK_MAP = dict(order=0, ridge=100.0, bandwidth=1.0, prior_weight=0.05)
MODELS = ("radio-map", "path-loss")
MAP_KEYS = ("order", "ridge", "bandwidth", "prior_weight")


def calibration_for(ds: BLERSSIDataset, track_name: str, path_loss: Path | None,
                    cache: dict | None = None, per_receiver: bool = True) -> PathLossCalibration:
    """Path-loss calibration that does not use ``track_name`` (see the module docstring)."""
    if path_loss is not None:
        cal = PathLossCalibration.from_json(json.loads(Path(path_loss).read_text()), ds.receiver_macs)
        if track_name in cal.tracks:
            raise DfusionError(f"{path_loss} was fitted on {track_name} itself; refusing an in-sample calibration")
        return cal
    others = [n for n in ds.track_names() if n != track_name]
    if others:
        cache = {} if cache is None else cache
        tracks = [cache.setdefault(n, ds.load_track(n)) for n in others]
        return calibrate_path_loss(tracks, ds.receiver_positions, ds.receiver_macs, per_receiver=per_receiver)
    stored = ds.root / "path_loss.json"
    if stored.is_file():
        cal = PathLossCalibration.from_json(json.loads(stored.read_text()), ds.receiver_macs)
        if track_name in cal.tracks:
            raise DfusionError(f"{stored} was fitted on {track_name} itself; refusing an in-sample calibration")
        return cal
    raise DfusionError(f"no calibration for {track_name}: {ds.root / 'trk'} holds no other track and there is "
                       f"no {stored}; pass --path-loss FILE")


def radio_map_for(ds: BLERSSIDataset, track_name: str | None, radio_map: Path | None, cache: dict | None = None,
                  settings: dict | None = None, noise: str = DEFAULTS["map_noise"],
                  spatial_std: bool = True) -> RadioMap:
    """Radio map that does not use ``track_name``: ``radio_map`` FILE (.npz), else fitted on the other
    tracks in ``DIR/trk`` (leave-one-track-out), else ``DIR/radio_map.npz``; refused if its
    provenance lists ``track_name`` (None: no track is evaluated, every track may be used).

    ``settings`` maps ``order``, ``ridge``, ``bandwidth``, ``prior_weight`` to a value, or to None
    (or leaves them out) to choose them from :data:`MAP_SETTINGS_GRID` by leave-one-track-out
    predictive density among the calibration tracks (:func:`select_radio_map_settings`).
    ``noise``: ``"split-normal"`` (fitted to held-out residuals of the calibration tracks) or
    ``"gaussian"``. The chosen settings are recorded in ``RadioMap.settings``.
    """
    settings = {k: v for k, v in (settings or {}).items() if v is not None}
    if radio_map is not None:
        rmap, src = RadioMap.from_npz(radio_map), Path(radio_map)
    else:
        others = [n for n in ds.track_names() if n != track_name]
        if others:
            cache = {} if cache is None else cache
            tracks = [cache.setdefault(n, ds.load_track(n)) for n in others]
            kw = dict(limits=ds.limits, spatial_std=spatial_std, exclude=track_name)
            if len(tracks) >= 2:
                grid = {k: (settings[k],) if k in settings else MAP_SETTINGS_GRID[k] for k in MAP_KEYS}
                best, table = select_radio_map_settings(tracks, ds.receiver_positions, ds.receiver_macs,
                                                        grid=grid, noise=noise, **kw)
                chosen, law = {k: best[k] for k in MAP_KEYS}, best["noise"]
                how = "selected" if len(table) > 1 else "given"
            else:  # one calibration track: no held-out data to choose settings or fit the noise law
                chosen, law, how = {k: settings.get(k, v) for k, v in SINGLE_TRACK_MAP.items()}, None, "single-track"
            rmap = calibrate_radio_map(tracks, ds.receiver_positions, ds.receiver_macs, order=chosen["order"],
                                       ridge=chosen["ridge"], bandwidth=chosen["bandwidth"],
                                       prior_weight=chosen["prior_weight"], noise=law, **kw)[0]
            rmap.settings["how"] = how
            return rmap
        src = ds.root / "radio_map.npz"
        if not src.is_file():
            raise DfusionError(f"no radio-map calibration for {track_name}: {ds.root / 'trk'} holds no other "
                               f"track and there "
                               f"is no {src}; pass --radio-map FILE or --model path-loss")
        rmap = RadioMap.from_npz(src)
    if track_name in rmap.tracks:
        raise DfusionError(f"{src} was learnt from {track_name} itself; refusing an in-sample calibration")
    rmap.settings["how"] = f"file {src.name}"
    return rmap


def evaluate_track(ds: BLERSSIDataset, track_file: str | Path, *, particles: int = DEFAULTS["particles"],
                   motion: str = DEFAULTS["motion"], q: float = DEFAULTS["q"],
                   grid_cell: float | None = DEFAULTS["grid_cell"], window: float = DEFAULTS["window"],
                   seed: int = DEFAULTS["seed"], path_loss: Path | None = None, cache: dict | None = None,
                   per_receiver: bool = True, model: str = DEFAULTS["model"], radio_map: Path | None = None,
                   map_order: int | None = DEFAULTS["map_order"], map_ridge: float | None = DEFAULTS["map_ridge"],
                   map_bandwidth: float | None = DEFAULTS["map_bandwidth"],
                   map_prior_weight: float | None = DEFAULTS["map_prior_weight"],
                   map_noise: str = DEFAULTS["map_noise"], map_spatial_std: bool = True,
                   **tracker_kw) -> dict:
    """Run the tracker and the baseline on one track; returns metrics and the per-row errors.

    ``map_*`` settings left at None are chosen on the calibration tracks (:func:`radio_map_for`).
    """
    if model not in MODELS:
        raise DfusionError(f"model must be one of {MODELS}, got {model!r}")
    track = ds.load_track(track_file)
    map_settings = None
    if model == "radio-map":
        rmap = radio_map_for(ds, track.name, radio_map, cache,
                             dict(order=map_order, ridge=map_ridge, bandwidth=map_bandwidth,
                                  prior_weight=map_prior_weight), map_noise, map_spatial_std)
        # The map holds the whole measurement model; the sensor only places the receivers.
        sensors, cal_tracks = RSSISensor(ds.receiver_positions, -60.0, 2.0, 5.0), rmap.tracks
        tracker_kw["radio_map"] = rmap
        map_settings = dict(rmap.settings, noise=None if rmap.noise is None else list(rmap.noise))
    else:
        cal = calibration_for(ds, track.name, path_loss, cache, per_receiver)
        sensors, cal_tracks = cal.sensors(ds.receiver_positions), cal.tracks
    grid = ds.load_grid(grid_cell) if grid_cell else None
    tracker = WSNTracker(sensors, particles, motion=motion, q=q, grid=grid,
                         bounds=None if grid is not None else ds.limits, seed=seed, **tracker_kw)
    t0 = time.perf_counter()
    cov = np.empty((len(track), 2, 2))
    est = run_tracker(track, tracker, cov_out=cov)
    elapsed = time.perf_counter() - t0
    base = weighted_centroid(track, ds.receiver_positions, window=window)
    err = np.linalg.norm(est - track.truth[:, :2], axis=1)
    berr = np.linalg.norm(base - track.truth[:, :2], axis=1)
    pf, bl = error_stats(err), error_stats(berr)
    return {
        "track": track.name,
        "rows": len(track),
        "dropped_rows": track.n_dropped,
        "duration_s": track.duration,
        "rmse": pf["rmse"],
        "median_error": pf["median_error"],
        "mean_error": pf["mean_error"],
        "p90_error": pf["p90_error"],
        "baseline_rmse": bl["rmse"],
        "baseline_median_error": bl["median_error"],
        "ratio": pf["rmse"] / bl["rmse"],
        "ms_per_packet": 1e3 * elapsed / len(track),
        "moves_refused": tracker.n_refused,
        "steps_all_refused": tracker.n_all_refused,
        "model": model,
        "map_settings": map_settings,
        "calibration_tracks": cal_tracks,
        "_errors": err,
        "_baseline_errors": berr,
        "_series": {"t": np.asarray(track.t, float), "truth": track.truth[:, :2], "mean": est, "cov": cov,
                    "baseline": base},
    }


def pooled(results: list[dict]) -> dict:
    """RMSE and median over all rows of all tracks (each row counts once)."""
    e = np.concatenate([r["_errors"] for r in results])
    b = np.concatenate([r["_baseline_errors"] for r in results])
    pf, bl = error_stats(e), error_stats(b)
    return {"track": "pooled", "rows": int(e.size), "rmse": pf["rmse"], "median_error": pf["median_error"],
            "mean_error": pf["mean_error"], "p90_error": pf["p90_error"], "baseline_rmse": bl["rmse"],
            "baseline_median_error": bl["median_error"], "ratio": pf["rmse"] / bl["rmse"]}


def format_table(rows: list[dict]) -> str:
    head = (f"{'track':30s} {'rows':>6s} {'PF RMSE':>8s} {'PF med':>7s} {'WC RMSE':>8s} {'WC med':>7s} "
            f"{'PF/WC':>6s}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['track']:30s} {r['rows']:6d} {r['rmse']:8.2f} {r['median_error']:7.2f} "
                     f"{r['baseline_rmse']:8.2f} {r['baseline_median_error']:7.2f} {r['ratio']:6.2f}")
    return "\n".join(lines)


def format_map_settings(results: list[dict]) -> str:
    """The radio-map settings each track was evaluated with."""
    rows = [r for r in results if r.get("map_settings")]
    if not rows:
        return ""
    head = f"{'track':30s} {'order':>5s} {'ridge':>6s} {'b (m)':>6s} {'w0':>5s} {'noise (mode, sl, sr)':>22s}  how"
    lines = ["radio-map settings per track (chosen on its calibration tracks only):", head, "-" * len(head)]
    for r in rows:
        st = r["map_settings"]
        law = "gaussian" if st.get("noise") is None else "split " + " ".join(f"{v:.2f}" for v in st["noise"])
        cells = [f"{st[k]:g}" if isinstance(st.get(k), (int, float)) else "-" for k in MAP_KEYS]
        lines.append(f"{r['track']:30s} {cells[0]:>5s} {cells[1]:>6s} {cells[2]:>6s} {cells[3]:>5s} {law:>22s}  "
                     f"{st.get('how', '')}")
    return "\n".join(lines)


def figures(ds: BLERSSIDataset, r: dict, out: Path, grid_cell: float = DEFAULTS["grid_cell"]) -> list[Path]:
    """``out/ble_<track>_topdown.png`` (the floor plan, the receivers, the true track, the
    particle filter's estimate with 3-sigma ellipses and the weighted-centroid baseline)
    and ``out/ble_<track>_errors.png`` (X and Y errors of both, the filter's ±3σ)."""
    from dfusion.viz.plots import plot_track_errors
    from dfusion.viz.topdown import Scene, Track, draw_scene

    ser = r["_series"]
    t, truth = ser["t"] - ser["t"][0], ser["truth"]   # seconds since the track's first packet
    pf = Track("particle filter (WSN tracker)", t, ser["mean"], ser["cov"], "tab:blue")
    wc = Track("weighted centroid (baseline)", t, ser["baseline"], None, "tab:orange", style=":", width=0.8)
    grid = None
    try:
        grid = ds.load_grid(grid_cell).map
    except DfusionError:
        pass
    scene = Scene(title=f"BLE RSSI {r['track']}: {r['rows']} packets, {r['duration_s']:.0f} s",
                  truth={"walker (annotated positions)": (t, truth)}, tracks=[pf, wc],
                  points={"BLE receivers": (ds.receiver_positions[:, :2], "^", "tab:red")}, grid=grid,
                  labels=[(p[:2], rc.mac[-5:]) for p, rc in zip(ds.receiver_positions, ds.receivers)],
                  note=f"RMSE: particle filter {r['rmse']:.2f} m, weighted centroid {r['baseline_rmse']:.2f} m")
    out.mkdir(parents=True, exist_ok=True)
    a = draw_scene(scene, out / f"ble_{r['track']}_topdown.png")
    b = plot_track_errors(t, truth, [pf, wc], out / f"ble_{r['track']}_errors.png",
                          title=f"BLE RSSI {r['track']}: position errors (particle filter with its own ±3σ; "
                                f"weighted centroid); time since the first packet")
    return [a, b]


def public(r: dict) -> dict:
    return {k: v for k, v in r.items() if not k.startswith("_")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("track_file", nargs="?", help="a trk/*_all_sensors.mbd file")
    ap.add_argument("--dataset", type=Path, help="dataset directory (default: inferred from TRACK_FILE)")
    ap.add_argument("--all", action="store_true", help="run every track in DIR/trk and print the pooled table")
    ap.add_argument("--json", type=Path, help="write the metrics and each track's per-packet series as JSON")
    ap.add_argument("--plot", type=Path, metavar="DIR", help="write each track's top-down figure and error plot into DIR")
    ap.add_argument("--particles", type=int, default=DEFAULTS["particles"])
    ap.add_argument("--motion", choices=("random_walk", "constant_velocity"), default=DEFAULTS["motion"])
    ap.add_argument("--q", type=float, default=DEFAULTS["q"],
                    help="process noise: m^2/s (random walk) or m^2/s^3 (constant velocity)")
    ap.add_argument("--max-speed", type=float, default=None, help="speed cap (constant velocity, m/s)")
    ap.add_argument("--grid-cell", type=float, default=DEFAULTS["grid_cell"], help="occupancy grid cell (m)")
    ap.add_argument("--no-map", action="store_true", help="no occupancy-grid constraint")
    ap.add_argument("--outlier-prob", type=float, default=0.0,
                    help="outlier floor of the RSSI likelihood (weight of a uniform density over 60 dB)")
    ap.add_argument("--window", type=float, default=DEFAULTS["window"], help="baseline averaging window (s)")
    ap.add_argument("--seed", type=int, default=DEFAULTS["seed"])
    ap.add_argument("--path-loss", type=Path, help="path-loss calibration JSON (see --save-calibration)")
    ap.add_argument("--shared-path-loss", action="store_true",
                    help="fit one (p0, exponent, std) for all receivers instead of one per receiver")
    ap.add_argument("--model", choices=MODELS, default=DEFAULTS["model"],
                    help="measurement model: log-distance fit plus a learnt residual radio map (default), "
                         "or the log-distance path-loss fit alone")
    ap.add_argument("--radio-map", type=Path, help="radio map .npz (see --save-radio-map)")
    grid = MAP_SETTINGS_GRID
    ap.add_argument("--map-order", type=int, default=DEFAULTS["map_order"],
                    help=f"radio map: azimuthal harmonics of the path loss (default: chosen from {grid['order']})")
    ap.add_argument("--map-ridge", type=float, default=DEFAULTS["map_ridge"],
                    help=f"radio map: ridge penalty of the harmonics (default: chosen from {grid['ridge']})")
    ap.add_argument("--map-bandwidth", type=float, default=DEFAULTS["map_bandwidth"],
                    help=f"radio map: kernel bandwidth, m (default: chosen from {grid['bandwidth']})")
    ap.add_argument("--map-prior-weight", type=float, default=DEFAULTS["map_prior_weight"],
                    help="radio map: weight of the path-loss prior, in training packets per 0.2 m cell "
                         f"(default: chosen from {grid['prior_weight']})")
    ap.add_argument("--map-noise", choices=("split-normal", "gaussian"), default=DEFAULTS["map_noise"],
                    help="radio map: law of the standardized residual (default split-normal, fitted to "
                         "held-out residuals of the calibration tracks)")
    ap.add_argument("--map-constant-std", action="store_true",
                    help="radio map: each receiver's path-loss residual std everywhere (not a spatial std)")
    ap.add_argument("--save-radio-map", type=Path,
                    help="write the radio map learnt from every track except TRACK_FILE's, then exit")
    ap.add_argument("--save-calibration", type=Path,
                    help="write the calibration fitted on every track except TRACK_FILE's, then exit")
    args = ap.parse_args(argv)

    if not args.all and not args.track_file:
        ap.error("give TRACK_FILE or --all")
    root = args.dataset or (find_dataset_root(args.track_file) if args.track_file else None)
    if root is None:
        ap.error("cannot infer the dataset directory from TRACK_FILE: pass --dataset DIR")
    try:
        ds = BLERSSIDataset(root)
        if args.save_calibration:
            name = ds.load_track(args.track_file).name if args.track_file else None
            tracks = [ds.load_track(n) for n in ds.track_names() if n != name]
            cal = calibrate_path_loss(tracks, ds.receiver_positions, ds.receiver_macs)
            args.save_calibration.write_text(json.dumps(cal.to_json(), indent=2) + "\n")
            print(f"calibration from {cal.tracks} written to {args.save_calibration}")
            return 0
        if args.save_radio_map:
            name = ds.load_track(args.track_file).name if args.track_file else None
            rmap = radio_map_for(ds, name, None, None, dict(order=args.map_order, ridge=args.map_ridge,
                                                             bandwidth=args.map_bandwidth,
                                                             prior_weight=args.map_prior_weight),
                                 args.map_noise, not args.map_constant_std)
            rmap.to_npz(args.save_radio_map)
            print(f"radio map from {rmap.tracks} ({rmap.settings}) written to {args.save_radio_map}")
            return 0
        files = ds.track_paths() if args.all else [Path(args.track_file)]
        kw = dict(particles=args.particles, motion=args.motion, q=args.q, max_speed=args.max_speed,
                  grid_cell=None if args.no_map else args.grid_cell, window=args.window, seed=args.seed,
                  path_loss=args.path_loss, outlier_prob=args.outlier_prob,
                  per_receiver=not args.shared_path_loss, model=args.model, radio_map=args.radio_map,
                  map_order=args.map_order, map_ridge=args.map_ridge, map_bandwidth=args.map_bandwidth,
                  map_prior_weight=args.map_prior_weight, map_noise=args.map_noise,
                  map_spatial_std=not args.map_constant_std)
        cache: dict = {}
        results = [evaluate_track(ds, f, cache=cache, **kw) for f in files]
    except (DfusionError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = results + ([pooled(results)] if len(results) > 1 else [])
    model = args.model if args.model == "path-loss" else (
        "radio-map" + (" const-std" if args.map_constant_std else ""))
    print(f"WSN particle filter ({args.particles} particles, {args.motion}, q={args.q}, {model}, "
          f"map={'none' if args.no_map else f'{args.grid_cell} m grid'}) vs weighted centroid "
          f"(10^(rssi/10), {args.window} s window); errors in m, every packet row")
    print(format_table(rows))
    print(f"time per packet: {np.mean([r['ms_per_packet'] for r in results]):.2f} ms")
    if args.model == "radio-map":
        print(format_map_settings(results))
    if args.plot:
        for r in results:
            print("wrote " + ", ".join(str(p) for p in figures(ds, r, args.plot, args.grid_cell)))
    if args.json:
        out = public(rows[-1]) if len(results) == 1 else {**public(rows[-1]), "tracks": [public(r) for r in results]}
        out["series"] = {r["track"]: {k: np.asarray(v).tolist() for k, v in r["_series"].items()} for r in results}
        out["config"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in kw.items()}
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
