r"""Reliability models of localization sources (DESIGN.md sec. 7).

**Environmental camera** (the switching paper, ``000_2c7cfc349439030c.txt``,
sec. 2.1, eq. 1-9). A camera at height ``h`` above the plane of the target,
tilted by the installation angle ``alpha`` from the downward vertical, with a
vertical field angle ``theta`` over ``N`` pixel rows. A point seen at the
vertical angular coordinate ``phi`` in ``[-theta/2, theta/2]`` (measured from
the optical axis, positive towards the horizon) lies at the ground distance
``x = tan(phi + alpha) h`` and one pixel there covers ``D(phi)`` metres; the
farther the point, the larger ``D``, the fewer pixels a mark of width ``w``
covers and the larger the error of a detector that is off by ``k`` pixels::

    theta_0 = theta / N                                                   (1)
    x       = tan(phi + alpha) h                                          (2)
    D(phi)  = tan(phi + alpha + theta_0) h - tan(phi + alpha) h
            = sec^2(phi + alpha) h / (cot theta_0 - tan(phi + alpha))     (3)
    D(phi) ~= sec^2(phi + alpha) h / cot theta_0                          (4)
    n(phi)  = w / D                                                       (5)
    Phi     = n / n_max,   n_max = n(-theta/2)                            (6)
    E       = k D                                                         (7)
    S       = 1 / (E + 1)                                                 (8)
    R_c     = Phi S = n / (n(-theta/2) (k D + 1))                         (9)

The mark width ``w`` cancels in ``Phi = D(-theta/2) / D(phi)``, so it is not a
parameter here. ``D`` and ``E`` are in metres (``h`` in metres), ``k`` in pixels.

:func:`camera_geometry` and :func:`viewing_angle` read ``alpha, h, theta, N``
and ``phi`` off a :class:`~dfusion.models.PinholeCamera` and a target
position; :func:`camera_reliability_at` chains everything. The paper's model
is one-dimensional (the image row); for a camera without roll the row of a
ground point depends only on its distance along the camera's horizontal
heading, which is how ``phi`` is computed.

Every function is vectorized over ``phi`` where it takes one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import ValidationError
from .linalg import Array

__all__ = [
    "pixel_angle",
    "ground_distance",
    "pixel_footprint",
    "mark_pixels",
    "recognition_accuracy",
    "localization_error",
    "satisfaction",
    "camera_reliability",
    "CameraGeometry",
    "camera_geometry",
    "viewing_angle",
    "camera_reliability_at",
]


def pixel_angle(theta: float, N: int) -> float:
    """Eq. (1): the field angle of one pixel row, ``theta_0 = theta / N`` (rad)."""
    if not (np.isfinite(theta) and 0 < theta < math.pi):
        raise ValidationError(f"vertical field angle theta must be in (0, pi), got {theta!r}")
    if N < 1:
        raise ValidationError(f"pixel rows N must be >= 1, got {N!r}")
    return float(theta) / float(N)


def ground_distance(phi: ArrayLike, alpha: float, h: float) -> Array:
    """Eq. (2): horizontal distance from the camera's foot, ``x = tan(phi + alpha) h`` (m)."""
    return np.tan(np.asarray(phi, dtype=float) + alpha) * h


def pixel_footprint(phi: ArrayLike, alpha: float, h: float, theta_0: float, *, approximate: bool = False) -> Array:
    """Eq. (3) (or its approximation eq. (4)): metres covered by one pixel row at ``phi``.

    ``D = sec^2(phi + alpha) h / (cot theta_0 - tan(phi + alpha))``; with
    ``approximate=True``, ``D = sec^2(phi + alpha) h tan(theta_0)`` (valid when
    ``cot theta_0 >> tan(phi + alpha)``). Where the pixel row reaches the horizon
    (``phi + alpha + theta_0 >= pi/2``) the footprint is infinite.
    """
    a = np.asarray(phi, dtype=float) + alpha
    sec2 = 1.0 / np.cos(a) ** 2
    if approximate:
        D = sec2 * h * math.tan(theta_0)
    else:
        with np.errstate(divide="ignore"):
            D = sec2 * h / (1.0 / math.tan(theta_0) - np.tan(a))
    return np.where((a + theta_0 < math.pi / 2) & (a > -math.pi / 2), D, np.inf)


def mark_pixels(w: float, D: ArrayLike) -> Array:
    """Eq. (5): pixels covered by a mark of width ``w`` (m), ``n = w / D``."""
    return w / np.asarray(D, dtype=float)


def _min_footprint_angle(alpha: float, theta: float, theta_0: float) -> float:
    # The paper's n_max = n(-theta/2) assumes alpha >= theta/2 (the image does not reach
    # past the camera's foot). Otherwise the smallest footprint (largest mark) is at the row
    # straddling the vertical, phi + alpha = -theta_0/2, clipped to the image.
    return float(np.clip(-alpha - theta_0 / 2, -theta / 2, theta / 2)) if alpha < theta / 2 else -theta / 2


def recognition_accuracy(phi: ArrayLike, alpha: float, h: float, theta: float, N: int, *,
                         approximate: bool = False) -> Array:
    """Eq. (6): ``Phi = n(phi) / n(-theta/2) = D(-theta/2) / D(phi)`` in ``[0, 1]``.

    (When ``alpha < theta/2`` the largest mark is not at the image edge; ``n_max``
    is then taken at the row straddling the vertical, so ``Phi`` stays in ``[0, 1]``.)
    """
    t0 = pixel_angle(theta, N)
    D = pixel_footprint(phi, alpha, h, t0, approximate=approximate)
    D_min = pixel_footprint(_min_footprint_angle(alpha, theta, t0), alpha, h, t0, approximate=approximate)
    return np.where(np.isfinite(D), D_min / D, 0.0)


