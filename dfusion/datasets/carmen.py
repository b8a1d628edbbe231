r"""Reader for CARMEN text logs (``FLASER`` / ``ODOM`` / ``PARAM``; plain or gzip).

Format (one message per line, fields separated by spaces; CARMEN logger, see
http://carmen.sourceforge.net/logger_playback.html)::

    FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp
    PARAM name value [host timestamp]

Pitfalls handled (found in the Intel Research Lab log; an excerpt, its source and
where to get the full logs are in ``tests/data/carmen/README.md``):

* Each ``FLASER`` line is followed by an ``ODOM`` line that only *repeats the scan pose*
  with a meaningless time stamp (0 or ``1e-153``). Such an ``ODOM`` line (the one right
  after a ``FLASER`` whose pose equals the scan pose to ``1e-6``) is dropped from the pose
  stream and counted in ``CarmenLog.dropped_odom_copies``.
* ``NEFF`` lines (a non-standard per-scan number) are attached to the preceding scan
  (``LaserScan.neff``); other unknown message types are counted in ``CarmenLog.unknown``.
* Time stamps are *not monotonic* (ODOM and FLASER both step backwards). By default
  (``sort=True``) scans and odometry are stably sorted by time stamp; the number of
  backward steps in file order is kept in ``CarmenLog.backward_steps``.
* "No return" readings are stored as the maximum range (81.83 m in the Intel log).
  Readings ``>= max_range - 1e-6`` are flagged invalid (``LaserScan.valid``); keep them as
  "free up to max range" or drop them, depending on the sensor model.
* Beams are ordered from the robot's right to its left. The ``n`` beam angles are either
  spread exactly over the field of view, ``linspace(-fov/2, fov/2, n)``
  (``beam_layout="span"``), or start at ``-fov/2`` in steps of ``fov / n``
  (``beam_layout="step"``); readers differ (see the README). The default (``"step"``) was
  chosen on the Intel log: the pooled median distance from each end point to the nearest
  end point of the previous scan (both projected from their corrected poses) is 3.13 cm
  with ``"step"``, 3.21 cm with ``"span"`` and 3.18 cm with half-step-centred beams (the
  difference is small: the layouts differ by at most one degree).
* ``FLASER``'s ``x y theta`` is the *laser* pose and ``odom_*`` the robot's odometry pose;
  in the Intel log they are identical (corrected poses, laser offset 0).
* The velocities ``tv rv accel`` in ``ODOM`` are zero in the Intel log; they are read but
  not relied upon.
"""
from __future__ import annotations

import gzip
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from dfusion.errors import ValidationError

logger = logging.getLogger(__name__)

__all__ = ["LaserScan", "CarmenLog", "read_carmen", "beam_angles"]


def beam_angles(n: int, fov: float = math.pi, layout: Literal["span", "step"] = "step") -> np.ndarray:
    """Beam angles (rad, right to left) of an ``n``-beam scan over ``fov``."""
    if layout == "span":
        return np.linspace(-fov / 2, fov / 2, n)
    if layout == "step":
        return -fov / 2 + np.arange(n) * (fov / n)
    raise ValidationError(f"beam layout must be 'span' or 'step', got {layout!r}")


@dataclass
class LaserScan:
    """One ``FLASER`` message."""

    t: float
    ranges: np.ndarray
    angles: np.ndarray
    laser_pose: np.ndarray
    odom_pose: np.ndarray
    valid: np.ndarray
    neff: float | None = None
    line: int = 0

    def points(self, frame: Literal["laser", "world"] = "laser") -> np.ndarray:
        """End points ``(K, 2)`` of the valid beams, in the laser frame or the log's frame."""
        r, a = self.ranges[self.valid], self.angles[self.valid]
        if frame == "laser":
            return np.column_stack([r * np.cos(a), r * np.sin(a)])
        x, y, th = self.laser_pose
        return np.column_stack([x + r * np.cos(th + a), y + r * np.sin(th + a)])


@dataclass
class CarmenLog:
    """Contents of a CARMEN log.

    Attributes
    ----------
    params : dict
        ``PARAM`` name -> value (float when numeric).
    scans : list[LaserScan]
    odom_t : (N,) array
        Time stamps of the ODOM pose stream (copies after FLASER removed).
    odom : (N, 3) array
        ODOM poses ``(x, y, theta)``.
    odom_vel : (N, 3) array
        ``(tv, rv, accel)`` of each ODOM line.
    dropped_odom_copies : int
    backward_steps : dict
        ``{"scans": k, "odom": k}`` backward time steps in file order.
    unknown : dict
        Counts of message types the reader does not interpret.
    """

    params: dict = field(default_factory=dict)
    scans: list = field(default_factory=list)
    odom_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    odom_vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dropped_odom_copies: int = 0
    backward_steps: dict = field(default_factory=dict)
    unknown: dict = field(default_factory=dict)

    @property
    def scan_times(self) -> np.ndarray:
        return np.array([s.t for s in self.scans])

    @property
    def scan_poses(self) -> np.ndarray:
        return np.array([s.laser_pose for s in self.scans]).reshape(-1, 3)


