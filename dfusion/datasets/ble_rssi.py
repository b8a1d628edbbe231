r"""Reader for the position-annotated BLE RSSI dataset (Daniş, Naskali, Cemgil & Ersoy).

Source: GitHub ``philotuxo/Position-Annotated-BLE-RSSI-Dataset`` (CC0 1.0).
Cite F. S. Daniş, A. T. Naskali, A. T. Cemgil and C. Ersoy, "An Indoor
Localization Dataset and Data Collection Framework with High Precision Position
Annotation", *Pervasive and Mobile Computing* 81, 2022; or F. S. Daniş,
A. T. Cemgil and C. Ersoy, "Adaptive sequential Monte Carlo filter for indoor
positioning and tracking with Bluetooth Low Energy beacons", *IEEE Access* 9,
37022-37038, 2021.

Layout of a dataset directory ``DIR``::

    DIR/cnf/tetam.dev      receivers ("Dongles:" + JSON) and the beacon ("Beacons:" + JSON)
    DIR/cnf/tetam.par      JSON; "limits" = [x_min, y_min, x_max, y_max] (m)
    DIR/occ/tetam_<c>.occ  occupancy grids (see OccupancyGrid.from_occ_file)
    DIR/trk/*.mbd          tracks: CSV, one row per received packet

Pitfalls handled here (documented in the dataset's README):

* track rows with a non-negative RSSI are not physical (``straight_05`` has two,
  +42 and +29 dBm) and are dropped (counted in ``Track.n_dropped``);
* timestamps are not strictly increasing (sub-millisecond steps back): rows
  are stably sorted by time;
* fields 8-16 (the orientation matrix) are often not a rotation and are ignored;
* in the ``.occ`` files 1 marks obstacles, although the source README says the
  opposite (see :meth:`OccupancyGrid.from_occ_file`);
* ground truth may lie slightly outside the area limits (``straight_03``
  reaches y = -0.14 m) and, on 2 % of rows, on an occupied node.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ValidationError
from ..linalg import Array
from ..models.measurement import RSSISensor, fit_path_loss
from ..pf.occupancy import OccupancyGrid
from ..pf.radio_map import RadioMap, fit_radio_map

__all__ = [
    "BLERSSIDataset",
    "Receiver",
    "Track",
    "read_devices",
    "read_track",
    "find_dataset_root",
    "PathLossCalibration",
    "calibrate_path_loss",
    "calibrate_radio_map",
    "weighted_centroid",
    "run_tracker",
    "error_stats",
]

#: Name of the site in the configuration and occupancy file names.
SITE = "tetam"


@dataclass(frozen=True)
class Receiver:
    """A fixed BLE receiver: MAC address (12 lowercase hex digits), alias and position (m)."""

    mac: str
    alias: str
    position: Array


@dataclass
class Track:
    """One track: packets in time order, one row per packet received by one receiver.

    Attributes
    ----------
    name : str
        File name without ``_all_sensors.mbd``.
    t : (K,) float
        Receive time (Unix seconds).
    receiver : (K,) int
        Index of the receiving receiver in the dataset's receiver list.
    rssi : (K,) float
        RSSI (dBm).
    truth : (K, 3) float
        Ground-truth beacon position at that time (m).
    n_dropped : int
        Rows dropped as invalid (non-negative RSSI).
    """

    name: str
    t: Array
    receiver: np.ndarray
    rssi: Array
    truth: Array
    n_dropped: int = 0
    path: Path | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def duration(self) -> float:
        """Time between the first and the last packet (s)."""
        return float(self.t[-1] - self.t[0]) if len(self) else 0.0


def read_devices(path: str | Path) -> tuple[list[Receiver], dict[str, str]]:
    """Parse ``tetam.dev``: returns the receivers (file order) and ``{beacon MAC: alias}``.

    Each line is ``Dongles:`` or ``Beacons:`` followed by JSON
    ``{mac: [[x, y, z], colour, alias]}`` (split at the first ``:``).
    """
    path = Path(path)
    receivers: list[Receiver] = []
    beacons: dict[str, str] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        key, _, rest = line.partition(":")
        try:
            obj = json.loads(rest)
        except json.JSONDecodeError as exc:
            raise ValidationError(f"{path}: bad JSON after {key!r}: {exc}") from None
        if key.strip() == "Dongles":
            for mac, (pos, _colour, alias) in obj.items():
                p = np.array(pos, dtype=float)
                if p.shape != (3,):
                    raise ValidationError(f"{path}: receiver {mac} needs an [x, y, z] position, got {pos!r}")
                receivers.append(Receiver(mac.lower(), str(alias), p))
        elif key.strip() == "Beacons":
            beacons.update({mac.lower(): str(v[2]) for mac, v in obj.items()})
    if not receivers:
        raise ValidationError(f"{path}: no 'Dongles:' line")
    return receivers, beacons


def read_track(path: str | Path, receiver_macs: list[str], beacon: str | None = None) -> Track:
    """Read one ``*.mbd`` track file; receiver MACs are mapped to indices in ``receiver_macs``.

    Drops rows with RSSI >= 0 dBm, sorts stably by time, ignores the orientation
    fields. With ``beacon`` given, rows of other beacons are dropped too (counted).
    Raises :class:`ValidationError` on a malformed row or an unknown receiver.
    """
    path = Path(path)
    index = {m: i for i, m in enumerate(receiver_macs)}
    t, rec, rssi, truth = [], [], [], []
    dropped = 0
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        f = line.split(",")
        if len(f) < 7:
            raise ValidationError(f"{path}:{lineno}: expected at least 7 fields, got {len(f)}")
        mac = f[1].strip().lower()
        if mac not in index:
            raise ValidationError(f"{path}:{lineno}: unknown receiver {mac!r}")
        try:
            ti, ri = float(f[0]), float(f[3])
            xyz = (float(f[4]), float(f[5]), float(f[6]))
        except ValueError:
            raise ValidationError(f"{path}:{lineno}: non-numeric field") from None
        if ri >= 0 or (beacon is not None and f[2].strip().lower() != beacon):
            dropped += 1
            continue
        t.append(ti)
        rec.append(index[mac])
        rssi.append(ri)
        truth.append(xyz)
    if not t:
        raise ValidationError(f"{path}: no valid rows")
    t_a = np.array(t)
    order = np.argsort(t_a, kind="stable")
    name = path.name.removesuffix(".mbd").removesuffix("_all_sensors")
    return Track(name, t_a[order], np.array(rec, dtype=np.int64)[order], np.array(rssi)[order],
                 np.array(truth)[order], dropped, path)


def find_dataset_root(track_path: str | Path) -> Path | None:
    """The dataset directory holding a track file (``DIR`` for ``DIR/trk/x.mbd``), if it looks like one."""
    p = Path(track_path).resolve().parent
    for cand in (p.parent, p):
        if (cand / "cnf" / f"{SITE}.dev").is_file():
            return cand
    return None


class BLERSSIDataset:
    """A dataset directory (full dataset or a slice with the same layout).

    Parameters
    ----------
    root : path
        Directory containing ``cnf/``, ``occ/`` and ``trk/``.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        dev = self.root / "cnf" / f"{SITE}.dev"
        if not dev.is_file():
            raise ValidationError(f"{self.root} is not a BLE RSSI dataset directory (no cnf/{SITE}.dev)")
        self.receivers, self.beacons = read_devices(dev)
        par = self.root / "cnf" / f"{SITE}.par"
        self.limits = np.array(json.loads(par.read_text())["limits"], dtype=float) if par.is_file() else None

    def __repr__(self) -> str:
        return f"BLERSSIDataset({str(self.root)!r}, receivers={len(self.receivers)}, tracks={self.track_names()})"

    @property
    def receiver_macs(self) -> list[str]:
        return [r.mac for r in self.receivers]

    @property
    def receiver_positions(self) -> Array:
        """``(m, 3)`` receiver positions (m)."""
        return np.array([r.position for r in self.receivers])

    def track_paths(self) -> list[Path]:
        """Track files in ``trk/``, sorted by name."""
        return sorted((self.root / "trk").glob("*_all_sensors.mbd"))

    def track_names(self) -> list[str]:
        return [p.name.removesuffix(".mbd").removesuffix("_all_sensors") for p in self.track_paths()]

    def load_track(self, name_or_path: str | Path) -> Track:
        """Load a track by name (``straight_03``), file name, or path."""
        p = Path(name_or_path)
        if not p.is_file():
            p = self.root / "trk" / f"{name_or_path}_all_sensors.mbd"
        if not p.is_file():
            raise ValidationError(f"no track {name_or_path!r} in {self.root / 'trk'}")
        beacon = next(iter(self.beacons)) if len(self.beacons) == 1 else None
        return read_track(p, self.receiver_macs, beacon)

    def grid_cells(self) -> list[float]:
        """Cell sizes of the occupancy grids present."""
        out = []
        for p in (self.root / "occ").glob(f"{SITE}_*.occ"):
            try:
                out.append(float(p.stem.split("_", 1)[1]))
            except ValueError:
                pass
        return sorted(out)

    def load_grid(self, cell: float = 0.2) -> OccupancyGrid:
        """Occupancy grid with the given cell size (1 = occupied; see the module docstring)."""
        p = self.root / "occ" / f"{SITE}_{cell:g}.occ"
        if not p.is_file():
            p = self.root / "occ" / f"{SITE}_{cell:.1f}.occ"
        if not p.is_file():
            raise ValidationError(f"no occupancy grid with cell {cell} m in {self.root / 'occ'} "
                                  f"(present: {self.grid_cells()})")
        return OccupancyGrid.from_occ_file(p)


