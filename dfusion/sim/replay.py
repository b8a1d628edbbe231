r"""A scenario's nodes fed from a ROS bag instead of the simulated world (``dfusion replay``).

The scenario file still says what the nodes are (sensor kinds, their models and front
ends), the tree, the links, the target's motion model and prior, ``dt`` and the window;
the bag replaces :func:`dfusion.sim.world.simulate_world`: each mapped topic's messages
become its node's measurements, and an optional truth topic the ground truth. The run
itself is :func:`dfusion.sim.runner.run_scenario`, so the table, the series, the figures
and the MCAP recording are the same as for ``dfusion simulate``.

**Times.** Scenario time 0 is the earliest header stamp among the mapped topics and the
truth topic (or ``origin_ns``); a message's measurement time is its header stamp (``t``), never its
record time. With ``arrival="stamp"`` (the default: an offline replay) each
measurement reaches its node at ``t``, so the bag's record order does not matter. With
``arrival="record"`` it reaches its node at its record time, as the robot received it:
a message recorded after newer ones is a *late measurement*, fused at its own stamp by
the delayed-state filter (or refused and counted when it is older than the window),
exactly as the simulated world's delayed measurements.

**Measurements.** A node's measurement vector ``z`` comes from the message by the
standard conversion of its type (:mod:`dfusion.bags.convert`), cut to what the node's
sensor kind expects:

====================================================  ================================
message type                                          ``z``
====================================================  ================================
``geometry_msgs/PointStamped``,                       ``(x, y)``: a ``position`` node
``PoseWithCovarianceStamped``, ``PoseStamped``,
``nav_msgs/Odometry``
``sensor_msgs/Range``                                 ``(range,)``: a range sensor
                                                      (e.g. the ``range_beacon`` plug-in)
``sensor_msgs/LaserScan``                             the ranges: ``robot_mcl`` and
                                                      ``robot_icp`` nodes (the scan's
                                                      beams must match the node's
                                                      ``beams`` and ``fov``)
====================================================  ================================

The size of ``z`` must be the one the node's sensor takes: a message of another kind
(a ``LaserScan`` fed to a ``position`` node) is refused in one line, never cut. The
noise is the node's model's (``std`` of its table); a message's own covariance is
available to a user function. Any other type, or another ``z``, is given by a **user
function** ``f(msg, t) -> z`` (array-like, or ``None`` to skip the message) per topic,
:class:`TopicInput.convert`. ``docs/ros.md`` has examples.

**Truth.** ``truth_topic``: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped`` or ``PointStamped`` (or a user function ``f(msg, t) ->
state`` giving the full state). Positions are interpolated linearly at the filter's
times; the velocity of a constant-velocity state is the odometry twist turned into the
world frame (``v (cos yaw, sin yaw)``) when the topic has one, else the central
difference of the positions. The truth must cover every filter time, from 0 to the
duration: a topic that starts later or ends earlier is refused in one line that gives
the ``origin_ns`` and ``duration`` of the part it covers. Without a truth topic the
truth is unknown (NaN): the table says so and the figures draw no truth.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dfusion.bags.convert import Converter, PoseReading, PositionFix, convert, standard_z
from dfusion.bags.reader import Bag, read_bag
from dfusion.errors import ValidationError
from dfusion.scenario.spec import Scenario
from dfusion.sim.runner import SimulationResult, run_scenario
from dfusion.sim.world import TIME_DECIMALS, Measurement, World

log = logging.getLogger(__name__)

__all__ = ["TopicInput", "world_from_bag", "replay_scenario", "parse_topic_input", "ARRIVALS"]

#: Values of ``arrival``.
ARRIVALS = ("stamp", "record")


@dataclass
class TopicInput:
    """A bag topic that feeds a node: ``convert(msg, t) -> z`` (default: the standard
    conversion of the message type, see the module docstring)."""

    topic: str
    node: str
    convert: Callable[[Any, float], Any] | None = None


def _truth_samples(bag: Bag, topic: str, origin_ns: int, fn: Converter | None):
    ts, states, vel = [], [], []
    for m in bag.on(topic):
        t = bag.seconds(m.stamp_ns, origin_ns)
        if fn is not None:
            ts.append(t)
            states.append(np.asarray(fn(m.msg, t), float))
            continue
        r = convert(m.msgtype, m.msg, t)
        if isinstance(r, PoseReading):
            ts.append(t)
            states.append(r.pose[:2])
            if r.twist is not None:
                c, s = np.cos(r.pose[2]), np.sin(r.pose[2])
                vel.append(r.twist[0] * np.array([c, s]))
        elif isinstance(r, PositionFix):
            ts.append(t)
            states.append(r.z)
        else:
            raise ValidationError(f"truth topic {topic}: {m.msgtype} gives no position")
    return np.array(ts), np.array(states), (np.array(vel) if len(vel) == len(ts) and vel else None), fn is not None


def _truth_at(times: np.ndarray, n: int, axes: int, samples) -> np.ndarray:
    ts, states, vel, full = samples
    out = np.full((times.size, n), np.nan)
    if ts.size == 0:
        return out
    inside = (times >= ts[0] - 1e-9) & (times <= ts[-1] + 1e-9)
    cols = states.shape[1] if full else min(axes, states.shape[1])
    for j in range(min(cols, n)):
        out[inside, j] = np.interp(times[inside], ts, states[:, j])
    if not full and n == 2 * axes and axes == 2:
        if vel is not None:
            for j in range(2):
                out[inside, 2 + j] = np.interp(times[inside], ts, vel[:, j])
        elif ts.size > 1:
            for j in range(2):
                out[inside, 2 + j] = np.interp(times[inside], ts, np.gradient(states[:, j], ts))
    return out


def _require_cover(ts: np.ndarray, times: np.ndarray, topic: str, origin_ns: int, duration: float) -> None:
    """Refuse a truth topic that does not cover every filter time (its RMSE would be unknown)."""
    if ts.size and ts[0] <= times[0] + 1e-9 and ts[-1] >= times[-1] - 1e-9:
        return
    if not ts.size:
        raise ValidationError(f"truth topic {topic} has no message in the run")
    a, b = float(ts[0]), float(ts[-1])
    start = max(a, 0.0)
    raise ValidationError(
        f"truth topic {topic} covers {a:.3f}-{b:.3f} s of the run's {times[0]:.3f}-{times[-1]:.3f} s, so RMSE and "
        f"ANEES would be unknown: replay the covered part (--origin-ns {origin_ns + int(round(start * 1e9))} "
        f"--duration {max(min(b, duration) - start, 0.0):.3f}) or give no --truth")


def world_from_bag(
    sc: Scenario,
    bag: str | Path | Bag,
    inputs: Sequence[TopicInput],
    *,
    truth_topic: str | None = None,
    truth_convert: Converter | None = None,
    arrival: str = "stamp",
    origin_ns: int | None = None,
) -> World:
    """The world of ``sc`` read from ``bag`` (see the module docstring).

    Measurements outside ``(0, sc.duration]`` are left out (logged). A message whose
    ``z`` does not have the size the node's sensor takes (a ``LaserScan`` fed to a
    ``position`` node) is refused, as is a truth topic that does not cover every filter
    time (the error gives the ``--origin-ns`` and ``--duration`` of the part it covers).
    """
    if arrival not in ARRIVALS:
        raise ValidationError(f"arrival must be one of {ARRIVALS}, got {arrival!r}")
    for inp in inputs:
        if inp.node not in sc.nodes:
            raise ValidationError(f"topic {inp.topic}: node {inp.node!r} is not in the scenario "
                                  f"(nodes: {sorted(sc.nodes)})")
        if sc.nodes[inp.node].sensor is None:
            raise ValidationError(f"topic {inp.topic}: node {inp.node!r} has no sensor")
    topics = [i.topic for i in inputs] + ([truth_topic] if truth_topic else [])
    if not isinstance(bag, Bag):
        bag = read_bag(bag, topics)
    by_topic = {i.topic: i for i in inputs}
    if origin_ns is None:
        origin_ns = min((m.stamp_ns for m in bag.messages if m.topic in topics), default=bag.origin_ns)
    meas: list[Measurement] = []
    skipped = 0
    for m in bag.messages:
        inp = by_topic.get(m.topic)
        if inp is None:
            continue
        t = round(bag.seconds(m.stamp_ns, origin_ns), TIME_DECIMALS)
        if not 0.0 < t <= sc.duration + 1e-9:
            skipped += 1
            continue
        z = inp.convert(m.msg, t) if inp.convert is not None else standard_z(convert(m.msgtype, m.msg, t))[0]
        if z is None:
            skipped += 1
            continue
        z = np.atleast_1d(np.asarray(z, dtype=float)).ravel()
        node = sc.nodes[inp.node]
        dim = getattr(node.sensor, "dim_z", None)
        if dim is not None and z.size != dim:
            what = "its converter gives" if inp.convert is not None else f"a {m.msgtype} gives"
            raise ValidationError(f"topic {m.topic}: {what} {z.size} numbers, but node {inp.node!r} "
                                  f"({node.sensor_kind}) takes {dim}: map the topic to a node of a fitting kind "
                                  f"or with a function msg, t -> z")
        rec = round(bag.seconds(m.record_ns, origin_ns), TIME_DECIMALS) if arrival == "record" else t
        meas.append(Measurement(t, inp.node, z, max(t, rec)))
    if skipped:
        log.info("%s: %d messages outside (0, %g] s or skipped by their converter", bag.path, skipped, sc.duration)
    meas.sort(key=lambda x: (x.t, x.node))
    grid = np.round(sc.dt * np.arange(sc.steps + 1), TIME_DECIMALS)
    times = np.unique(np.concatenate([grid, np.array([x.t for x in meas], dtype=float)]))
    n = sc.target.motion.dim
    if truth_topic:
        samples = _truth_samples(bag, truth_topic, origin_ns, truth_convert)
        _require_cover(samples[0], times, truth_topic, origin_ns, sc.duration)
        states = _truth_at(times, n, sc.target.axes, samples)
    else:
        states = np.full((times.size, n), np.nan)
    return World(times, states, meas, int(origin_ns))


def replay_scenario(sc: Scenario, bag: str | Path | Bag, inputs: Sequence[TopicInput], *,
                    truth_topic: str | None = None, truth_convert: Converter | None = None,
                    arrival: str = "stamp", origin_ns: int | None = None,
                    progress: bool = False) -> SimulationResult:
    """Run ``sc`` on the world of ``bag`` (:func:`world_from_bag`, then
    :func:`~dfusion.sim.runner.run_scenario`)."""
    world = world_from_bag(sc, bag, inputs, truth_topic=truth_topic, truth_convert=truth_convert,
                           arrival=arrival, origin_ns=origin_ns)
    return run_scenario(sc, progress=progress, world=world)


def parse_topic_input(text: str) -> TopicInput:
    """``TOPIC=NODE`` or ``TOPIC=NODE:FILE.py:FUNCTION`` (a user converter ``f(msg, t) -> z``
    loaded from a Python file) -> :class:`TopicInput`."""
    topic, sep, rest = text.partition("=")
    if not sep or not topic or not rest:
        raise ValidationError(f"--topic wants TOPIC=NODE or TOPIC=NODE:FILE.py:FUNCTION, got {text!r}")
    node, fn = split_converter(rest, f"--topic {text!r}")
    return TopicInput(topic, node, fn)


def split_converter(text: str, where: str) -> tuple[str, Callable | None]:
    """``NAME`` or ``NAME:FILE.py:FUNCTION`` -> ``(NAME, the function or None)`` (:func:`load_function`)."""
    name, _, func = text.partition(":")
    if not func:
        return name, None
    path, sep, fname = func.rpartition(":")
    if not sep or not path or not fname:
        raise ValidationError(f"{where}: the converter is FILE.py:FUNCTION")
    return name, load_function(path, fname)


def load_function(path: str, name: str) -> Callable:
    """Function ``name`` of the Python file ``path`` (a user converter)."""
    import importlib.util

    p = Path(path)
    if not p.is_file():
        raise ValidationError(f"converter file {path} does not exist")
    spec = importlib.util.spec_from_file_location(f"dfusion_user_{p.stem}", p)
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
    except Exception as exc:   # the user's file: a syntax error, a failing import, ...
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise ValidationError(f"converter file {path} does not load: {type(exc).__name__}: {first}") from None
    fn = getattr(mod, name, None)
    if not callable(fn):
        raise ValidationError(f"{path} has no function {name!r}")
    return fn
