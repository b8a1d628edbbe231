r"""A multi-target world: people walking across a plaza, seen by cameras with overlapping views.

**Truth.** A rectangular plaza ``[0, width] x [0, height]`` (m). Each person walks by the
nearly-constant-velocity model (:class:`~dfusion.models.ConstantVelocity`, acceleration
noise ``q``), sampled exactly at the frame times: ``x_{k+1} = F x_k + w_k``,
``w_k ~ N(0, Q(dt))``. ``n_people`` people start inside at uniform positions, each heading
for a uniform point on the plaza's border at a uniform speed in ``speed``; a person who
leaves the plaza dies, and ``mean_birth_wait`` seconds later on average (exponential) a new
person is born just inside a uniform point of the border, heading for a uniform point on
another side (so paths cross). The population stays near ``n_people``.

**Detections.** Every ``1 / rate`` seconds each camera detects each person inside its
view (an axis-aligned rectangle) with probability ``detection``, at the person's position
plus ``N(0, std^2 I)``. False detections: Poisson with mean ``clutter_per_frame`` times the
view's share of the plaza's area, uniform in the view; the clutter density is therefore
``clutter_per_frame / (width height)`` per m^2 in every view (overlapping views each draw
their own). Three generators spawned from the seed (truth, detections, clutter).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.models.measurement import PositionSensor
from dfusion.models.motion import ConstantVelocity
from dfusion.tracking.history import TruthPaths
from dfusion.tracking.track import Scan

__all__ = ["CameraView", "PlazaConfig", "CameraFrame", "PlazaWorld", "simulate_plaza", "plaza_cameras"]


@dataclass(frozen=True)
class CameraView:
    """A camera that sees the rectangle ``[x0, x1] x [y0, y1]`` of the plaza."""

    name: str
    x0: float
    x1: float
    y0: float
    y1: float

    def __post_init__(self) -> None:
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise ValidationError(f"camera {self.name!r}: view must have x1 > x0 and y1 > y0")

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def probability_inside(self, mean: Array, cov: Array) -> float:
        """Probability that a position ``N(mean[:2], cov[:2, :2])`` is in view (the axes taken as independent)."""
        p = 1.0
        for a, (lo, hi) in enumerate(((self.x0, self.x1), (self.y0, self.y1))):
            s = math.sqrt(max(float(cov[a, a]), 1e-18)) * math.sqrt(2.0)
            p *= 0.5 * (math.erf((hi - mean[a]) / s) - math.erf((lo - mean[a]) / s))
        return min(max(p, 0.0), 1.0)

    def contains(self, p: Array, margin: float = 0.0) -> bool:
        """Whether position (or state) ``p`` is in view, or within ``margin`` metres of it."""
        return bool(self.x0 - margin <= p[0] <= self.x1 + margin and self.y0 - margin <= p[1] <= self.y1 + margin)


def plaza_cameras(count: int, width: float = 40.0, height: float = 30.0, overlap: float = 4.0) -> tuple[CameraView, ...]:
    """``count`` cameras covering the plaza with overlapping views.

    1: one view of the whole plaza; 3: three vertical strips; 6: a 3 x 2 grid; neighbouring
    views overlap by ``overlap`` metres.
    """
    grids = {1: (1, 1), 2: (2, 1), 3: (3, 1), 4: (2, 2), 6: (3, 2)}
    if count not in grids:
        raise ValidationError(f"plaza_cameras takes 1, 2, 3, 4 or 6 cameras, got {count!r}")
    nx, ny = grids[count]
    h = overlap / 2.0
    views = []
    for j in range(ny):
        for i in range(nx):
            x0, x1 = width * i / nx, width * (i + 1) / nx
            y0, y1 = height * j / ny, height * (j + 1) / ny
            views.append(CameraView(f"cam{len(views) + 1}", max(0.0, x0 - h), min(width, x1 + h),
                                    max(0.0, y0 - h), min(height, y1 + h)))
    return tuple(views)


@dataclass(frozen=True)
class PlazaConfig:
    """The plaza world's settings (module docstring); the defaults are the issue's scenario."""

    width: float = 40.0
    height: float = 30.0
    n_people: int = 8
    duration: float = 60.0
    rate: float = 10.0
    std: float = 0.3
    detection: float = 0.9
    clutter_per_frame: float = 3.0
    speed: tuple[float, float] = (0.8, 1.6)
    q: float = 0.02
    mean_birth_wait: float = 2.0
    cameras: tuple[CameraView, ...] = field(default_factory=lambda: plaza_cameras(1))
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("width", "height", "duration", "rate", "std", "q", "mean_birth_wait"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValidationError(f"plaza {name} must be positive and finite, got {v!r}")
        if not (isinstance(self.n_people, int) and self.n_people >= 0):
            raise ValidationError(f"n_people must be an integer >= 0, got {self.n_people!r}")
        if not (0.0 <= self.detection <= 1.0):
            raise ValidationError(f"detection probability must be in [0, 1], got {self.detection!r}")
        if not (math.isfinite(self.clutter_per_frame) and self.clutter_per_frame >= 0):
            raise ValidationError(f"clutter_per_frame must be >= 0, got {self.clutter_per_frame!r}")
        if not (0 < self.speed[0] <= self.speed[1]):
            raise ValidationError(f"speed must be a range 0 < lo <= hi, got {self.speed!r}")
        if not self.cameras or len({c.name for c in self.cameras}) != len(self.cameras):
            raise ValidationError("the plaza needs at least one camera, with unique names")

    @property
    def clutter_density(self) -> float:
        """False detections per m^2 per frame in every view."""
        return self.clutter_per_frame / (self.width * self.height)


@dataclass(frozen=True)
class CameraFrame:
    """One camera's detections of one frame: ``z`` (k, 2); ``person[i]`` is the person detected, -1 for clutter."""

    camera: str
    z: Array
    person: Array


