r"""Pedestrian dead reckoning (PDR) of a hand-held phone: steps, step lengths, headings, world-frame field.

**Step detection (causal, as a phone runs it).** The specific force magnitude minus gravity,
``a_k = ||acc_k|| - g``, is low-passed by a causal second-order Butterworth filter
(cut-off ``cutoff`` Hz, ``scipy.signal.lfilter``, so sample ``k`` of the output uses only samples
``<= k``). A step is declared at sample ``k`` when sample ``k - 1`` of the filtered signal ``y``
is a local maximum (``y[k-2] < y[k-1] >= y[k]``) above ``peak_min`` and at least
``min_interval`` seconds after the previous step: the step is known one sample after its peak.
The filter delays the peak by its group delay; with a sinusoidal gait ``a = A sin(2 pi f t)`` the
filtered signal is ``A |H(f)| sin(2 pi f t + arg H(f))``, which ``tests/test_indoor.py`` checks.

**Step length (Weinberg).** ``L = K (a_max - a_min)^(1/4)`` with ``a_max, a_min`` the largest and
smallest filtered acceleration since the previous step (H. Weinberg, "Using the ADXL202 in
pedometer and personal navigation applications", Analog Devices application note AN-602, 2002).
``K`` depends on the person and the phone: :func:`fit_weinberg_gain` fits one ``K`` to training
walks (distance walked between waypoints over the sum of ``(a_max - a_min)^(1/4)``) and the
particle filter estimates a per-walk scale around it.

**Heading.** The rotation vector gives the rotation ``R`` device -> world (East, North, Up);
a phone held in front of the walker points its ``y`` axis forward, so the walking direction is
``psi = atan2(R[1, 1], R[0, 1])`` (angle of the device ``y`` axis from East, counter-clockwise),
averaged over the step as a circular mean. The floor's frame is rotated from East-North by an
angle common to the floor (:func:`fit_heading_offset`, from training walks) plus a per-walk
offset (the phone's heading error, how it is held) that the particle filter estimates.

**World-frame magnetic field.** ``B_w = R B_dev``; its vertical component ``B_z``, horizontal
magnitude ``B_h = sqrt(B_x^2 + B_y^2)`` and magnitude ``|B|`` do not depend on the heading (the
rotation vector's yaw is itself referenced to magnetic north, so ``B_x, B_y`` are not
informative about position).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import butter, lfilter

from dfusion.errors import ValidationError
from dfusion.linalg import Array

__all__ = [
    "quaternion_matrices",
    "PDRSteps",
    "StepDetector",
    "Steps",
    "detect_steps",
    "world_field",
    "device_heading",
    "pdr_steps",
    "fit_weinberg_gain",
    "fit_heading_offset",
    "dead_reckon",
    "anchored_track",
    "GRAVITY",
]

#: Standard gravity [m/s^2].
GRAVITY = 9.80665


def quaternion_matrices(rotvec: Array) -> Array:
    r"""``(n, 3, 3)`` rotation matrices device -> world (East, North, Up) of Android rotation vectors.

    With ``q = (w, x, y, z)``, ``w = sqrt(max(0, 1 - x^2 - y^2 - z^2))`` (Android's
    ``SensorManager.getRotationMatrixFromVector``), the matrix of the unit quaternion:
    ``R = [[1-2(y^2+z^2), 2(xy-zw), 2(xz+yw)], [2(xy+zw), 1-2(x^2+z^2), 2(yz-xw)],
    [2(xz-yw), 2(yz+xw), 1-2(x^2+y^2)]]``. ``rotvec``: ``(n, >= 3)`` of x, y, z (time dropped
    by the caller). Android's rotation vector is referenced to East, North, Up..
    """
    v = np.asarray(rotvec, dtype=float)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    w = np.sqrt(np.clip(1.0 - x * x - y * y - z * z, 0.0, None))
    R = np.empty((v.shape[0], 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - z * w)
    R[:, 0, 2] = 2 * (x * z + y * w)
    R[:, 1, 0] = 2 * (x * y + z * w)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - x * w)
    R[:, 2, 0] = 2 * (x * z - y * w)
    R[:, 2, 1] = 2 * (y * z + x * w)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


@dataclass
class StepDetector:
    """Settings of the causal step detector (module docstring)."""

    cutoff: float = 3.0
    peak_min: float = 0.6
    min_interval: float = 0.3
    rate: float = 50.0

    def __post_init__(self) -> None:
        if not (0 < self.cutoff < self.rate / 2):
            raise ValidationError(f"cutoff must be in (0, rate/2), got {self.cutoff}")
        if self.min_interval <= 0:
            raise ValidationError(f"min_interval must be positive, got {self.min_interval}")

    def coefficients(self) -> tuple[Array, Array]:
        """``(b, a)`` of the second-order Butterworth low-pass at the nominal sample rate."""
        b, a = butter(2, self.cutoff / (self.rate / 2))
        return np.asarray(b), np.asarray(a)


@dataclass
class Steps:
    """Detected steps: ``t`` time each step is declared [s], ``t_prev`` the previous step's time
    (the first step's is the first sample), ``swing`` = ``a_max - a_min`` over the step [m/s^2]."""

    t: Array
    t_prev: Array
    swing: Array

    def __len__(self) -> int:
        return int(self.t.shape[0])


def detect_steps(t: ArrayLike, acc: ArrayLike, detector: StepDetector | None = None) -> Steps:
    """Steps of an accelerometer stream ``acc`` ``(n, 3)`` at times ``t`` ``(n,)`` (module docstring).

    The signal is resampled to the detector's nominal rate by linear interpolation first (the
    phone's samples are not evenly spaced); a step's time is that of the resampled sample at which
    it is declared, so only samples up to it were used.
    """
    det = detector or StepDetector()
    t = np.asarray(t, dtype=float)
    a = np.asarray(acc, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] != t.shape[0]:
        raise ValidationError(f"acc must have shape (n, 3) matching t, got {a.shape} and {t.shape}")
    if t.shape[0] < 3:
        return Steps(np.zeros(0), np.zeros(0), np.zeros(0))
    tu = np.arange(t[0], t[-1], 1.0 / det.rate)
    mag = np.linalg.norm(a, axis=1) - GRAVITY
    x = np.interp(tu, t, mag)
    b, aa = det.coefficients()
    y = lfilter(b, aa, x - x[0]) + x[0]
    out_t, out_prev, out_sw = [], [], []
    last = tu[0]
    lo = np.inf
    hi = -np.inf
    for k in range(2, y.shape[0]):
        v = y[k - 1]
        lo = min(lo, v)
        hi = max(hi, v)
        if v > y[k - 2] and v >= y[k] and v > det.peak_min and tu[k] - last >= det.min_interval:
            out_t.append(tu[k])
            out_prev.append(last)
            out_sw.append(hi - lo)
            last = tu[k]
            lo, hi = np.inf, -np.inf
            lo = min(lo, y[k])
    return Steps(np.asarray(out_t), np.asarray(out_prev), np.asarray(out_sw))


def device_heading(rotvec: ArrayLike) -> Array:
    """Walking direction ``psi`` [rad from East, counter-clockwise] per rotation matrix (module docstring)."""
    R = quaternion_matrices(np.asarray(rotvec, dtype=float))
    return np.arctan2(R[:, 1, 1], R[:, 0, 1])


def world_field(rotvec: ArrayLike, mag: ArrayLike) -> Array:
    """``(n, 3)`` of ``(B_z, B_h, |B|)`` [uT]: the device-frame field ``mag`` rotated to the world frame."""
    R = quaternion_matrices(np.asarray(rotvec, dtype=float))
    B = np.einsum("nij,nj->ni", R, np.asarray(mag, dtype=float))
    return np.column_stack([B[:, 2], np.hypot(B[:, 0], B[:, 1]), np.linalg.norm(B, axis=1)])


@dataclass
class PDRSteps:
    """Per step: time ``t``, Weinberg length factor ``w = swing^(1/4)``, heading ``psi`` (East-North
    frame), the world-frame field ``field`` ``(n, 3)`` averaged over the step (``B_z, B_h, |B|``)."""

    t: Array
    w: Array
    psi: Array
    field: Array

    def __len__(self) -> int:
        return int(self.t.shape[0])


def pdr_steps(trace, detector: StepDetector | None = None) -> PDRSteps:
    """Steps of an :class:`~dfusion.datasets.indoor.IndoorTrace` with their heading and field.

    Heading and field are averaged over ``(t_prev, t]`` of each step (circular mean for the heading),
    from the rotation vector and magnetometer interpolated to the accelerometer's times.
    """
    st = detect_steps(trace.acc[:, 0], trace.acc[:, 1:], detector)
    if len(st) == 0 or len(trace.rotvec) < 2 or len(trace.mag) < 2:
        return PDRSteps(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    tr = trace.rotvec[:, 0]
    psi = device_heading(trace.rotvec[:, 1:])
    rv_at_mag = np.column_stack([np.interp(trace.mag[:, 0], tr, trace.rotvec[:, i]) for i in (1, 2, 3)])
    fld = world_field(rv_at_mag, trace.mag[:, 1:])
    tm = trace.mag[:, 0]
    c, s = np.cos(psi), np.sin(psi)
    out_psi = np.empty(len(st))
    out_f = np.empty((len(st), 3))
    for i, (t1, t0) in enumerate(zip(st.t, st.t_prev)):
        m = (tr > t0) & (tr <= t1)
        if not m.any():
            m = np.abs(tr - t1) == np.abs(tr - t1).min()
        out_psi[i] = np.arctan2(s[m].mean(), c[m].mean())
        mm = (tm > t0) & (tm <= t1)
        if not mm.any():
            mm = np.abs(tm - t1) == np.abs(tm - t1).min()
        out_f[i] = fld[mm].mean(axis=0)
    return PDRSteps(st.t, st.swing ** 0.25, out_psi, out_f)


def _truth_at(waypoints: Array, t: Array) -> Array:
    return np.column_stack([np.interp(t, waypoints[:, 0], waypoints[:, 1]), np.interp(t, waypoints[:, 0], waypoints[:, 2])])


def fit_weinberg_gain(traces_steps: list[tuple[Array, PDRSteps]]) -> float:
    """One Weinberg ``K`` for training walks: ``sum`` of the straight-line distances between
    successive waypoints over the ``sum`` of the steps' ``swing^(1/4)`` between them.

    ``traces_steps``: ``(waypoints (m, 3), steps)`` per walk. Straight lines between waypoints
    shorten curved paths a little, so ``K`` is slightly low; the filter's per-walk scale absorbs it.
    """
    dist = wsum = 0.0
    for wp, st in traces_steps:
        if len(wp) < 2 or len(st) == 0:
            continue
        dist += float(np.sum(np.hypot(*np.diff(wp[:, 1:], axis=0).T)))
        m = (st.t >= wp[0, 0]) & (st.t <= wp[-1, 0])
        wsum += float(st.w[m].sum())
    if wsum <= 0:
        raise ValidationError("no steps between waypoints in the training walks")
    return dist / wsum


def fit_heading_offset(traces_steps: list[tuple[Array, PDRSteps]]) -> float:
    """Rotation [rad] from the East-North frame to the floor's frame: the circular mean, weighted by
    segment length, of ``direction of waypoint segment - mean step heading`` over the segments
    longer than 3 m with at least 3 steps."""
    acc = 0j
    for wp, st in traces_steps:
        for k in range(len(wp) - 1):
            d = wp[k + 1, 1:] - wp[k, 1:]
            L = float(np.hypot(*d))
            m = (st.t > wp[k, 0]) & (st.t <= wp[k + 1, 0])
            if L < 3.0 or m.sum() < 3:
                continue
            h = np.angle(np.exp(1j * st.psi[m]).mean())
            acc += L * np.exp(1j * (np.arctan2(d[1], d[0]) - h))
    if acc == 0:
        raise ValidationError("no usable waypoint segments to fit the heading offset")
    return float(np.angle(acc))


def dead_reckon(steps: PDRSteps, start: ArrayLike, gain: float, heading_offset: float) -> Array:
    """``(n + 1, 2)`` positions: ``start`` then after each step ``p += K w [cos, sin](psi + offset)``."""
    p0 = np.asarray(start, dtype=float).reshape(2)
    ang = steps.psi + heading_offset
    d = (gain * steps.w)[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.vstack([p0, p0 + np.cumsum(d, axis=0)])


def anchored_track(steps: PDRSteps, waypoints: ArrayLike, gain: float, heading_offset: float) -> Array:
    """``(n, 2)`` positions at the step times, dead reckoning bent onto the waypoints (training data).

    Between two successive waypoints the dead-reckoned path is moved by the similarity transform
    (rotation, scale, shift) that maps its ends onto the two waypoints, so the track passes through
    every waypoint and keeps the shape PDR gives in between. Steps before the first or after the last
    waypoint are dead reckoned from the nearest waypoint. Used to place training samples on the map.
    """
    wp = np.asarray(waypoints, dtype=float)
    if len(steps) == 0 or wp.shape[0] == 0:
        return np.zeros((len(steps), 2))
    raw = dead_reckon(steps, [0.0, 0.0], gain, heading_offset)
    tt = np.concatenate([[steps.t[0] - 1e-3], steps.t])

    def at(t: float) -> Array:
        return np.array([np.interp(t, tt, raw[:, 0]), np.interp(t, tt, raw[:, 1])])

    out = np.empty((len(steps), 2))
    for k, t in enumerate(steps.t):
        i = int(np.searchsorted(wp[:, 0], t))
        if i == 0 or i == wp.shape[0]:
            w = wp[0] if i == 0 else wp[-1]
            out[k] = w[1:] + at(t) - at(w[0])
            continue
        a, b = wp[i - 1], wp[i]
        pa, pb = at(a[0]), at(b[0])
        d_raw = complex(*(pb - pa))
        d_true = complex(*(b[1:] - a[1:]))
        z = d_true / d_raw if abs(d_raw) > 1e-6 else 1.0
        r = z * complex(*(at(t) - pa))
        if abs(d_raw) <= 1e-6:  # standing still: interpolate in time
            f = (t - a[0]) / max(b[0] - a[0], 1e-9)
            out[k] = a[1:] + f * (b[1:] - a[1:])
        else:
            out[k] = a[1:] + np.array([r.real, r.imag])
    return out
