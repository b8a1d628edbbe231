r"""Calibrating a radio map of a receiver network from labelled tracks, and evaluating trackers on them.

Used with the BLE RSSI dataset (:mod:`dfusion.datasets.ble_rssi`), and with any data of
the same shape: tracks of RSSI readings with known tag positions.

* :class:`PathLossCalibration`, :func:`calibrate_path_loss` -- log-distance path loss per
  receiver (optionally with a directional gain), fitted by least squares;
* :func:`calibrate_radio_map`, :func:`held_out_residuals`, :func:`held_out_score`,
  :func:`select_radio_map_settings` -- the radio map of :mod:`dfusion.localization.radio_map`
  learnt from calibration tracks, with its settings chosen by leave-one-track-out
  predictive density (``docs/wsn.md``);
* :func:`weighted_centroid` -- the causal weighted-centroid baseline;
* :func:`run_tracker` -- a :class:`~dfusion.localization.WSNTracker` over a track, packet
  by packet.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.datasets.ble_rssi import Track
from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.localization.radio_map import (
    RadioMap,
    fit_directional_path_loss,
    fit_radio_maps,
    fit_split_normal,
    path_loss_design,
    split_normal_logpdf,
)
from dfusion.models.measurement import RSSISensor, fit_path_loss

__all__ = ["PathLossCalibration", "calibrate_path_loss", "calibrate_radio_map", "held_out_residuals", "held_out_score", "select_radio_map_settings", "MAP_SETTINGS_GRID", "NOISE_MODELS", "weighted_centroid", "run_tracker"]

@dataclass
class PathLossCalibration:
    """Log-distance path-loss parameters per receiver, optionally with a directional gain.

    Fitted with :func:`fit_path_loss` (``order = 0``) or
    :func:`dfusion.localization.radio_map.fit_directional_path_loss`: the mean RSSI of receiver ``j``
    for a tag at ``p`` is ``p0_j - 10 n_j log10(d / d0) + sum_k (a_jk cos k phi + b_jk sin k phi)``
    with ``d`` the 3-D distance and ``phi`` the azimuth of the tag seen from the receiver.

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
    harmonics : (m, 2K) array
        ``[a_1, b_1, ..., a_K, b_K]`` per receiver (dB); ``K = 0`` (no column) by default.
    ridge : float
        Ridge penalty the harmonics were fitted with (provenance).
    """

    macs: list[str]
    p0: Array
    exponent: Array
    std: Array
    d0: float
    height: float
    n_samples: np.ndarray
    tracks: list[str]
    harmonics: Array | None = None
    ridge: float = 0.0

    def __post_init__(self) -> None:
        m = len(self.macs)
        h = np.zeros((m, 0)) if self.harmonics is None else np.asarray(self.harmonics, dtype=float)
        if h.ndim != 2 or h.shape[0] != m or h.shape[1] % 2:
            raise ValidationError(f"harmonics must be an (m, 2K) array for {m} receivers, got shape {h.shape}")
        self.harmonics = h

    @property
    def order(self) -> int:
        """Number ``K`` of azimuthal harmonics."""
        return self.harmonics.shape[1] // 2

    def sensors(self, receiver_positions: Array) -> list[RSSISensor]:
        """One single-receiver :class:`RSSISensor` per receiver, for :class:`dfusion.localization.WSNTracker`.

        Only for the plain log-distance model (``order = 0``): an :class:`RSSISensor` has no
        directional gain.
        """
        pos = np.asarray(receiver_positions, dtype=float)
        if pos.shape[0] != len(self.macs):
            raise ValidationError(f"{pos.shape[0]} receiver positions for {len(self.macs)} calibrated receivers")
        if self.order:
            raise ValidationError("a directional path-loss fit (order > 0) cannot be expressed as RSSISensor; "
                                  "use it through a radio map")
        return [RSSISensor(pos[j], self.p0[j], self.exponent[j], self.std[j], d0=self.d0, height=self.height)
                for j in range(len(self.macs))]

    def mean_rssi(self, j: int, xy: ArrayLike, receiver_positions: ArrayLike) -> Array:
        """Mean RSSI of receiver ``j`` for a tag at ``xy`` (N, 2), at the calibration height."""
        r = np.asarray(receiver_positions, dtype=float)[j]
        q = np.asarray(xy, dtype=float).reshape(-1, 2)
        d = np.sqrt((q[:, 0] - r[0]) ** 2 + (q[:, 1] - r[1]) ** 2 + (self.height - r[2]) ** 2)
        out = self.p0[j] - 10.0 * self.exponent[j] * np.log10(np.maximum(d, 0.01) / self.d0)
        if self.order:
            phi = np.arctan2(q[:, 1] - r[1], q[:, 0] - r[0])
            out = out + path_loss_design(d, phi, self.order, self.d0)[:, 2:] @ self.harmonics[j]
        return out

    def to_json(self) -> dict:
        model = "rssi = p0 - 10 exponent log10(d / d0) + N(0, std^2), d = 3-D distance (m)"
        if self.order:
            model = ("rssi = p0 - 10 exponent log10(d / d0) + sum_k (a_k cos(k phi) + b_k sin(k phi)) + N(0, std^2), "
                     "d = 3-D distance (m), phi = azimuth of the tag seen from the receiver; harmonics = "
                     "[a_1, b_1, ..., a_K, b_K] (dB)")
        out = {
            "model": model,
            "d0": self.d0,
            "height": self.height,
            "tracks": self.tracks,
            "receivers": {m: {"p0": float(a), "exponent": float(b), "std": float(c), "n_samples": int(k)}
                          for m, a, b, c, k in zip(self.macs, self.p0, self.exponent, self.std, self.n_samples)},
        }
        if self.order:
            out["ridge"] = self.ridge
            for m, h in zip(self.macs, self.harmonics):
                out["receivers"][m]["harmonics"] = [float(v) for v in h]
        return out

    @classmethod
    def from_json(cls, obj: dict, macs: list[str]) -> "PathLossCalibration":
        """Read :meth:`to_json` output; ``macs`` fixes the receiver order (all must be present)."""
        try:
            rec = obj["receivers"]
            rows = [rec[m] for m in macs]
            harm = np.array([r.get("harmonics", []) for r in rows], dtype=float).reshape(len(rows), -1)
            return cls(list(macs), np.array([r["p0"] for r in rows], dtype=float),
                       np.array([r["exponent"] for r in rows], dtype=float),
                       np.array([r["std"] for r in rows], dtype=float), float(obj.get("d0", 1.0)),
                       float(obj["height"]), np.array([r.get("n_samples", 0) for r in rows], dtype=int),
                       list(obj.get("tracks", [])), harm, float(obj.get("ridge", 0.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValidationError(f"bad path-loss calibration: {exc!r}") from None


def calibrate_path_loss(tracks: list[Track], receiver_positions: Array, macs: list[str],
                        per_receiver: bool = True, d0: float = 1.0, order: int = 0,
                        ridge: float = 100.0) -> PathLossCalibration:
    """Fit the (directional) path-loss model to ground-truth-labelled tracks.

    The distance of each row is the 3-D distance between the labelled tag position
    and the receiver. ``order = 0``: the log-distance fit :func:`fit_path_loss`;
    ``order = K > 0``: :func:`dfusion.localization.radio_map.fit_directional_path_loss` with ``K``
    azimuthal harmonics and the ridge penalty ``ridge`` on them (per receiver only).
    ``per_receiver=False`` fits one ``(p0, exponent, std)`` for all receivers. Use tracks other
    than the one evaluated (leave-one-track-out).
    """
    if not tracks:
        raise ValidationError("calibrate_path_loss needs at least one track")
    if order and not per_receiver:
        raise ValidationError("a directional path loss (order > 0) is fitted per receiver")
    pos = np.asarray(receiver_positions, dtype=float)
    j = np.concatenate([t.receiver for t in tracks])
    z = np.concatenate([t.rssi for t in tracks])
    truth = np.vstack([t.truth for t in tracks])
    d = np.linalg.norm(truth - pos[j], axis=1)
    m = pos.shape[0]
    counts = np.bincount(j, minlength=m)
    harm = np.zeros((m, 2 * int(order)))
    if per_receiver:
        fits = []
        for r in range(m):
            sel = j == r
            if sel.sum() < 3 + 2 * order:
                raise ValidationError(f"receiver {macs[r]} has {int(sel.sum())} calibration rows (< {3 + 2 * order})")
            if order:
                phi = np.arctan2(truth[sel, 1] - pos[r, 1], truth[sel, 0] - pos[r, 0])
                p0_, n_, harm[r], s_ = fit_directional_path_loss(d[sel], phi, z[sel], order, ridge, d0)
                fits.append((p0_, n_, s_))
            else:
                fits.append(fit_path_loss(d[sel], z[sel], d0))
        p0, n, s = (np.array(v) for v in zip(*fits))
    else:
        p0_, n_, s_ = fit_path_loss(d, z, d0)
        p0, n, s = np.full(m, p0_), np.full(m, n_), np.full(m, s_)
    return PathLossCalibration(list(macs), p0, n, s, float(d0), float(truth[:, 2].mean()), counts,
                               [t.name for t in tracks], harm, float(ridge) if order else 0.0)


#: Candidate settings of :func:`select_radio_map_settings` (the example's default search):
#: path-loss harmonics ``order`` and their ``ridge``, kernel ``bandwidth`` (m) and ``prior_weight``.
MAP_SETTINGS_GRID: dict[str, tuple] = {
    "order": (0, 1, 2, 3),
    "ridge": (30.0, 100.0, 300.0),
    "bandwidth": (0.5, 0.6, 0.8, 1.0),
    "prior_weight": (0.05, 0.1, 0.2, 0.5),
}

#: Noise laws of :func:`calibrate_radio_map` and :func:`select_radio_map_settings`.
NOISE_MODELS = ("split-normal", "gaussian")


def _map_nodes(limits: ArrayLike, cell: float) -> tuple[Array, tuple[int, int]]:
    """Origin and shape of the node grid ``(0, 0) + cell (ix, iy)`` covering ``limits``."""
    lim = np.asarray(limits, dtype=float).reshape(4)
    origin = np.floor(lim[:2] / cell) * cell
    shape = tuple(int(v) for v in np.ceil((lim[2:] - origin) / cell - 1e-9).astype(int) + 1)
    return origin, shape


def _fit_maps(tracks: list[Track], pos: Array, macs: list[str], cal: PathLossCalibration, limits: ArrayLike,
              cell: float, bandwidths: list[float], prior_weights: list[float], spatial_std: bool,
              noise: tuple[float, float, float] | None) -> dict[tuple[float, float], RadioMap]:
    origin, shape = _map_nodes(limits, cell)
    truth = np.vstack([t.truth for t in tracks])
    names = [t.name for t in tracks]
    return fit_radio_maps(truth[:, :2], np.concatenate([t.receiver for t in tracks]),
                          np.concatenate([t.rssi for t in tracks]), lambda j, xy: cal.mean_rssi(j, xy, pos),
                          cal.std, origin=origin, cell=cell, shape=shape, bandwidths=bandwidths,
                          prior_weights=prior_weights, spatial_std=spatial_std,
                          tracks=sorted(set(names) | set(cal.tracks)), noise=noise,
                          settings={"order": cal.order, "ridge": cal.ridge})


def held_out_residuals(tracks: list[Track], receiver_positions: Array, macs: list[str], *, limits: ArrayLike,
                       settings: list[dict], cell: float = 0.2,
                       spatial_std: bool = True) -> list[tuple[Array, Array]]:
    """Leave-one-track-out residuals of radio maps among ``tracks``, for each of ``settings``.

    For every track ``t``, the path loss (``order``, ``ridge``) and the map (``bandwidth``,
    ``prior_weight``) are fitted on the *other* tracks and evaluated at ``t``'s labelled
    positions. Returns, per setting, the standardized residuals ``u = (z - M) / S`` and the map
    spreads ``S`` of every row of every track (concatenated). Needs at least two tracks.
    """
    if len(tracks) < 2:
        raise ValidationError("held-out residuals need at least two tracks")
    pos = np.asarray(receiver_positions, dtype=float)
    keys = [(int(st["order"]), float(st["ridge"]) if st["order"] else 0.0, float(st["bandwidth"]),
             float(st["prior_weight"])) for st in settings]
    groups: dict[tuple[int, float], list[tuple[float, float]]] = {}
    for o, r, bw, w0 in keys:
        groups.setdefault((o, r), []).append((bw, w0))
    parts: dict[tuple, list[tuple[Array, Array]]] = {k: [] for k in keys}
    for i, t in enumerate(tracks):
        train = tracks[:i] + tracks[i + 1:]
        rows = np.arange(len(t))
        for (o, r), pairs in groups.items():
            cal = calibrate_path_loss(train, pos, macs, order=o, ridge=r if o else 100.0)
            bws = sorted({bw for bw, _ in pairs})
            pws = sorted({w0 for _, w0 in pairs})
            maps = _fit_maps(train, pos, macs, cal, limits, cell, bws, pws, spatial_std, None)
            for bw, w0 in set(pairs):
                M, S = maps[(bw, w0)].lookup(t.truth[:, :2], np.arange(pos.shape[0]))
                Mr, Sr = M[rows, t.receiver], S[rows, t.receiver]
                parts[(o, r, bw, w0)].append(((t.rssi - Mr) / Sr, Sr))
    return [(np.concatenate([u for u, _ in parts[k]]), np.concatenate([s for _, s in parts[k]])) for k in keys]


def held_out_score(u: Array, S: Array, noise: str = "split-normal") -> tuple[float, tuple[float, float, float] | None]:
    """Mean log predictive density per reading (nats) of held-out residuals ``u = (z - M) / S``.

    ``noise="gaussian"``: ``mean(log N(u; 0, 1) - ln S)``; ``"split-normal"``: the split normal
    fitted to ``u`` (:func:`dfusion.localization.radio_map.fit_split_normal`; three parameters against
    thousands of readings) in place of ``N(0, 1)``. Returns the score and the fitted law.
    """
    if noise == "gaussian":
        return float(np.mean(-0.5 * u * u - 0.5 * np.log(2 * np.pi) - np.log(S))), None
    if noise != "split-normal":
        raise ValidationError(f"noise must be one of {NOISE_MODELS}, got {noise!r}")
    law = fit_split_normal(u)
    return float(np.mean(split_normal_logpdf(u, *law) - np.log(S))), law


def select_radio_map_settings(tracks: list[Track], receiver_positions: Array, macs: list[str], *,
                              limits: ArrayLike, grid: dict[str, tuple] | None = None, noise: str = "split-normal",
                              cell: float = 0.2, spatial_std: bool = True,
                              exclude: str | None = None) -> tuple[dict, list[tuple[dict, float]]]:
    """Choose the radio-map settings by leave-one-track-out predictive density among ``tracks``.

    Every combination of ``grid`` (keys ``order``, ``ridge``, ``bandwidth``, ``prior_weight``;
    default :data:`MAP_SETTINGS_GRID`; ``ridge`` is moot for ``order = 0``) is scored by
    :func:`held_out_score` of its :func:`held_out_residuals`: each track of ``tracks`` is
    predicted by a map learnt from the others. The best setting wins; its noise law (split
    normal) is fitted to those held-out residuals, so it describes maps applied off their
    training paths. Only ``tracks`` are used: pass the calibration tracks, never the evaluated
    one (``exclude`` names it and raises if it is among ``tracks``).

    Returns ``(best, table)``: ``best`` holds the four settings, ``noise`` (the law or
    ``None``) and ``score``; ``table`` lists ``(settings, score)`` best first.
    """
    if len(tracks) < 2:
        raise ValidationError("select_radio_map_settings needs at least two calibration tracks")
    if exclude is not None and exclude in [t.name for t in tracks]:
        raise ValidationError(f"calibration data include the evaluated track {exclude!r} (leave-one-track-out)")
    g = dict(MAP_SETTINGS_GRID if grid is None else grid)
    missing = set(MAP_SETTINGS_GRID) - set(g)
    if missing:
        raise ValidationError(f"grid misses {sorted(missing)}")
    cands, seen = [], set()
    for o in g["order"]:
        for r in (g["ridge"] if o else (0.0,)):
            for bw in g["bandwidth"]:
                for w0 in g["prior_weight"]:
                    key = (int(o), float(r), float(bw), float(w0))
                    if key not in seen:
                        seen.add(key)
                        cands.append(dict(order=key[0], ridge=key[1], bandwidth=key[2], prior_weight=key[3]))
    res = held_out_residuals(tracks, receiver_positions, macs, limits=limits, settings=cands, cell=cell,
                             spatial_std=spatial_std)
    scored = []
    for st, (u, S) in zip(cands, res):
        sc, law = held_out_score(u, S, noise)
        scored.append((st, sc, law))
    scored.sort(key=lambda v: -v[1])
    st, sc, law = scored[0]
    return dict(st, noise=law, score=sc), [(a, b) for a, b, _ in scored]


def calibrate_radio_map(tracks: list[Track], receiver_positions: Array, macs: list[str], *,
                        limits: ArrayLike, cell: float = 0.2, bandwidth: float = 1.0, prior_weight: float = 1.0,
                        spatial_std: bool = True, path_loss: PathLossCalibration | None = None,
                        exclude: str | None = None, order: int = 0, ridge: float = 100.0,
                        noise: str | tuple[float, float, float] | None = "gaussian"
                        ) -> tuple[RadioMap, PathLossCalibration]:
    """Per-receiver (directional) path-loss fit plus a kernel-smoothed residual map (:func:`~.radio_map.fit_radio_map`).

    The nodes are ``(0, 0) + cell (ix, iy)`` up to the first multiple of ``cell`` at or beyond
    ``limits = [x_min, y_min, x_max, y_max]`` (the layout of the dataset's ``.occ`` grids).
    ``path_loss`` defaults to :func:`calibrate_path_loss` on the same tracks with ``order``
    azimuthal harmonics and ``ridge``. ``noise``: ``"gaussian"`` (or ``None``), an explicit
    split-normal ``(mode, sigma_left, sigma_right)``, or ``"split-normal"``: fitted to the
    leave-one-track-out residuals among ``tracks`` (:func:`held_out_residuals`, same settings;
    needs two tracks or more). ``exclude``: the name of the track to be evaluated; a
    :class:`ValidationError` is raised if it is among ``tracks`` (or among the tracks of
    ``path_loss``), so that the map can never be learnt from the track it is then used on.
    Returns the map and the path-loss fit under it.
    """
    if not tracks:
        raise ValidationError("calibrate_radio_map needs at least one track")
    names = [t.name for t in tracks]
    if exclude is not None and (exclude in names or (path_loss is not None and exclude in path_loss.tracks)):
        raise ValidationError(f"calibration data include the evaluated track {exclude!r} (leave-one-track-out)")
    pos = np.asarray(receiver_positions, dtype=float)
    cal = path_loss if path_loss is not None else calibrate_path_loss(tracks, pos, macs, order=order, ridge=ridge)
    if isinstance(noise, str):
        if noise == "split-normal":
            st = dict(order=cal.order, ridge=cal.ridge if cal.order else ridge, bandwidth=bandwidth,
                      prior_weight=prior_weight)
            (u, S), = held_out_residuals(tracks, pos, macs, limits=limits, settings=[st], cell=cell,
                                         spatial_std=spatial_std)
            noise = fit_split_normal(u)
        elif noise == "gaussian":
            noise = None
        else:
            raise ValidationError(f"noise must be one of {NOISE_MODELS} or (mode, sigma_left, sigma_right)")
    elif noise is not None:
        noise = tuple(float(v) for v in noise)
    rmap = _fit_maps(tracks, pos, macs, cal, limits, cell, [bandwidth], [prior_weight], spatial_std, noise)
    return next(iter(rmap.values())), cal


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


def run_tracker(track: Track, tracker, initialize: bool = True, cov_out: Array | None = None) -> Array:
    """Run a :class:`dfusion.localization.WSNTracker` over a track packet by packet.

    For each row: predict to its time, update with that row's single reading, record the
    weighted-mean position. The tracker starts at the first row's time (initialized
    here, uniformly over its map, unless ``initialize=False``). Returns ``(K, 2)``;
    ``cov_out`` (a ``(K, 2, 2)`` array), when given, receives each row's covariance.
    """
    if initialize:
        tracker.initialize(t=float(track.t[0]))
    else:
        tracker.time = float(track.t[0])
    est = np.empty((len(track), 2))
    for k in range(len(track)):
        t = float(track.t[k])
        tracker.predict(t)
        tracker.update(t, track.rssi[k:k + 1], track.receiver[k:k + 1])
        e = tracker.estimate()
        est[k] = e.mean
        if cov_out is not None:
            cov_out[k] = np.asarray(e.cov)[:2, :2]
    return est