# --------------------------------------------------------------------------- evaluation helpers
@dataclass
class PathLossCalibration:
    """Log-distance path-loss parameters per receiver, fitted with :func:`fit_path_loss`.

    Attributes
    ----------
    macs : list of str
        Receiver MACs, in the dataset's receiver order.
    p0, exponent, std : (m,) arrays
        Power at ``d0`` (dBm), path-loss exponent, residual standard deviation (dB).
    d0 : float
        Reference distance (m).
    height : float
        Tag height used for the 3-D distances (m): mean ground-truth height of the
        calibration rows.
    n_samples : (m,) int array
        Rows used per receiver.
    tracks : list of str
        Names of the tracks the fit used.
    """

    macs: list[str]
    p0: Array
    exponent: Array
    std: Array
    d0: float
    height: float
    n_samples: np.ndarray
    tracks: list[str]

    def sensors(self, receiver_positions: Array) -> list[RSSISensor]:
        """One single-receiver :class:`RSSISensor` per receiver, for :class:`dfusion.pf.WSNTracker`."""
        pos = np.asarray(receiver_positions, dtype=float)
        if pos.shape[0] != len(self.macs):
            raise ValidationError(f"{pos.shape[0]} receiver positions for {len(self.macs)} calibrated receivers")
        return [RSSISensor(pos[j], self.p0[j], self.exponent[j], self.std[j], d0=self.d0, height=self.height)
                for j in range(len(self.macs))]

    def mean_rssi(self, j: int, xy: ArrayLike, receiver_positions: ArrayLike) -> Array:
        """Log-distance mean RSSI of receiver ``j`` for a tag at ``xy`` (N, 2), at the calibration height."""
        r = np.asarray(receiver_positions, dtype=float)[j]
        q = np.asarray(xy, dtype=float).reshape(-1, 2)
        d = np.sqrt((q[:, 0] - r[0]) ** 2 + (q[:, 1] - r[1]) ** 2 + (self.height - r[2]) ** 2)
        return self.p0[j] - 10.0 * self.exponent[j] * np.log10(np.maximum(d, 0.01) / self.d0)

    def to_json(self) -> dict:
        return {
            "model": "rssi = p0 - 10 exponent log10(d / d0) + N(0, std^2), d = 3-D distance (m)",
            "d0": self.d0,
            "height": self.height,
            "tracks": self.tracks,
            "receivers": {m: {"p0": float(a), "exponent": float(b), "std": float(c), "n_samples": int(k)}
                          for m, a, b, c, k in zip(self.macs, self.p0, self.exponent, self.std, self.n_samples)},
        }

    @classmethod
    def from_json(cls, obj: dict, macs: list[str]) -> "PathLossCalibration":
        """Read :meth:`to_json` output; ``macs`` fixes the receiver order (all must be present)."""
        try:
            rec = obj["receivers"]
            rows = [rec[m] for m in macs]
            return cls(list(macs), np.array([r["p0"] for r in rows], dtype=float),
                       np.array([r["exponent"] for r in rows], dtype=float),
                       np.array([r["std"] for r in rows], dtype=float), float(obj.get("d0", 1.0)),
                       float(obj["height"]), np.array([r.get("n_samples", 0) for r in rows], dtype=int),
                       list(obj.get("tracks", [])))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValidationError(f"bad path-loss calibration: {exc!r}") from None


