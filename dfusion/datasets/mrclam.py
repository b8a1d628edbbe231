r"""Reader for the UTIAS Multi-Robot Cooperative Localization and Mapping (MRCLAM) dataset.

K. Y. K. Leung, Y. Halpern, T. D. Barfoot and H. H. T. Liu, "The UTIAS Multi-Robot
Cooperative Localization and Mapping Dataset", IJRR 30(8):969-974, 2011
(http://asrl.utias.utoronto.ca/datasets/mrclam/). Five robots drive among 15 landmarks;
each logs velocity odometry and range-bearing measurements of landmarks and of the other
robots (a monocular camera reading barcodes); motion capture gives ground truth.

Files of one dataset directory (``MRCLAM_Dataset<k>/``; each may also be gzip-compressed
with a ``.gz`` suffix, which the reader detects, as in the test slice)::

    Barcodes.dat               subject  barcode              (subjects 1-5 robots, 6-20 landmarks)
    Landmark_Groundtruth.dat   subject  x  y  std_x  std_y
    Robot<n>_Groundtruth.dat   time  x  y  theta
    Robot<n>_Odometry.dat      time  v  omega                 (velocities, not poses)
    Robot<n>_Measurement.dat   time  barcode  range  bearing

Pitfalls handled (found in Dataset 6; a slice, its source and where to get the full
dataset are in ``tests/data/mrclam/README.md``):

* ``Robot<n>_Measurement.dat`` names the target by its **barcode**, not its subject
  number (its header says "Subject #"): converted with ``Barcodes.dat``. Rows with a
  barcode that is in no row of ``Barcodes.dat`` (Dataset 6: barcodes 34, 43, 50, six
  rows) are dropped and counted in :attr:`RobotLog.unknown_barcode_rows`. The derived
  ``Robot<n>_Measurement_x.dat`` files of some copies are not read.
* Header lines start with ``#``; columns are separated by tabs *and* spaces.
* Odometry rows are velocities valid from their time stamp until the next row
  (piecewise constant): :func:`integrate_odometry` integrates them exactly (unicycle
  arcs). Nothing is recorded before 12-16 s (the robots stand still).
* Robot 1's ground truth ends at 771.9 s in Dataset 6, 128 s before the end: compare
  against ground truth only inside :attr:`RobotLog.gt_t`.
* Time stamps are Unix epoch seconds with millisecond resolution. All times are
  returned relative to :attr:`MRCLAMDataset.t0`, the earliest time stamp in any file
  (stored absolute for reference). Subtracting two epoch doubles would leave errors of
  up to 2.4e-7 s (their spacing at 1.2e9 s); the stamps are taken as integer
  microseconds instead and a relative time is ``(us - t0_us) * 1000 * 1e-9``: whole
  nanoseconds times 1e-9, exactly what a ROS header stamp gives
  (:func:`dfusion.bags.mrclam_from_bag`), so the directory and a bag of it give the same
  floats.
"""
from __future__ import annotations

import copy
import gzip
import io
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dfusion.errors import ValidationError
from dfusion.geometry import wrap_angle

logger = logging.getLogger(__name__)

__all__ = [
    "RobotLog",
    "MRCLAMDataset",
    "read_mrclam",
    "read_landmarks",
    "integrate_odometry",
    "interpolate_poses",
    "mean_velocities",
    "perturb_mrclam",
    "PERTURBATIONS",
    "ROBOTS",
]

#: Subject numbers of the robots.
ROBOTS = (1, 2, 3, 4, 5)


