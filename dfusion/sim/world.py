"""Ground truth and sensor measurements of a scenario, deterministic by seed.

The target moves by its motion model: ``x(t_{i+1}) = f(x(t_i), dt_i) + w_i``,
``w_i ~ N(0, Q(dt_i))``, sampled exactly on the union of the filter grid
``k dt`` and every measurement time, from ``x(0) ~ N(initial_mean, initial_cov)``
(the filters' prior, so that consistency tests are meaningful). Each node
measures at ``phase + k / rate`` while active, with probability ``detection``,
``z = h(x(t)) + v``, ``v ~ N(0, R)``; a sensor with an ``in_view(x)`` method
(a camera) only measures when the target is in view; a sensor that moves (a camera on a
robot, :func:`dfusion.models.base.model_at`) measures from where it is at ``t``. A node
measures only while it is in the network (it may join late or leave early). Measurements
reach the node ``U[0, delay]`` seconds late.

False detections (clutter): a sensor with a positive ``clutter_rate`` attribute
(a camera with ``false_detection_rate``) also produces, at every measurement
time while active, a Poisson(``clutter_rate``) number of false measurements
drawn by its ``sample_clutter(rng, k)`` (uniform in the image for a camera),
whether or not the target is in view or detected. They arrive with the frame's
delay and are flagged ``Measurement.clutter``. Their random draws come from a
third generator spawned from the seed, so the truth and the true measurements
of a scenario do not change when clutter is switched on, and scenarios without
clutter produce bit-identical worlds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfusion.linalg import Array
from dfusion.models.base import model_at
from dfusion.scenario.spec import Scenario

TIME_DECIMALS = 9


@dataclass(frozen=True)
class Measurement:
    """A measurement of ``node`` taken at ``t`` that reaches it at ``arrival``."""

    t: float
    node: str
    z: Array
    arrival: float
    #: A false detection (clutter), not a measurement of the target.
    clutter: bool = False


@dataclass
class World:
    """Truth at every simulated time, and every measurement in time order."""

    times: Array            # (T,) sorted
    states: Array           # (T, n)
    measurements: list[Measurement]
    #: The source's time of time 0, in ns (a bag's header stamp; 0 for a simulated world).
    origin_ns: int = 0

    @property
    def n_clutter(self) -> int:
        """Number of false detections among the measurements."""
        return sum(m.clutter for m in self.measurements)

    def truth(self, t: float) -> Array:
        i = int(np.searchsorted(self.times, t - 1e-9))
        if i >= len(self.times) or abs(self.times[i] - t) > 1e-9:
            raise KeyError(f"no truth at t={t}")
        return self.states[i]


def simulate_world(sc: Scenario) -> World:
    """Sample the truth and the measurements of scenario ``sc`` (seeded by ``sc.seed``)."""
    ss = np.random.SeedSequence(sc.seed)
    rng_truth, rng_meas = (np.random.default_rng(s) for s in ss.spawn(2))
    grid = np.round(sc.dt * np.arange(sc.steps + 1), TIME_DECIMALS)
    planned: list[tuple[float, str]] = []
    for name in sorted(sc.nodes):
        spec = sc.nodes[name]
        if spec.sensor is None or spec.rate <= 0:
            continue
        k = np.arange(1, int(np.floor((sc.duration - spec.phase) * spec.rate + 1e-9)) + 1)
        for t in np.round(spec.phase + k / spec.rate, TIME_DECIMALS):
            if 0 < t <= sc.duration + 1e-12:
                planned.append((float(t), name))
    times = np.unique(np.concatenate([grid, np.array([t for t, _ in planned], dtype=float)]))
    motion = sc.target.motion
    n = motion.dim
    states = np.empty((len(times), n))
    C0 = np.linalg.cholesky(sc.target.initial_cov)
    x = sc.target.initial_mean + C0 @ rng_truth.standard_normal(n)
    states[0] = x
    for i in range(1, len(times)):
        dt = times[i] - times[i - 1]
        Cq = np.linalg.cholesky(motion.Q(dt, x))
        x = motion.normalize(motion.f(x, dt) + Cq @ rng_truth.standard_normal(n))
        states[i] = x
    index = {float(t): i for i, t in enumerate(times)}
    meas: list[Measurement] = []
    rng_clutter = None   # spawned only when needed (does not disturb the other two streams)
    for t, name in sorted(planned):
        spec = sc.nodes[name]
        sensor = model_at(spec.sensor, t)
        draw = rng_meas.random()
        noise = rng_meas.standard_normal(sensor.dim_z)
        delay = rng_meas.uniform(0.0, spec.delay) if spec.delay > 0 else 0.0
        arrival = round(t + delay, TIME_DECIMALS)
        x = states[index[t]]
        if spec.is_active(t) and draw < spec.detection and not (hasattr(sensor, "in_view") and not sensor.in_view(x)):
            z = sensor.h(x) + np.linalg.cholesky(sensor.R) @ noise
            meas.append(Measurement(t, name, z, arrival))
        rate = float(getattr(sensor, "clutter_rate", 0.0) or 0.0)
        if rate > 0 and spec.is_active(t):
            if rng_clutter is None:
                rng_clutter = np.random.default_rng(np.random.SeedSequence(sc.seed).spawn(3)[2])
            k = int(rng_clutter.poisson(rate))
            for z in np.atleast_2d(sensor.sample_clutter(rng_clutter, k))[:k]:
                meas.append(Measurement(t, name, np.asarray(z, dtype=float), arrival, clutter=True))
    return World(times, states, meas)