def calibrate_path_loss(tracks: list[Track], receiver_positions: Array, macs: list[str],
                        per_receiver: bool = True, d0: float = 1.0) -> PathLossCalibration:
    """Fit the log-distance model to ground-truth-labelled tracks (:func:`fit_path_loss`).

    The distance of each row is the 3-D distance between the labelled tag position
    and the receiver. ``per_receiver=False`` fits one ``(p0, exponent, std)`` for all
    receivers. Use tracks other than the one evaluated (leave-one-track-out).
    """
    if not tracks:
        raise ValidationError("calibrate_path_loss needs at least one track")
    pos = np.asarray(receiver_positions, dtype=float)
    j = np.concatenate([t.receiver for t in tracks])
    z = np.concatenate([t.rssi for t in tracks])
    truth = np.vstack([t.truth for t in tracks])
    d = np.linalg.norm(truth - pos[j], axis=1)
    m = pos.shape[0]
    counts = np.bincount(j, minlength=m)
    if per_receiver:
        fits = []
        for r in range(m):
            sel = j == r
            if sel.sum() < 3:
                raise ValidationError(f"receiver {macs[r]} has {int(sel.sum())} calibration rows (< 3)")
            fits.append(fit_path_loss(d[sel], z[sel], d0))
        p0, n, s = (np.array(v) for v in zip(*fits))
    else:
        p0_, n_, s_ = fit_path_loss(d, z, d0)
        p0, n, s = np.full(m, p0_), np.full(m, n_), np.full(m, s_)
    return PathLossCalibration(list(macs), p0, n, s, float(d0), float(truth[:, 2].mean()), counts,
                               [t.name for t in tracks])


