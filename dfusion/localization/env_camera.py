r"""Environmental-camera localization: a robot seen by a calibrated ceiling camera.

A camera fixed in the environment (Hu et al.'s switching paper, sec. 2.1: "obliquely
installed on the ceiling") sees a marker on the robot. The marker's pixel ``(u, v)`` is
back-projected onto the plane the marker moves in
(:meth:`dfusion.models.PinholeCamera.ground_point`), which gives the robot's position;
its covariance is the pixel noise propagated through the back-projection,
``S = sigma_px^2 J J^T`` with ``J = (d pixel / d position)^-1`` (the inverse of the 2 x 2
position block of :meth:`PinholeCamera.H`). One marker does not show the heading: the
localizer takes it from the direction of the displacement since the previous fix when the
robot moved at least ``min_baseline`` (``var(heading) = (tr S_prev + tr S) / d^2``), and
reports an uninformative heading (variance ``pi^2 / 3``, a uniform angle) otherwise.

Reliability: the switching paper's environmental-camera model, eq. 1-9
(:func:`dfusion.reliability.camera_reliability`, the shared implementation of
``dfusion/reliability.py``): with the camera's installation angle ``alpha`` (optical axis
to the downward vertical), height ``h`` above the marker plane, vertical field angle
``theta`` and ``N`` pixel rows (:func:`dfusion.reliability.camera_geometry`), a pixel row
at vertical angular coordinate ``phi = atan((cy - v) / fy)`` (positive towards the
horizon; a camera without roll) covers ``D(phi) = h (tan(phi + alpha + theta / N) -
tan(phi + alpha))`` metres of ground, and::

    R_c = Phi S = D(phi_min) / (D(phi) (k D(phi) + 1))                     (9)

with ``k`` the recognition error in pixels (``k_pixels``, default the camera's
``pixel_std``) and ``phi_min = -theta/2`` (the image row nearest to the camera).
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import NotInitializedError, ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.linalg import as_vector, symmetrize
from dfusion.models.camera import PinholeCamera
from dfusion.reliability import camera_geometry, camera_reliability

__all__ = ["EnvironmentCameraLocalizer"]


class EnvironmentCameraLocalizer:
    """Localizes a robot from the pixel of its marker in a calibrated ceiling camera.

    Parameters
    ----------
    camera : PinholeCamera
        The calibrated camera (pose, intrinsics, pixel noise, marker plane height).
    k_pixels : float
        Recognition error ``k`` of eq. 7 (pixels); default the camera's ``pixel_std``.
    min_baseline : float
        Minimum displacement (m) between two fixes to estimate the heading.
    max_gap : float
        Two fixes further apart in time (s) do not give a heading.
    """

    def __init__(self, camera: PinholeCamera, *, k_pixels: float | None = None, min_baseline: float = 0.3,
                 max_gap: float = 5.0) -> None:
        if not isinstance(camera, PinholeCamera):
            raise ValidationError("camera must be a PinholeCamera")
        self.camera = camera
        self.geometry = camera_geometry(camera)
        self.k = float(camera.pixel_std if k_pixels is None else k_pixels)
        self.min_baseline = float(min_baseline)
        self.max_gap = float(max_gap)
        self._prev: tuple[float, np.ndarray, np.ndarray] | None = None
        self.last: Estimate | None = None

    def reliability(self, pixel: ArrayLike) -> float:
        """``R_c`` of eq. 9 at this pixel."""
        u, v = as_vector(pixel, 2, "pixel")
        g = self.geometry
        phi = math.atan((self.camera.cy - float(v)) / self.camera.fy)
        return float(camera_reliability(phi, g.alpha, g.h, g.theta, g.N, self.k))

    def position(self, pixel: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Ground position ``(x, y)`` of the marker and its covariance."""
        cam = self.camera
        p = cam.ground_point(pixel)
        Hp = cam.H(p)[:, :2]
        J = np.linalg.inv(Hp)
        S = symmetrize(cam.pixel_std**2 * J @ J.T)
        return p, S

    def predict(self, t: float, u: None = None) -> None:
        """Nothing to do: every fix stands on its own (the heading comes from two fixes)."""

    def update(self, t: float, z: ArrayLike) -> bool:
        """A fix from the marker's pixel ``z`` at time ``t`` (:meth:`estimate` then returns it);
        ``False`` if the pixel is outside the image or its ray misses the marker plane."""
        z = as_vector(z, 2, "pixel")
        cam = self.camera
        if not (0.0 <= z[0] < cam.width and 0.0 <= z[1] < cam.height):
            return False
        try:
            p, S = self.position(z)
        except (ValidationError, np.linalg.LinAlgError):
            return False
        heading, var_h = 0.0, math.pi**2 / 3.0
        if self._prev is not None and 0.0 < float(t) - self._prev[0] <= self.max_gap:
            d = p - self._prev[1]
            dist = float(np.hypot(*d))
            if dist >= self.min_baseline:
                heading = math.atan2(d[1], d[0])
                var_h = float(np.trace(self._prev[2]) + np.trace(S)) / dist**2
        self._prev = (float(t), p, S)
        cov = np.zeros((3, 3))
        cov[:2, :2] = S
        cov[2, 2] = var_h
        self.last = Estimate("env_camera", float(t), np.array([p[0], p[1], heading]), cov, self.reliability(z))
        return True

    def estimate(self) -> Estimate:
        """The latest fix: mean ``(x, y, heading)``, 3 x 3 covariance and the reliability ``R_c``."""
        if self.last is None:
            raise NotInitializedError("no fix yet: call update() with a pixel in the image first")
        return self.last
