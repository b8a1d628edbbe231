"""Phones in a mall: PDR, magnetic map, WiFi/iBeacon fingerprints and their fusion network, on real walks.

Usage::

    python examples/indoor_localization.py --all DIR [--folds 10] [--json out/indoor.json] [--figure out/indoor.png]
    python examples/indoor_localization.py DIR/site1-F1 [...]

``DIR`` holds one folder per floor (``floor_info.json``, ``geojson_map.json``, ``path_data_files/``),
the layout of the Indoor Location Competition 2.0 data (docs/indoor.md). Every floor is evaluated with
the same settings (this file's ``SETTINGS``), by k-fold cross-validation over walks: walk ``i`` (in
file-name order) is in fold ``i mod k``, ``k = 10`` by default; the maps, the Weinberg gain, the floor's heading offset and
the fingerprint databases are built from the other folds' walks only. Errors are measured at the
waypoints' times, a walk's first waypoint excluded; each method's estimate at a waypoint is its
estimate interpolated linearly between its outputs before and after (at most one step later); the
radio k-NN fixes are held from the latest scan.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from dfusion.datasets.indoor import IndoorTrace, RadioScan, read_floor
from dfusion.frontends.indoor import FingerprintFrontEnd, MagneticFrontEnd
from dfusion.fusion.node import FusionNode
from dfusion.localization.fingerprint import FingerprintLocalizer
from dfusion.localization.magnetic_pf import MagneticLocalizer, MagneticPFSettings, build_bias_free_map
from dfusion.models.motion import ConstantVelocity
from dfusion.models.pdr import PDRSteps, anchored_track, dead_reckon, fit_heading_offset, fit_weinberg_gain, pdr_steps

log = logging.getLogger("indoor")

#: One set of settings for the whole data family (never per floor).
SETTINGS = dict(
    folds=10,
    map_cell=1.0, map_sigma=1.0, map_n0=2.0,
    knn_k=4, knn_missing=-95.0, wifi_max_age=5.0,
    kf_step_var=0.15, kf_init_scale=1.0,
    pf=MagneticPFSettings(),
    track_init_std=1.0,
    radio_weight=1.0, contribute_max_std=3.0, inject=0.0, radio_floor=0.0, mode_output=False,
    network_q=0.5, use_beacon=False,
    localized_within=(2.0, 5.0), long_walk=30.0,
)

METHODS = ["wifi_knn", "beacon_knn", "pdr_true_start", "kf_pdr_wifi", "magnetic_true_start", "fused_network"]
LABELS = {
    "wifi_knn": "WiFi weighted k-NN",
    "beacon_knn": "iBeacon weighted k-NN",
    "pdr_true_start": "PDR alone from the true start",
    "kf_pdr_wifi": "Kalman filter PDR + WiFi (from WiFi)",
    "magnetic_true_start": "magnetic PF from the true start",
    "fused_network": "fused network (phone PDR + magnetic PF node, WiFi node), no prior",
}


def interp_at(ts: np.ndarray, xs: np.ndarray, t: float) -> np.ndarray | None:
    """Linear interpolation of a track ``xs`` at ``t`` (None before its first output)."""
    if len(ts) == 0 or t < ts[0] - 1e-9:
        return None
    return np.array([np.interp(t, ts, xs[:, 0]), np.interp(t, ts, xs[:, 1])])


def scan_positions(trace: IndoorTrace, steps: PDRSteps, gain: float, off: float, scans) -> list[tuple[dict, np.ndarray]]:
    """Training scans with the (waypoint-anchored PDR) position at their time."""
    if len(steps) >= 2:
        pos, tt = anchored_track(steps, trace.waypoints, gain, off), steps.t
    else:
        pos, tt = trace.waypoints[:, 1:], trace.waypoints[:, 0]
    if len(tt) == 0:
        return []
    return [(s.rssi, np.array([np.interp(s.t, tt, pos[:, 0]), np.interp(s.t, tt, pos[:, 1])])) for s in scans]


def beacon_epochs(trace: IndoorTrace, times: np.ndarray) -> list[dict[str, float]]:
    """The iBeacon readings between successive epoch ``times`` as one scan each (mean RSSI per beacon)."""
    out: list[dict[str, float]] = []
    bt = np.array([b.t for b in trace.beacons])
    prev = -np.inf
    for t in times:
        sel = np.flatnonzero((bt > prev) & (bt <= t)) if bt.size else []
        acc: dict[str, list] = {}
        for i in sel:
            for k, r in trace.beacons[i].rssi.items():
                acc.setdefault(k, []).append(r)
        out.append({k: float(np.mean(v)) for k, v in acc.items()})
        prev = t
    return out


class Fold:
    """What is learnt from the training walks of one fold."""

    def __init__(self, floor, steps: list[PDRSteps], train: list[int], cfg: dict) -> None:
        tr = [(floor.traces[i].waypoints, steps[i]) for i in train]
        self.gain = fit_weinberg_gain(tr)
        self.off = fit_heading_offset(tr)
        tracks, fields = [], []
        for i in train:
            st = steps[i]
            if len(st) >= 2 and len(floor.traces[i].waypoints) >= 1:
                tracks.append(anchored_track(st, floor.traces[i].waypoints, self.gain, self.off))
                fields.append(st.field)
        self.map, _ = build_bias_free_map(tracks, fields, bounds=(0, 0, floor.width, floor.height),
                                          cell=cfg["map_cell"], sigma=cfg["map_sigma"], n0=cfg["map_n0"])
        self.wifi = self._fingerprints(floor, steps, train, "wifi", cfg)
        self.beacon = self._fingerprints(floor, steps, train, "beacon", cfg)

    def _fingerprints(self, floor, steps, train, kind: str, cfg: dict) -> FingerprintLocalizer | None:
        S, P, G = [], [], []
        for i in train:
            trc = floor.traces[i]
            times, wifi, beac = radio_epochs(trc)
            scans = [RadioScan(t, d) for t, d in zip(times, wifi if kind == "wifi" else beac) if d]
            for sc, p in scan_positions(trc, steps[i], self.gain, self.off, scans):
                if sc:
                    S.append(sc)
                    P.append(p)
                    G.append(i)
        if len(set(G)) < 2:
            return None
        loc = FingerprintLocalizer(S, np.array(P), np.array(G), k=cfg["knn_k"], missing=cfg["knn_missing"])
        loc.calibrate()
        return loc


def radio_epochs(trace: IndoorTrace) -> tuple[np.ndarray, list[dict], list[dict]]:
    """Epoch times (the WiFi scans; every 2 s without WiFi), the WiFi scan and the beacon scan of each."""
    if trace.wifi:
        times = np.array([s.t for s in trace.wifi])
        wifi = [s.rssi for s in trace.wifi]
    else:
        times = np.arange(2.0, trace.duration + 2.0, 2.0)
        wifi = [{} for _ in times]
    return times, wifi, beacon_epochs(trace, times)


def run_walk(trace: IndoorTrace, st: PDRSteps, fold: Fold, cfg: dict, seed: int) -> tuple[dict, dict, dict]:
    """Every method on one walk: ``(tracks, run times, global-localization record)``; a track is ``(times, (n, 2))``."""
    wp = trace.waypoints
    times, wifi, beac = radio_epochs(trace)
    tracks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    cpu: dict[str, float] = {}

    # radio fingerprints alone: the latest fix at each epoch
    for name, loc, scans in (("wifi_knn", fold.wifi, wifi), ("beacon_knn", fold.beacon, beac)):
        t0 = time.process_time()
        T, X, C = [], [], []
        for t, sc in zip(times, scans):
            fix = loc.locate(sc) if (loc is not None and sc) else None
            if fix is not None:
                T.append(t)
                X.append(fix.mean)
                C.append(fix.cov)
        # hold the latest fix until the next one (a fix is not interpolated towards the future)
        tracks[name] = (np.array(T), np.array(X).reshape(-1, 2))
        tracks[name + "_cov"] = np.array(C).reshape(-1, 2, 2)
        cpu[name] = time.process_time() - t0

    # PDR from the true start
    t0 = time.process_time()
    p = dead_reckon(st, wp[0, 1:], fold.gain, fold.off)
    tracks["pdr_true_start"] = (np.concatenate([[wp[0, 0]], st.t]), p)
    cpu["pdr_true_start"] = time.process_time() - t0

    # Kalman filter PDR + WiFi, started from the first WiFi fix
    t0 = time.process_time()
    wt, wx = tracks["wifi_knn"]
    wc = tracks["wifi_knn_cov"]
    ev = sorted([(t, 0, k) for k, t in enumerate(st.t)] + [(t, 1, k) for k, t in enumerate(wt)])
    x = P = None
    T, X = [], []
    for t, kind, k in ev:
        if kind == 1:
            if x is None:
                x, P = wx[k].copy(), wc[k] * cfg["kf_init_scale"]
            else:
                S = P + wc[k]
                G = np.linalg.solve(S, P).T
                x = x + G @ (wx[k] - x)
                P = (np.eye(2) - G) @ P
                P = 0.5 * (P + P.T)
        elif x is not None:
            a = st.psi[k] + fold.off
            x = x + fold.gain * st.w[k] * np.array([math.cos(a), math.sin(a)])
            P = P + cfg["kf_step_var"] * np.eye(2)
        if x is not None:
            T.append(t)
            X.append(x.copy())
    tracks["kf_pdr_wifi"] = (np.array(T), np.array(X).reshape(-1, 2))
    cpu["kf_pdr_wifi"] = time.process_time() - t0

    # magnetic particle filter from the true start
    t0 = time.process_time()
    loc = MagneticLocalizer(fold.map, fold.gain, fold.off, cfg["pf"], seed=seed)
    loc.initialize(wp[0, 0], wp[0, 1:], cfg["track_init_std"] ** 2 * np.eye(2))
    T, X = [wp[0, 0]], [wp[0, 1:].copy()]
    for k in range(len(st)):
        loc.step(st.t[k], st.w[k], st.psi[k], st.field[k])
        T.append(st.t[k])
        X.append(loc.mode_estimate() if cfg["mode_output"] else loc.estimate()[0])
    tracks["magnetic_true_start"] = (np.array(T), np.array(X))
    cpu["magnetic_true_start"] = time.process_time() - t0

    # the fused network from no prior: phone (PDR + magnetic PF) -- wifi, phone -- beacon
    t0 = time.process_time()
    tstart = min(times[0] if len(times) else 0.0, st.t[0] if len(st) else 0.0, wp[0, 0]) - 1e-3
    motion = ConstantVelocity(2, cfg["network_q"])
    prior = (tstart, np.array([0.5 * fold.map.weight.shape[0], 0.5 * fold.map.weight.shape[1], 0, 0]),
             np.diag([1e4, 1e4, 4.0, 4.0]))
    nodes = {"phone": FusionNode("phone", ["wifi", "beacon"], motion, window=400, prior=prior),
             "wifi": FusionNode("wifi", ["phone"], motion, window=400, prior=prior),
             "beacon": FusionNode("beacon", ["phone"], motion, window=400, prior=prior)}
    gl = MagneticLocalizer(fold.map, fold.gain, fold.off, cfg["pf"], seed=seed + 1)
    gl.initialize(tstart)
    phone = MagneticFrontEnd(gl, cfg["radio_weight"], cfg["contribute_max_std"], cfg["inject"],
                             cfg["radio_floor"])
    radios = {"wifi": FingerprintFrontEnd(fold.wifi) if fold.wifi else None,
              "beacon": FingerprintFrontEnd(fold.beacon) if (fold.beacon and cfg["use_beacon"]) else None}
    ev = sorted([(t, 0, k) for k, t in enumerate(st.t)] + [(t, 1, k) for k, t in enumerate(times)])
    T, X = [], []
    for t, kind, k in ev:
        if kind == 0:
            phone.step(t, st.w[k], st.psi[k], st.field[k])
        else:
            for nd in nodes.values():
                if t > nd.latest_time:
                    nd.predict(t)
            if radios["wifi"] and wifi[k]:
                radios["wifi"].process(nodes["wifi"], t, wifi[k])
            if radios["beacon"] and beac[k]:
                radios["beacon"].process(nodes["beacon"], t, beac[k])
            phone.process(nodes["phone"], t)
            for r in ("wifi", "beacon"):
                nodes["phone"].receive(nodes[r].message_to("phone"))
                nodes[r].receive(nodes["phone"].message_to(r))
            phone.absorb(nodes["phone"], t)
        if phone.stats.absorbed:  # no output before the first radio information: the set is still uniform
            T.append(t)
            X.append(gl.mode_estimate() if cfg["mode_output"] else phone.estimate()[0])
    tracks["fused_network"] = (np.array(T), np.array(X).reshape(-1, 2))
    cpu["fused_network"] = time.process_time() - t0
    return tracks, cpu, {"pdr_distance": np.concatenate([[0.0], np.cumsum(fold.gain * st.w)]),
                         "step_t": np.concatenate([[wp[0, 0]], st.t])}


def waypoint_errors(trace: IndoorTrace, track: tuple[np.ndarray, np.ndarray], hold: bool = False) -> list[float | None]:
    """Error at every waypoint but the first (None where the method has no output yet)."""
    ts, xs = track
    out: list[float | None] = []
    for w in trace.waypoints[1:]:
        if hold:
            i = np.searchsorted(ts, w[0] + 1e-9) - 1
            q = xs[i] if i >= 0 else None
        else:
            q = interp_at(ts, xs, w[0])
        out.append(None if q is None else float(np.hypot(*(q - w[1:]))))
    return out


def localized_at(errors: list[float | None], within: float) -> int | None:
    """Index of the first waypoint from which every error is within ``within`` (None: never)."""
    for i in range(len(errors)):
        if all(e is not None and e <= within for e in errors[i:]):
            return i
    return None


def evaluate_floor(floor_dir: Path, cfg: dict) -> dict:
    t0 = time.time()
    floor = read_floor(floor_dir, max_wifi_age=cfg["wifi_max_age"])
    steps = [pdr_steps(tr) for tr in floor.traces]
    n = len(floor.traces)
    errs: dict[str, list[float]] = {m: [] for m in METHODS}
    missing: dict[str, int] = {m: 0 for m in METHODS}
    cpu: dict[str, float] = {m: 0.0 for m in METHODS}
    glob = {r: {"walks": 0, "success": 0, "distance": []} for r in cfg["localized_within"]}
    fig_data = None
    for f in range(cfg["folds"]):
        test = [i for i in range(n) if i % cfg["folds"] == f]
        train = [i for i in range(n) if i % cfg["folds"] != f]
        fold = Fold(floor, steps, train, cfg)
        log.info("%s fold %d: K=%.3f offset=%.1f deg, map support %d cells, wifi covariance scale %s",
                 floor.name, f, fold.gain, math.degrees(fold.off), int(fold.map.support.sum()),
                 f"{fold.wifi.scale:.2f}" if fold.wifi else "none (no WiFi database: fewer than 2 training walks)")
        for i in test:
            tr, st = floor.traces[i], steps[i]
            if len(tr.waypoints) < 2 or len(st) < 2:
                for m in METHODS:
                    missing[m] += max(0, len(tr.waypoints) - 1)
                continue
            tracks, c, extra = run_walk(tr, st, fold, cfg, seed=1000 * f + i)
            for m in METHODS:
                cpu[m] += c[m]
                e = waypoint_errors(tr, tracks[m], hold=m in ("wifi_knn", "beacon_knn"))
                errs[m] += [x for x in e if x is not None]
                missing[m] += sum(x is None for x in e)
            if tr.duration >= cfg["long_walk"]:
                e = waypoint_errors(tr, tracks["fused_network"])
                for r, g in glob.items():
                    k = localized_at(e, r)
                    g["walks"] += 1
                    if k is not None:
                        g["success"] += 1
                        g["distance"].append(float(np.interp(tr.waypoints[1 + k, 0], extra["step_t"],
                                                             extra["pdr_distance"])))
            if fig_data is None or tr.duration > fig_data["duration"]:  # the figure shows the longest walk
                fig_data = {"walk": tr.name, "duration": tr.duration, "truth": tr.waypoints[:, 1:].tolist(),
                            **{m: tracks[m][1].tolist() for m in ("pdr_true_start", "magnetic_true_start",
                                                                   "wifi_knn", "fused_network")}}
    rows = {}
    for m in METHODS:
        e = np.array(errs[m])
        rows[m] = {"n": int(e.size), "missing": missing[m],
                   "mean": float(e.mean()) if e.size else None, "median": float(np.median(e)) if e.size else None,
                   "p90": float(np.percentile(e, 90)) if e.size else None, "cpu_s": cpu[m]}
    return {"floor": floor.name, "walks": n, "rows": rows,
            "global": {f"{r:g}": {"walks_30s": g["walks"], "success": g["success"],
                                  "rate": g["success"] / g["walks"] if g["walks"] else None,
                                  "median_distance_m": float(np.median(g["distance"])) if g["distance"] else None}
                       for r, g in glob.items()},
            "outline": [o.tolist() for o in floor.outline], "size": [floor.width, floor.height],
            "figure": fig_data, "wall_s": time.time() - t0}


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def table(results: list[dict]) -> str:
    floors = [r["floor"] for r in results]
    head = "| method | " + " | ".join(f"{f} mean / median / p90 [m]" for f in floors) + " | CPU [s] |"
    lines = [head, "|---|" + "---|" * len(floors) + "---|"]
    for m in METHODS:
        cells = []
        for r in results:
            row = r["rows"][m]
            cells.append(f"{fmt(row['mean'])} / {fmt(row['median'])} / {fmt(row['p90'])} "
                         f"(n={row['n']}, {row['missing']} without output)")
        lines.append(f"| {LABELS[m]} | " + " | ".join(cells) + f" | {sum(r['rows'][m]['cpu_s'] for r in results):.1f} |")
    for key in results[0]["global"]:
        g = " | ".join(f"{r['global'][key]['success']}/{r['global'][key]['walks_30s']} "
                       f"({fmt(100 * r['global'][key]['rate'] if r['global'][key]['rate'] is not None else None)} %), "
                       f"median {fmt(r['global'][key]['median_distance_m'])} m walked until then" for r in results)
        lines.append(f"| fused network, global localization: within {key} m from a waypoint to the end, walks >= 30 s "
                     f"| {g} | |")
    return "\n".join(lines)


def figure(results: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = [r for r in results if r["figure"]]
    if not res:
        return
    fig, axes = plt.subplots(1, len(res), figsize=(7 * len(res), 6), squeeze=False)
    for ax, r in zip(axes[0], res):
        for o in r["outline"]:
            o = np.asarray(o)
            ax.plot(o[:, 0], o[:, 1], color="0.6", lw=0.8)
        d = r["figure"]
        styles = {"truth": ("k", "o-", "truth (waypoints)"), "pdr_true_start": ("tab:orange", "-", "PDR"),
                  "magnetic_true_start": ("tab:green", "-", "magnetic PF (true start)"),
                  "wifi_knn": ("tab:blue", ".", "WiFi k-NN"), "fused_network": ("tab:red", "-", "fused network (no prior)")}
        for k, (c, ls, lab) in styles.items():
            a = np.asarray(d[k]).reshape(-1, 2)
            if a.size:
                ax.plot(a[:, 0], a[:, 1], ls, color=c, label=lab, ms=4, lw=1.2)
        ax.set_aspect("equal")
        ax.set_xlim(0, r["size"][0])
        ax.set_ylim(0, r["size"][1])
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(f"{r['floor']}, walk {d['walk']} ({d['duration']:.0f} s)")
        ax.legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("path", type=Path, help="a floor folder, or with --all a folder of floor folders")
    ap.add_argument("--all", action="store_true", help="evaluate every floor folder in PATH")
    ap.add_argument("--folds", type=int, default=SETTINGS["folds"])
    ap.add_argument("--json", type=Path, default=Path("out/indoor.json"))
    ap.add_argument("--figure", type=Path, default=Path("out/indoor.png"))
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = dict(SETTINGS, folds=a.folds)
    if a.all:
        floors = sorted(p for p in a.path.iterdir() if (p / "floor_info.json").is_file())
    else:
        floors = [a.path]
    if not floors:
        print(f"error: no floor folder (with floor_info.json) in {a.path}", file=sys.stderr)
        return 2
    results = [evaluate_floor(p, cfg) for p in floors]
    print(table(results))
    a.json.parent.mkdir(parents=True, exist_ok=True)
    settings = {k: (v.__dict__ if isinstance(v, MagneticPFSettings) else v) for k, v in cfg.items()}
    a.json.write_text(json.dumps({"settings": settings, "results": results}, indent=1, default=float))
    figure(results, a.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