def calibrate_radio_map(tracks: list[Track], receiver_positions: Array, macs: list[str], *,
                        limits: ArrayLike, cell: float = 0.2, bandwidth: float = 1.0, prior_weight: float = 1.0,
                        spatial_std: bool = True, path_loss: PathLossCalibration | None = None,
                        exclude: str | None = None) -> tuple[RadioMap, PathLossCalibration]:
    """Per-receiver log-distance fit plus a kernel-smoothed residual map (:func:`dfusion.pf.fit_radio_map`).

    The nodes are ``(0, 0) + cell (ix, iy)`` up to the first multiple of ``cell`` at or beyond
    ``limits = [x_min, y_min, x_max, y_max]`` (the layout of the dataset's ``.occ`` grids).
    ``path_loss`` defaults to :func:`calibrate_path_loss` on the same tracks. ``exclude``: the
    name of the track to be evaluated; a :class:`ValidationError` is raised if it is among
    ``tracks`` (or among the tracks of ``path_loss``), so that the map can never be learnt
    from the track it is then used on. Returns the map and the path-loss fit under it.
    """
    if not tracks:
        raise ValidationError("calibrate_radio_map needs at least one track")
    names = [t.name for t in tracks]
    if exclude is not None and (exclude in names or (path_loss is not None and exclude in path_loss.tracks)):
        raise ValidationError(f"calibration data include the evaluated track {exclude!r} (leave-one-track-out)")
    pos = np.asarray(receiver_positions, dtype=float)
    cal = path_loss if path_loss is not None else calibrate_path_loss(tracks, pos, macs)
    lim = np.asarray(limits, dtype=float).reshape(4)
    origin = np.floor(lim[:2] / cell) * cell
    shape = tuple(int(v) for v in np.ceil((lim[2:] - origin) / cell - 1e-9).astype(int) + 1)
    truth = np.vstack([t.truth for t in tracks])
    rmap = fit_radio_map(truth[:, :2], np.concatenate([t.receiver for t in tracks]),
                         np.concatenate([t.rssi for t in tracks]),
                         lambda j, xy: cal.mean_rssi(j, xy, pos), cal.std, origin=origin, cell=cell,
                         shape=shape, bandwidth=bandwidth, prior_weight=prior_weight, spatial_std=spatial_std,
                         tracks=sorted(set(names) | set(cal.tracks)))
    return rmap, cal