@dataclass
class RobotLog:
    """One robot's files, times relative to :attr:`MRCLAMDataset.t0`.

    Attributes
    ----------
    robot : int
        Subject number (1-5).
    gt_t, gt : (G,), (G, 3)
        Ground-truth times and poses ``(x, y, theta)``.
    odom_t, odom : (M,), (M, 2)
        Odometry times and velocities ``(v, omega)`` (m/s, rad/s), each valid until the
        next time stamp.
    meas_t, meas_subject, meas_range, meas_bearing : (K,) arrays
        Measurements with the target's *subject* number (1-5 robot, 6-20 landmark).
    unknown_barcode_rows : int
        Measurement rows dropped because their barcode is not in ``Barcodes.dat``.
    """

    robot: int
    gt_t: np.ndarray
    gt: np.ndarray
    odom_t: np.ndarray
    odom: np.ndarray
    meas_t: np.ndarray
    meas_subject: np.ndarray
    meas_range: np.ndarray
    meas_bearing: np.ndarray
    unknown_barcode_rows: int = 0

    def truth_at(self, t: np.ndarray | float) -> np.ndarray:
        """Ground-truth poses interpolated at ``t`` (see :func:`interpolate_poses`)."""
        return interpolate_poses(self.gt_t, self.gt, t)

    def observations_of(self, subject: int) -> np.ndarray:
        """Row indices of the measurements of ``subject``."""
        return np.flatnonzero(self.meas_subject == int(subject))


@dataclass
class MRCLAMDataset:
    """A dataset directory (see the module docstring).

    Attributes
    ----------
    root : Path
    t0 : float
        Absolute time (Unix s) of the earliest time stamp in any file; every time in the
        dataset is relative to it.
    barcodes : dict[int, int]
        Barcode -> subject.
    landmarks : dict[int, numpy.ndarray]
        Landmark subject (6-20) -> ``(x, y)``.
    robots : dict[int, RobotLog]
    """

    root: Path
    t0: float
    barcodes: dict[int, int]
    landmarks: dict[int, np.ndarray]
    robots: dict[int, RobotLog] = field(default_factory=dict)

    @property
    def duration(self) -> float:
        """Time of the last time stamp in any file (relative)."""
        ends = [float(a[-1]) for r in self.robots.values() for a in (r.gt_t, r.odom_t, r.meas_t) if a.size]
        return max(ends) if ends else 0.0

    def landmark_array(self) -> tuple[np.ndarray, np.ndarray]:
        """Landmark subjects ``(L,)`` and positions ``(L, 2)``, sorted by subject."""
        ids = np.array(sorted(self.landmarks), dtype=int)
        return ids, np.array([self.landmarks[i] for i in ids]).reshape(-1, 2)


def _find(root: Path, name: str) -> Path:
    for p in (root / name, root / (name + ".gz")):
        if p.is_file():
            return p
    raise ValidationError(f"{root}: missing {name} (or {name}.gz)")


def _load(path: Path, cols: int) -> np.ndarray:
    """Whitespace-separated numbers, ``#`` comments; plain or gzip (detected by content)."""
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    text = raw.decode("ascii", errors="replace")
    try:
        a = np.loadtxt(io.StringIO(text), comments="#", ndmin=2)
    except ValueError as exc:
        raise ValidationError(f"{path}: malformed data ({exc})") from None
    if a.size == 0:
        return np.zeros((0, cols))
    if a.shape[1] < cols:
        raise ValidationError(f"{path}: expected {cols} columns, got {a.shape[1]}")
    if not np.all(np.isfinite(a[:, :cols])):
        raise ValidationError(f"{path}: non-finite values")
    return a[:, :cols]


def _epoch_us(t: np.ndarray) -> np.ndarray:
    """Epoch seconds (parsed to the nearest double, 0.12 us apart at 1.2e9 s) as integer
    microseconds: exact for stamps of microsecond resolution or coarser (the files have
    milliseconds)."""
    return np.round(np.asarray(t, float) * 1e6).astype(np.int64)


