"""Pinhole camera observing a point on a horizontal plane.

``PinholeCamera``: a calibrated camera with known pose that sees a target whose
``(x, y)`` position is the first two state components, on the plane
``z = point_height`` (Hartley & Zisserman, *Multiple View Geometry in Computer
Vision*, 2nd ed., 2004, sec. 6.1 for the projection, sec. 8.1.1 for the
plane-to-image homography ``K [r1 r2 t]``). Camera frame: ``z`` forward (optical
axis), ``x`` right, ``y`` down in the image::

    p_w = (x, y, point_height)
    p_c = R_wc^T (p_w - C)
    h(x) = (fx p_c[0] / p_c[2] + cx,  fy p_c[1] / p_c[2] + cy)        (pixels)

``MountedCamera``: a camera on a moving platform (a robot driving a path): at time ``t``
it is the :class:`SceneCamera` at the platform's pose, ``MountedCamera.at(t)``.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any, Callable

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array, as_finite, as_matrix, as_positive, as_vector
from dfusion.models.base import MeasurementModel
from dfusion.models.measurement import position_state


def _image_size(value: int, name: str) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise ValidationError(f"{name} must be a positive integer, got {value!r}") from None
    if v != value or v <= 0:
        raise ValidationError(f"{name} must be a positive integer, got {value!r}")
    return v


class PinholeCamera(MeasurementModel):
    """Calibrated pinhole camera with known pose observing a point on a plane.

    Projection (Hartley & Zisserman, 2004, sec. 6.1), with ``(X, Y, Z) = p_c``::

        p_c  = R_wc^T (p_w - C),   p_w = (x, y, point_height)
        h(x) = (fx X / Z + cx, fy Y / Z + cy)
        H(x) = [[fx / Z, 0, -fx X / Z^2],
                [0, fy / Z, -fy Y / Z^2]] @ R_wc^T[:, :2]      (zeros beyond x, y)

    ``R = pixel_std^2 I_2``. ``h`` and ``H`` raise :class:`ValidationError` for a
    point behind (or in the plane of) the camera, ``Z <= 1e-9`` m, where the
    projection is undefined; call :meth:`in_view` first.

    Parameters
    ----------
    position : 3-vector
        Camera centre ``C`` in world coordinates (m).
    R_wc : 3x3 rotation
        Orientation: maps camera-frame vectors to world-frame vectors (its columns
        are the camera's right, down and forward axes in world coordinates).
    fx, fy : float
        Focal lengths (pixels), ``> 0``.
    cx, cy : float
        Principal point (pixels).
    width, height : int
        Image size (pixels). Pixel coordinates are continuous with ``(0, 0)`` the
        top-left corner of the image; the image is ``[0, width) x [0, height)``.
    pixel_std : float
        Pixel noise standard deviation (pixels), ``> 0``.
    point_height : float
        Height ``z`` (m) of the plane the observed point lies on.
    min_depth : float
        Minimum depth ``Z`` (m) for :meth:`in_view` to report the point visible.
    """

    dim_z = 2
    is_linear = False
    #: Depth (m) at or below which the projection is undefined.
    MIN_PROJECT_DEPTH = 1e-9

    def __init__(
        self,
        position: Array,
        R_wc: Array,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        pixel_std: float = 1.0,
        point_height: float = 0.0,
        min_depth: float = 0.01,
    ) -> None:
        self.position = as_vector(position, 3, "PinholeCamera position")
        R = as_matrix(R_wc, (3, 3), "PinholeCamera R_wc")
        if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) <= 0:
            raise ValidationError("PinholeCamera R_wc must be a rotation matrix (orthonormal, det = +1)")
        self.R_wc = R
        self.fx = as_positive(fx, "PinholeCamera fx")
        self.fy = as_positive(fy, "PinholeCamera fy")
        self.cx = as_finite(cx, "PinholeCamera cx")
        self.cy = as_finite(cy, "PinholeCamera cy")
        self.width = _image_size(width, "PinholeCamera width")
        self.height = _image_size(height, "PinholeCamera height")
        self.pixel_std = as_positive(pixel_std, "PinholeCamera pixel_std")
        self.point_height = as_finite(point_height, "PinholeCamera point_height")
        self.min_depth = as_positive(min_depth, "PinholeCamera min_depth")
        self._R = self.pixel_std**2 * np.eye(2)

    @classmethod
    def looking_at(
        cls,
        position: Array,
        target: Array,
        up: Array = (0.0, 0.0, 1.0),
        *,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        pixel_std: float = 1.0,
        point_height: float = 0.0,
        min_depth: float = 0.01,
    ) -> "PinholeCamera":
        """Camera at ``position`` whose optical axis points at ``target`` (both 3-D, m).

        ``forward = (target - position) / ||.||``, ``right = forward x up / ||.||``,
        ``down = forward x right``, ``R_wc = [right, down, forward]`` (columns), so
        ``up`` appears upwards in the image. Raises :class:`ValidationError` when
        ``target == position`` or ``up`` is parallel to the viewing direction.
        """
        C = as_vector(position, 3, "looking_at position")
        T = as_vector(target, 3, "looking_at target")
        U = as_vector(up, 3, "looking_at up")
        fwd = T - C
        nf = np.linalg.norm(fwd)
        if nf < 1e-12:
            raise ValidationError("looking_at: target coincides with the camera position")
        fwd = fwd / nf
        right = np.cross(fwd, U)
        nr = np.linalg.norm(right)
        if nr < 1e-9 * max(np.linalg.norm(U), 1e-300):
            raise ValidationError("looking_at: 'up' is parallel to the viewing direction; choose another 'up'")
        right = right / nr
        down = np.cross(fwd, right)
        R_wc = np.column_stack([right, down, fwd])
        return cls(C, R_wc, fx, fy, cx, cy, width, height, pixel_std, point_height, min_depth)

    def __repr__(self) -> str:
        return (
            f"PinholeCamera(position={self.position.tolist()}, fx={self.fx}, fy={self.fy}, "
            f"cx={self.cx}, cy={self.cy}, width={self.width}, height={self.height}, "
            f"pixel_std={self.pixel_std}, point_height={self.point_height})"
        )

    @property
    def K(self) -> Array:
        """Intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def camera_point(self, x: Array) -> Array:
        """The observed point in the camera frame, ``p_c = R_wc^T (p_w - C)`` (m)."""
        x = position_state(x, "PinholeCamera")
        p_w = np.array([x[0], x[1], self.point_height])
        return self.R_wc.T @ (p_w - self.position)

    def _pixel(self, p_c: Array) -> Array:
        return np.array([self.fx * p_c[0] / p_c[2] + self.cx, self.fy * p_c[1] / p_c[2] + self.cy])

    def _check_depth(self, p_c: Array) -> None:
        if p_c[2] <= self.MIN_PROJECT_DEPTH:
            raise ValidationError(
                f"PinholeCamera: point is behind or in the plane of the camera (depth {p_c[2]:.3g} m)"
            )

    def h(self, x: Array) -> Array:
        p_c = self.camera_point(x)
        self._check_depth(p_c)
        return self._pixel(p_c)

    def H(self, x: Array) -> Array:
        n = position_state(x, "PinholeCamera").shape[0]
        X, Y, Z = p_c = self.camera_point(x)
        self._check_depth(p_c)
        J_proj = np.array([[self.fx / Z, 0.0, -self.fx * X / Z**2], [0.0, self.fy / Z, -self.fy * Y / Z**2]])
        H = np.zeros((2, n))
        H[:, :2] = J_proj @ self.R_wc.T[:, :2]
        return H

    @property
    def R(self) -> Array:
        return self._R

    def in_view(self, x: Array) -> bool:
        """True when the point is in front of the camera (depth ``> min_depth``) and
        projects inside the image, ``0 <= u < width`` and ``0 <= v < height``."""
        p_c = self.camera_point(x)
        if not p_c[2] > self.min_depth:
            return False
        u, v = self._pixel(p_c)
        return bool(0.0 <= u < self.width and 0.0 <= v < self.height)

    def ground_point(self, pixel: Array) -> Array:
        """Back-project ``pixel = (u, v)`` onto the plane ``z = point_height``; returns ``(x, y)``.

        The ray ``C + s R_wc d``, ``d = ((u - cx)/fx, (v - cy)/fy, 1)``, meets the plane at
        ``s = (point_height - C_z) / (R_wc d)_z``; ``s`` is the depth of the point. Raises
        :class:`ValidationError` unless ``s > 0`` (the ray hits the plane in front of the camera).
        """
        u, v = as_vector(pixel, 2, "PinholeCamera pixel")
        d_w = self.R_wc @ np.array([(u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0])
        dz = self.point_height - self.position[2]
        if abs(d_w[2]) < 1e-12 or dz / d_w[2] <= 0.0:
            raise ValidationError(
                f"PinholeCamera: the ray through pixel ({u}, {v}) does not hit the plane "
                f"z = {self.point_height} in front of the camera"
            )
        s = dz / d_w[2]
        p = self.position + s * d_w
        return p[:2].copy()

    def homography(self) -> Array:
        """Plane-to-image homography ``G = K [r1 r2 t]`` (3 x 3).

        With ``R_cw = R_wc^T = [r1 r2 r3]`` (columns) and ``t = -R_cw C`` the camera
        translation, a point ``(x, y)`` on the plane ``z = point_height`` maps to the
        homogeneous pixel ``G (x, y, 1)^T``, where the plane's height is folded into
        the translation: ``G = K [r1, r2, t + point_height r3]`` (Hartley & Zisserman,
        2004, sec. 8.1.1; Zhang, *A flexible new technique for camera calibration*,
        IEEE TPAMI 22(11), 2000, sec. 2.2).
        """
        R_cw = self.R_wc.T
        t = -R_cw @ self.position + self.point_height * R_cw[:, 2]
        return self.K @ np.column_stack([R_cw[:, 0], R_cw[:, 1], t])


class SceneCamera(PinholeCamera):
    """A :class:`PinholeCamera` that also produces false detections in the simulated world.

    ``clutter_rate`` is the mean number of false detections per frame (Poisson);
    :meth:`sample_clutter` draws them uniformly in the image.
    """

    def __init__(self, *args: Any, clutter_rate: float = 0.0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not (math.isfinite(clutter_rate) and clutter_rate >= 0):
            raise ValidationError(f"false_detection_rate must be >= 0, got {clutter_rate!r}")
        self.clutter_rate = float(clutter_rate)

    def sample_clutter(self, rng: np.random.Generator, k: int) -> Array:
        """``k`` false detections ``(u, v)`` uniform in ``[0, width) x [0, height)``, shape ``(k, 2)``."""
        return rng.random((int(k), 2)) * np.array([self.width, self.height], dtype=float)


class MountedCamera:
    """A camera carried by a moving platform: at time ``t`` the :class:`SceneCamera` at its pose.

    The platform's pose ``(x, y, theta)`` at ``t`` comes from ``pose(t)`` (for a robot of a
    scenario its :class:`~dfusion.geometry.WaypointPath`: the robot knows where it is). The
    camera sits ``mount_height`` metres above the ground, looks along the platform's heading
    turned by ``yaw_offset`` and tilted down by ``pitch`` (radians)::

        C(t) = (x, y, mount_height)
        forward(t) = (cos(pitch) cos(psi), cos(pitch) sin(psi), -sin(pitch)),   psi = theta + yaw_offset

    and :meth:`at` builds ``SceneCamera.looking_at(C, C + forward, up = z)``. Measurement
    models need the time: the simulated world, the front end and the centralized reference
    take ``at(t)`` of the measurement's time ``t``.
    """

    dim_z = 2
    is_linear = False

    def __init__(self, pose: Callable[[float], Array], *, mount_height: float, pitch: float, yaw_offset: float = 0.0,
                 fx: float, fy: float, cx: float, cy: float, width: int, height: int, pixel_std: float = 1.0,
                 point_height: float = 0.0, clutter_rate: float = 0.0) -> None:
        self.pose = pose
        self.mount_height = as_finite(mount_height, "mount_height")
        if self.mount_height <= point_height:
            raise ValidationError(f"mount_height must be above point_height, got {mount_height!r}")
        self.pitch = as_finite(pitch, "pitch")
        if not 0.0 < self.pitch < math.pi / 2:
            raise ValidationError(f"pitch must be in (0, 90) degrees down, got {math.degrees(self.pitch)!r}")
        self.yaw_offset = as_finite(yaw_offset, "yaw_offset")
        self._kw = dict(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, pixel_std=pixel_std,
                        point_height=point_height)
        self.clutter_rate = float(clutter_rate)
        self.pixel_std = as_positive(pixel_std, "pixel_std")
        self._cache: OrderedDict[float, SceneCamera] = OrderedDict()
        self.at(0.0)    # checks the intrinsics once

    def __repr__(self) -> str:
        return (f"MountedCamera(mount_height={self.mount_height}, pitch={math.degrees(self.pitch):.1f} deg, "
                f"{self._kw})")

    @property
    def R(self) -> Array:
        return self.pixel_std**2 * np.eye(2)

    def at(self, t: float) -> SceneCamera:
        """The camera at time ``t`` (the last 64 are kept)."""
        t = float(t)
        cam = self._cache.get(t)
        if cam is not None:
            return cam
        x, y, theta = (float(v) for v in self.pose(t))
        psi = theta + self.yaw_offset
        c = np.array([x, y, self.mount_height])
        fwd = np.array([math.cos(self.pitch) * math.cos(psi), math.cos(self.pitch) * math.sin(psi),
                        -math.sin(self.pitch)])
        base = PinholeCamera.looking_at(c, c + fwd, (0.0, 0.0, 1.0), **self._kw)
        cam = SceneCamera(base.position, base.R_wc, **self._kw, clutter_rate=self.clutter_rate)
        self._cache[t] = cam
        if len(self._cache) > 64:
            self._cache.popitem(last=False)
        return cam