def weighted_centroid(track: Track, receiver_positions: Array, window: float = 2.0,
                      scale_db: float = 10.0) -> Array:
    """Causal weighted-centroid baseline, one ``(x, y)`` per track row.

    At row ``k`` (time ``t``), the RSSI of each receiver is averaged (in dBm) over its
    packets among rows ``0..k`` received in ``(t - window, t]``; receiver ``j`` gets the weight
    ``10^(mean_j / scale_db)`` (``scale_db = 10``: linear received power in mW) and
    the estimate is the weighted mean of the receivers' ``(x, y)``. Receivers
    without a packet in the window get no weight.
    """
    pos = np.asarray(receiver_positions, dtype=float)
    t = track.t
    num = np.zeros((len(track), 2))
    den = np.zeros(len(track))
    for r in range(pos.shape[0]):
        sel = track.receiver == r
        tr, zr = t[sel], track.rssi[sel]
        if tr.size == 0:
            continue
        c = np.concatenate([[0.0], np.cumsum(zr)])
        hi = np.cumsum(sel)  # packets of r among rows 0..k (causal: not the rows after k)
        lo = np.minimum(np.searchsorted(tr, t - window, side="right"), hi)
        cnt = hi - lo
        have = cnt > 0
        mean = np.where(have, (c[hi] - c[lo]) / np.maximum(cnt, 1), -np.inf)
        w = np.where(have, 10.0 ** (mean / scale_db), 0.0)
        num += w[:, None] * pos[r, :2]
        den += w
    return num / den[:, None]


def run_tracker(track: Track, tracker, initialize: bool = True) -> Array:
    """Run a :class:`dfusion.pf.WSNTracker` over a track packet by packet.

    For each row: predict over the time since the previous row, update with that
    row's single reading, record the weighted-mean position. Returns ``(K, 2)``.
    """
    if initialize:
        tracker.initialize()
    est = np.empty((len(track), 2))
    t_prev = track.t[0]
    for k in range(len(track)):
        tracker.predict(track.t[k] - t_prev)
        t_prev = track.t[k]
        tracker.update(track.rssi[k:k + 1], track.receiver[k:k + 1])
        est[k] = tracker.estimate()
    return est


def error_stats(errors: Array) -> dict[str, float]:
    """RMSE, median, mean and 90th percentile of horizontal errors (m)."""
    e = np.asarray(errors, dtype=float)
    return {"rmse": float(np.sqrt(np.mean(e * e))), "median_error": float(np.median(e)),
            "mean_error": float(np.mean(e)), "p90_error": float(np.percentile(e, 90)), "n": int(e.size)}