def localization_error(k: float, D: ArrayLike) -> Array:
    """Eq. (7): ground error of a detector off by ``k`` pixels, ``E = k D`` (m)."""
    return k * np.asarray(D, dtype=float)


def satisfaction(E: ArrayLike) -> Array:
    """Eq. (8) (and eq. (12) for a covariance-based error): ``S = 1 / (E + 1)`` in ``[0, 1]``."""
    return 1.0 / (np.asarray(E, dtype=float) + 1.0)


def camera_reliability(phi: ArrayLike, alpha: float, h: float, theta: float, N: int, k: float = 1.0, *,
                       approximate: bool = False) -> Array:
    """Eq. (9): ``R_c = Phi S = n / (n(-theta/2) (k D + 1))`` in ``[0, 1]``.

    Parameters
    ----------
    phi : float or array
        Vertical angular coordinate of the point in the image (rad), ``0`` on the
        optical axis, increasing towards the horizon.
    alpha : float
        Installation angle: the optical axis' angle from the downward vertical (rad).
    h : float
        Camera height above the target's plane (m), ``> 0``.
    theta : float
        Vertical field angle (rad); ``N`` the number of pixel rows.
    k : float
        Recognition error of the detector (pixels).

    Zero outside the image rows (``|phi| > theta/2``) and where the row reaches
    the horizon. With ``approximate=True`` the footprint uses eq. (4).
    """
    if not (np.isfinite(h) and h > 0):
        raise ValidationError(f"camera height above the target plane must be positive, got {h!r}")
    if not (np.isfinite(k) and k >= 0):
        raise ValidationError(f"recognition error k must be >= 0 pixels, got {k!r}")
    phi = np.asarray(phi, dtype=float)
    t0 = pixel_angle(theta, N)
    D = pixel_footprint(phi, alpha, h, t0, approximate=approximate)
    Phi = recognition_accuracy(phi, alpha, h, theta, N, approximate=approximate)
    with np.errstate(invalid="ignore"):
        R = np.where(np.isfinite(D), Phi * satisfaction(localization_error(k, D)), 0.0)
    inside = np.abs(phi) <= theta / 2 + 1e-12
    out = np.where(inside, R, 0.0)
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class CameraGeometry:
    """The quantities of eq. (1)-(9) read off a camera: ``alpha``, ``h`` (m), ``theta`` (rad), ``N`` rows."""

    alpha: float
    h: float
    theta: float
    N: int


def _horizontal_heading(camera) -> Array:
    """Unit horizontal direction in which image rows move away from the camera."""
    f = camera.R_wc[:, 2]
    u = f[:2] if np.hypot(*f[:2]) > 1e-9 else -camera.R_wc[:2, 1]  # looking straight down: image "up"
    n = np.hypot(*u)
    if n < 1e-12:
        raise ValidationError("camera has no horizontal heading (optical axis and image rows vertical)")
    return u / n


def camera_geometry(camera) -> CameraGeometry:
    """``alpha, h, theta, N`` of a :class:`~dfusion.models.PinholeCamera`.

    ``h = C_z - point_height``; ``alpha = arccos(-f_z)`` with ``f`` the optical
    axis (0 looking straight down, ``pi/2`` horizontal); ``theta =
    atan(cy / fy) + atan((height - cy) / fy)`` (``2 atan(height / (2 fy))`` for a
    centred principal point); ``N = height``. Raises :class:`ValidationError`
    when the camera is not above the target's plane.
    """
    h = float(camera.position[2] - camera.point_height)
    if not h > 0:
        raise ValidationError(f"the camera is not above the target's plane (height {h:.3g} m)")
    fz = float(np.clip(camera.R_wc[2, 2], -1.0, 1.0))
    alpha = math.acos(-fz)
    theta = math.atan(camera.cy / camera.fy) + math.atan((camera.height - camera.cy) / camera.fy)
    return CameraGeometry(alpha, h, theta, int(camera.height))


def viewing_angle(camera, xy: ArrayLike, geometry: CameraGeometry | None = None) -> float:
    """Vertical angular coordinate ``phi`` of the ground point ``xy`` (eq. (2) inverted).

    ``phi = atan2(d, h) - alpha`` with ``d`` the point's horizontal distance from
    the camera's foot along the camera's heading. For a camera without roll this
    is the angle of the point's image row from the principal point,
    ``atan((cy - v) / fy)``.
    """
    g = geometry or camera_geometry(camera)
    p = np.asarray(xy, dtype=float).reshape(-1)[:2]
    d = float((p - camera.position[:2]) @ _horizontal_heading(camera))
    return math.atan2(d, g.h) - g.alpha


def camera_reliability_at(camera, xy: ArrayLike, k: float | None = None, *, approximate: bool = False) -> float:
    """Eq. (9) for a target at ground position ``xy`` seen by ``camera``.

    Zero when the target is not in the camera's view (``camera.in_view``): the
    camera cannot localize it there. ``k`` (recognition error, pixels) defaults to
    the camera's ``pixel_std``.
    """
    p = np.asarray(xy, dtype=float).reshape(-1)
    if not camera.in_view(p):
        return 0.0
    g = camera_geometry(camera)
    k = camera.pixel_std if k is None else k
    return float(camera_reliability(viewing_angle(camera, p, g), g.alpha, g.h, g.theta, g.N, k,
                                    approximate=approximate))