def _sorted(t: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    k = np.argsort(t, kind="stable")
    return [t[k], *(a[k] for a in arrays)]


def read_landmarks(root: str | Path) -> tuple[dict[int, int], dict[int, np.ndarray]]:
    """``Barcodes.dat`` (barcode -> subject) and ``Landmark_Groundtruth.dat`` (landmark
    subject -> ``(x, y)``) of a dataset directory: the map knowledge a recording of the
    robots' own sensors (a bag, :func:`dfusion.bags.mrclam_from_bag`) does not hold."""
    root = Path(root)
    if not root.is_dir():
        raise ValidationError(f"{root}: not a directory")
    bc = _load(_find(root, "Barcodes.dat"), 2)
    lm = _load(_find(root, "Landmark_Groundtruth.dat"), 3)
    return {int(b): int(s) for s, b in bc}, {int(s): np.array([x, y]) for s, x, y in lm}


def read_mrclam(
    root: str | Path,
    robots: tuple[int, ...] = ROBOTS,
    *,
    duration: float | None = None,
) -> MRCLAMDataset:
    """Read an MRCLAM dataset directory (see the module docstring for the conventions).

    Parameters
    ----------
    root : directory with ``Barcodes.dat``, ``Landmark_Groundtruth.dat`` and the
        ``Robot<n>_*.dat`` files (each possibly ``.gz``)
    robots : which robots to read
    duration : keep only rows with a relative time ``<= duration`` (seconds after ``t0``)
    """
    root = Path(root)
    barcodes, landmarks = read_landmarks(root)
    raw: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for n in robots:
        if n not in ROBOTS:
            raise ValidationError(f"robot numbers are 1-5, got {n}")
        raw[n] = (
            _load(_find(root, f"Robot{n}_Groundtruth.dat"), 4),
            _load(_find(root, f"Robot{n}_Odometry.dat"), 3),
            _load(_find(root, f"Robot{n}_Measurement.dat"), 4),
        )
    starts = [a[0, 0] for trio in raw.values() for a in trio if a.shape[0]]
    if not starts:
        raise ValidationError(f"{root}: no data rows")
    t0_us = min(int(np.min(_epoch_us(a[:, 0]))) for trio in raw.values() for a in trio if a.shape[0])
    ds = MRCLAMDataset(root, t0_us * 1e-6, barcodes, landmarks)

    def rel(col: np.ndarray) -> np.ndarray:
        return (_epoch_us(col) - t0_us) * 1000 * 1e-9

    for n, (gt, od, me) in raw.items():
        gt_t, gt_p = _sorted(rel(gt[:, 0]), gt[:, 1:4])
        od_t, od_v = _sorted(rel(od[:, 0]), od[:, 1:3])
        me_t, me_v = _sorted(rel(me[:, 0]), me[:, 1:4])
        subj = np.array([barcodes.get(int(round(b)), -1) for b in me_v[:, 0]], dtype=int)
        ok = subj > 0
        if duration is not None:
            gsel, osel = gt_t <= duration, od_t <= duration
            gt_t, gt_p, od_t, od_v = gt_t[gsel], gt_p[gsel], od_t[osel], od_v[osel]
            ok &= me_t <= duration
            unknown = int(np.count_nonzero((subj <= 0) & (me_t <= duration)))
        else:
            unknown = int(np.count_nonzero(subj <= 0))
        gt_p = gt_p.copy()
        gt_p[:, 2] = wrap_angle(gt_p[:, 2])
        ds.robots[n] = RobotLog(
            n, gt_t, gt_p, od_t, od_v, me_t[ok], subj[ok], me_v[ok, 1].copy(), me_v[ok, 2].copy(), unknown
        )
        if unknown:
            logger.info("%s: robot %d: dropped %d measurement rows with unknown barcodes", root, n, unknown)
    return ds


def interpolate_poses(t_ref: np.ndarray, poses: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Poses ``(x, y, theta)`` at times ``t``, linear between samples (theta on the unwrapped
    heading, then wrapped); times outside ``[t_ref[0], t_ref[-1]]`` are clamped to the end poses."""
    tq = np.asarray(t, dtype=float)
    th = np.unwrap(poses[:, 2])
    out = np.stack([np.interp(tq, t_ref, poses[:, 0]), np.interp(tq, t_ref, poses[:, 1]),
                    wrap_angle(np.interp(tq, t_ref, th))], axis=-1)
    return out


def _arc(x: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    a = 0.5 * w * dt
    s = math.sin(a) / a if abs(a) > 1e-12 else 1.0
    phi = x[2] + a
    return np.array([x[0] + v * dt * s * math.cos(phi), x[1] + v * dt * s * math.sin(phi), float(wrap_angle(x[2] + w * dt))])


def integrate_odometry(odom_t: np.ndarray, odom: np.ndarray, pose0: np.ndarray, t0: float,
                       times: np.ndarray) -> np.ndarray:
    """Dead reckoning: integrate piecewise-constant velocities from ``pose0`` at ``t0``.

    Row ``k`` of ``odom`` holds ``(v, omega)`` from ``odom_t[k]`` until ``odom_t[k + 1]``
    (the last row until the end); before the first row the robot stands still. Each
    constant piece is integrated exactly along its circular arc (the unicycle model).
    Returns the poses ``(len(times), 3)`` at the sorted query ``times`` (``>= t0``).
    """
    times = np.asarray(times, dtype=float)
    if times.size and (np.any(np.diff(times) < 0) or times[0] < t0):
        raise ValidationError("query times must be sorted and >= t0")
    out = np.empty((times.size, 3))
    x = np.asarray(pose0, dtype=float).copy()
    t = float(t0)
    k = int(np.searchsorted(odom_t, t, side="right")) - 1  # row valid at t (-1: none yet)
    for q, tq in enumerate(times):
        while t < tq:
            t_next = odom_t[k + 1] if k + 1 < odom_t.size else math.inf
            t_end = min(t_next, tq)
            if k >= 0:
                x = _arc(x, float(odom[k, 0]), float(odom[k, 1]), t_end - t)
            t = t_end
            if t == t_next:
                k += 1
        out[q] = x
    return out


def mean_velocities(odom_t: np.ndarray, odom: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Time-averaged ``(v, omega)`` of piecewise-constant odometry over ``[edges[k], edges[k+1])``.

    Row ``j`` of ``odom`` is valid from ``odom_t[j]`` until ``odom_t[j + 1]`` (the last row
    until ``+inf``); before the first row the velocity is 0. Returns ``(len(edges) - 1, 2)``.
    """
    edges = np.asarray(edges, dtype=float)
    t = np.asarray(odom_t, dtype=float)
    u = np.asarray(odom, dtype=float).reshape(-1, 2)
    if t.size == 0:
        return np.zeros((max(edges.size - 1, 0), 2))
    # cumulative integral at every odometry time stamp, then at the edges
    dt = np.diff(t)
    cum = np.vstack([np.zeros((1, 2)), np.cumsum(u[:-1] * dt[:, None], axis=0)])
    j = np.searchsorted(t, edges, side="right") - 1
    jc = np.maximum(j, 0)
    at = cum[jc] + u[jc] * (edges - t[jc])[:, None]
    at[j < 0] = 0.0
    span = np.diff(edges)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.diff(at, axis=0) / span[:, None]
    out[span <= 0] = 0.0
    return out


#: Kinds of :func:`perturb_mrclam` (``"combined"`` applies the three others).
PERTURBATIONS = ("none", "outliers", "gap", "odometry-scale", "combined")


def perturb_mrclam(
    ds: MRCLAMDataset,
    kind: str,
    *,
    target: int = 1,
    observers: tuple[int, ...] = (2, 3, 4, 5),
    seed: int = 0,
    outlier_fraction: float = 0.1,
    gap_seconds: float = 60.0,
    gap_start: float | None = None,
    odometry_robot: int | None = None,
    odometry_scale: float = 1.05,
) -> MRCLAMDataset:
    """A perturbed copy of ``ds`` (``ds`` itself is not changed) for robustness tests.

    Kinds (:data:`PERTURBATIONS`):

    ``"outliers"``
        ``round(outlier_fraction * K)`` of the ``K`` sightings of ``target`` by the
        ``observers``, drawn without replacement (``numpy.random.default_rng(seed)``),
        get a range uniform in ``[r_min, r_max]`` and a bearing uniform in
        ``[b_min, b_max]``: the span of *all* range and bearing measurements of the
        dataset (the camera's field of view; Dataset 6: 0.94-8.63 m, -0.592-0.572 rad).
    ``"gap"``
        every sighting of ``target`` by the ``observers`` in ``[gap_start, gap_start +
        gap_seconds)`` is removed; by default ``gap_start`` is the start of the window
        of that length holding the most such sightings (Dataset 6: 108.5 s, 270
        sightings), so the gap removes as much as a gap of that length can.
    ``"odometry-scale"``
        ``odometry_robot``'s odometry velocities ``(v, omega)`` are multiplied by
        ``odometry_scale`` (a wheel-radius error); by default the observer with the most
        sightings of ``target`` (Dataset 6: robot 3).
    ``"combined"``
        the three above, in that order, each with the default it would have alone
        (the gap window and the odometry robot are chosen on the unperturbed data);
        ``"none"`` returns an unchanged copy.
    """
    if kind not in PERTURBATIONS:
        raise ValidationError(f"perturbation must be one of {PERTURBATIONS}, got {kind!r}")
    out = copy.deepcopy(ds)
    kinds = ("outliers", "gap", "odometry-scale") if kind == "combined" else (kind,)
    sightings = [(o, i) for o in observers for i in out.robots[o].observations_of(target).tolist()]
    if odometry_robot is None:  # chosen on the unperturbed data, so "combined" = the three kinds
        odometry_robot = max(observers, key=lambda o: (out.robots[o].observations_of(target).size, -o))
    if "outliers" in kinds and sightings:
        rng = np.random.default_rng(seed)
        ranges = np.concatenate([r.meas_range for r in out.robots.values()])
        bearings = np.concatenate([r.meas_bearing for r in out.robots.values()])
        k = int(round(outlier_fraction * len(sightings)))
        chosen = rng.choice(len(sightings), size=k, replace=False)
        for c in np.sort(chosen).tolist():
            o, i = sightings[c]
            out.robots[o].meas_range[i] = rng.uniform(ranges.min(), ranges.max())
            out.robots[o].meas_bearing[i] = rng.uniform(bearings.min(), bearings.max())
        logger.info("perturb: %d of %d sightings of robot %d replaced by outliers", k, len(sightings), target)
    if "gap" in kinds:
        if gap_start is None:
            t = np.sort([float(out.robots[o].meas_t[i]) for o, i in sightings])
            if t.size:
                n_in = np.searchsorted(t, t + gap_seconds, side="left") - np.arange(t.size)
                gap_start = float(t[int(np.argmax(n_in))])
            else:
                gap_start = 0.0
        removed = 0
        for o in observers:
            r = out.robots[o]
            drop = (r.meas_subject == target) & (r.meas_t >= gap_start) & (r.meas_t < gap_start + gap_seconds)
            keep = ~drop
            removed += int(np.count_nonzero(drop))
            r.meas_t, r.meas_subject = r.meas_t[keep], r.meas_subject[keep]
            r.meas_range, r.meas_bearing = r.meas_range[keep], r.meas_bearing[keep]
        logger.info("perturb: %d sightings of robot %d removed in [%.1f, %.1f) s", removed, target,
                    gap_start, gap_start + gap_seconds)
    if "odometry-scale" in kinds:
        out.robots[odometry_robot].odom = out.robots[odometry_robot].odom * float(odometry_scale)
        logger.info("perturb: robot %d odometry scaled by %g", odometry_robot, odometry_scale)
    return out