def _open(path: Path):
    with open(path, "rb") as f:
        magic = f.read(2)
    if magic == b"\x1f\x8b":
        return gzip.open(path, "rt", encoding="ascii", errors="replace")
    return open(path, encoding="ascii", errors="replace")


def _num(s: str) -> float | str:
    try:
        return float(s)
    except ValueError:
        return s


def read_carmen(
    path: str | Path,
    *,
    fov: float = math.pi,
    beam_layout: Literal["span", "step"] = "step",
    max_range: float = 81.83,
    sort: bool = True,
    max_lines: int | None = None,
) -> CarmenLog:
    """Read a CARMEN log (see the module docstring for the conventions).

    Parameters
    ----------
    path : file name (``.gz`` or plain text, detected from the content)
    fov : field of view of the front laser (rad)
    beam_layout : ``"span"`` or ``"step"`` (see :func:`beam_angles`)
    max_range : readings at or above this (m) are "no return" (``valid = False``)
    sort : stably sort scans and odometry by time stamp
    max_lines : stop after this many lines

    Raises
    ------
    ValidationError
        For a malformed ``FLASER`` or ``ODOM`` line (with its line number).
    """
    path = Path(path)
    log = CarmenLog()
    odom_t: list[float] = []
    odom: list[tuple[float, float, float]] = []
    vel: list[tuple[float, float, float]] = []
    angle_cache: dict[int, np.ndarray] = {}
    prev_type = None
    with _open(path) as fh:
        for lineno, raw in enumerate(fh, 1):
            if max_lines is not None and lineno > max_lines:
                break
            f = raw.split()
            if not f or f[0].startswith("#"):
                continue
            kind = f[0]
            try:
                if kind == "FLASER":
                    n = int(f[1])
                    if len(f) < 2 + n + 9:
                        raise ValueError(f"expected {2 + n + 9} fields, got {len(f)}")
                    r = np.array(f[2 : 2 + n], dtype=float)
                    rest = f[2 + n :]
                    lp = np.array(rest[0:3], dtype=float)
                    op = np.array(rest[3:6], dtype=float)
                    t = float(rest[6])
                    if n not in angle_cache:
                        angle_cache[n] = beam_angles(n, fov, beam_layout)
                    valid = np.isfinite(r) & (r > 0) & (r < max_range - 1e-6)
                    log.scans.append(LaserScan(t, r, angle_cache[n], lp, op, valid, None, lineno))
                elif kind == "ODOM":
                    if len(f) < 10:
                        raise ValueError(f"expected 10 fields, got {len(f)}")
                    pose = (float(f[1]), float(f[2]), float(f[3]))
                    if prev_type == "FLASER" and np.allclose(pose, log.scans[-1].laser_pose, atol=1e-6, rtol=0):
                        log.dropped_odom_copies += 1
                    else:
                        odom.append(pose)
                        vel.append((float(f[4]), float(f[5]), float(f[6])))
                        odom_t.append(float(f[7]))
                elif kind == "NEFF":
                    if log.scans and len(f) > 1:
                        log.scans[-1].neff = float(f[1])
                elif kind == "PARAM":
                    if len(f) >= 3:
                        log.params[f[1]] = _num(f[2])
                else:
                    log.unknown[kind] = log.unknown.get(kind, 0) + 1
            except (ValueError, IndexError) as exc:
                raise ValidationError(f"{path}:{lineno}: malformed {kind} line: {exc}") from None
            prev_type = kind
    t_o = np.asarray(odom_t, dtype=float)
    t_s = np.array([s.t for s in log.scans], dtype=float)
    log.backward_steps = {"scans": int(np.sum(np.diff(t_s) < 0)), "odom": int(np.sum(np.diff(t_o) < 0))}
    o = np.asarray(odom, dtype=float).reshape(-1, 3)
    v = np.asarray(vel, dtype=float).reshape(-1, 3)
    if sort:
        k = np.argsort(t_o, kind="stable")
        t_o, o, v = t_o[k], o[k], v[k]
        order = np.argsort(t_s, kind="stable")
        log.scans = [log.scans[i] for i in order]
    log.odom_t, log.odom, log.odom_vel = t_o, o, v
    logger.info(
        "%s: %d scans, %d odometry poses (%d scan-pose copies dropped), backward time steps %s, unknown messages %s",
        path, len(log.scans), t_o.size, log.dropped_odom_copies, log.backward_steps, log.unknown or "none",
    )
    return log