@dataclass
class PlazaWorld:
    """Frames of truth and detections.

    Attributes
    ----------
    config : the settings.
    times : (F,) frame times.
    truth : per frame, ``{person: state [x, y, vx, vy]}`` of the people inside the plaza.
    frames : per frame, one :class:`CameraFrame` per camera, in the order of ``config.cameras``.
    """

    config: PlazaConfig
    times: Array
    truth: list[dict[int, Array]]
    frames: list[list[CameraFrame]]

    @property
    def sensor(self) -> PositionSensor:
        return PositionSensor(2, self.config.std)

    def scans(self, k: int) -> list[Scan]:
        """Frame ``k`` as one :class:`~dfusion.tracking.track.Scan` per camera.

        A track's detection probability in a camera's scan is ``P_D`` times the probability
        that its estimated position is in the camera's view
        (:meth:`CameraView.probability_inside`): an estimate a little outside the view of a
        target just inside still takes its detections, and a target near the edge is not
        counted as missed by a camera that probably does not see it.
        """
        c = self.config
        sensor = self.sensor
        return [Scan(float(self.times[k]), f.z, sensor, c.clutter_density, c.detection, view.contains, view.name,
                     view.probability_inside)
                for view, f in zip(c.cameras, self.frames[k])]

    def truth_positions(self, k: int) -> tuple[list[int], Array]:
        """Person ids and (n, 2) positions at frame ``k``."""
        ids = sorted(self.truth[k])
        return ids, np.array([self.truth[k][i][:2] for i in ids]).reshape(-1, 2)

    def truth_paths(self) -> TruthPaths:
        """Every person's path: ``"person <id>"`` -> (times, positions) of the frames where they are in the plaza."""
        got: dict[int, tuple[list[float], list[Array]]] = {}
        for t, people in zip(self.times, self.truth):
            for pid, x in people.items():
                ts, xy = got.setdefault(pid, ([], []))
                ts.append(float(t))
                xy.append(x[:2])
        return TruthPaths({f"person {pid}": (np.array(ts), np.array(xy)) for pid, (ts, xy) in sorted(got.items())})


def _border_point(rng: np.random.Generator, c: PlazaConfig, avoid_side: int | None = None) -> tuple[Array, int]:
    sides = [s for s in range(4) if s != avoid_side]
    side = int(rng.choice(sides))
    u = rng.uniform()
    eps = 1e-3
    p = {0: (u * c.width, eps), 1: (c.width - eps, u * c.height), 2: (u * c.width, c.height - eps),
         3: (eps, u * c.height)}[side]
    return np.array(p, dtype=float), side


def _heading_state(rng: np.random.Generator, c: PlazaConfig, p: Array, side: int | None) -> Array:
    goal, _ = _border_point(rng, c, side)
    d = goal - p
    v = rng.uniform(*c.speed) * d / max(float(np.linalg.norm(d)), 1e-9)
    return np.concatenate([p, v])


def simulate_plaza(config: PlazaConfig) -> PlazaWorld:
    """Sample the plaza world of ``config`` (deterministic by ``config.seed``)."""
    c = config
    rng_truth, rng_det, rng_clutter = (np.random.default_rng(s) for s in np.random.SeedSequence(c.seed).spawn(3))
    motion = ConstantVelocity(2, c.q)
    dt = 1.0 / c.rate
    steps = int(round(c.duration * c.rate))
    times = np.round(dt * np.arange(1, steps + 1), 9)
    F, L = motion.F(dt), np.linalg.cholesky(motion.Q(dt))
    alive: dict[int, Array] = {}
    for i in range(c.n_people):
        p = np.array([rng_truth.uniform(0, c.width), rng_truth.uniform(0, c.height)])
        alive[i] = _heading_state(rng_truth, c, p, None)
    next_id = c.n_people
    births: list[float] = []
    truth: list[dict[int, Array]] = []
    frames: list[list[CameraFrame]] = []
    for t in times:
        for pid in sorted(alive):
            alive[pid] = F @ alive[pid] + L @ rng_truth.standard_normal(4)
        for pid in [pid for pid, x in alive.items() if not (0 <= x[0] <= c.width and 0 <= x[1] <= c.height)]:
            del alive[pid]
            births.append(float(t) + rng_truth.exponential(c.mean_birth_wait))
        for tb in sorted(b for b in births if b <= t):
            births.remove(tb)
            p, side = _border_point(rng_truth, c)
            alive[next_id] = _heading_state(rng_truth, c, p, side)
            next_id += 1
        truth.append({pid: x.copy() for pid, x in sorted(alive.items())})
        per_cam = []
        for view in c.cameras:
            zs, who = [], []
            for pid in sorted(alive):
                x = alive[pid]
                if view.contains(x) and rng_det.uniform() < c.detection:
                    zs.append(x[:2] + c.std * rng_det.standard_normal(2))
                    who.append(pid)
            k = int(rng_clutter.poisson(c.clutter_per_frame * view.area / (c.width * c.height)))
            for _ in range(k):
                zs.append(np.array([rng_clutter.uniform(view.x0, view.x1), rng_clutter.uniform(view.y0, view.y1)]))
                who.append(-1)
            order = rng_det.permutation(len(zs))          # detections come in no particular order
            z = np.array(zs).reshape(-1, 2)[order]
            per_cam.append(CameraFrame(view.name, z, np.array(who, dtype=int)[order]))
        frames.append(per_cam)
    return PlazaWorld(c, times, truth, frames)
