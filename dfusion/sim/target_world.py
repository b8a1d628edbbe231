r"""The world of a multi-target scenario: people and robots on their paths, and what the nodes sense.

**Truth.** Each ``[[targets]]`` entry (:class:`~dfusion.scenario.spec.TargetPath`) exists from
``appear`` to ``leave`` and is at ``path.position(t)`` meanwhile (straight segments at its
speed, waiting at the last waypoint if it leaves later than it arrives).

**Frames.** A node with a sensor measures at ``phase + j / rate`` (``j = 0, 1, ...`` up to
the duration) while it is active:

* ``sensor = "detections"``: every target inside the node's ``view`` (an axis-aligned
  rectangle, :class:`~dfusion.sim.plaza.CameraView`) is detected with probability
  ``detection`` at its position plus ``N(0, std^2 I)``; false detections are Poisson with
  mean ``clutter`` per frame, uniform in the view, so the clutter density of the scan is
  ``clutter / area(view)`` per m^2 (at least :data:`MIN_CLUTTER_DENSITY`). The detections of a frame come in random order, as one
  :class:`~dfusion.tracking.Scan` whose view probability is the view's
  (:meth:`CameraView.probability_inside`).
* ``sensor = "tags"``: every target of the node's ``targets`` that exists (and is inside
  ``view``, when the node has one) is read with probability ``detection`` at its position
  plus ``N(0, std^2 I)``, with its identity (:class:`TagReading`).

Every node draws from its own generator (spawned from the scenario's seed in node-name
order), so a node's frames do not change when another node's settings do.

**A recorded world** (:func:`world_from_bag`, ``dfusion replay SCENARIO BAG --topic TOPIC=NODE``):
the frames of the scenario's camera nodes are a bag's detection arrays instead
(:func:`dfusion.sim.bag_scans.scans_from_bag`, one scan per message, the node's ``std``,
``detection``, clutter density and ``view``), and the truth is the bag's truth topics
(:func:`dfusion.sim.track_replay.truth_tracks`; none: no truth, the metrics are unknown).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dfusion.bags.detections import DetectionTopic
from dfusion.bags.reader import Bag
from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.scenario.spec import NodeSpec, Scenario
from dfusion.scenario.tracking_kinds import view_of
from dfusion.sim.bag_scans import ScanCounts, scans_from_bag
from dfusion.sim.plaza import CameraView
from dfusion.tracking.history import TruthPaths
from dfusion.tracking.track import Scan

__all__ = ["TagReading", "NodeFrame", "TargetWorld", "simulate_targets", "node_view", "MIN_CLUTTER_DENSITY",
           "detection_topic", "world_from_bag"]

#: Clutter density (per m^2) a scan states at least: a camera without false detections still
#: gives the association a finite miss weight ``lambda (1 - P_D P_G)``.
MIN_CLUTTER_DENSITY = 1e-6


@dataclass(frozen=True)
class TagReading:
    """One reading of an identified target: its name and the measured position."""

    target: str
    z: Array


@dataclass
class NodeFrame:
    """What one node sensed at one time: a scan of anonymous detections (``scan``; ``source[i]``
    the target detection ``i`` came from, ``""`` for a false one) or tag readings."""

    t: float
    node: str
    scan: Scan | None = None
    source: tuple[str, ...] = ()
    readings: list[TagReading] = field(default_factory=list)


@dataclass
class TargetWorld:
    """A multi-target scenario's world: frames in time order (then node order), the truth at
    the step times, and counts."""

    times: Array
    frames: list[NodeFrame]
    truth: TruthPaths
    detections: int = 0
    false_detections: int = 0
    readings: int = 0
    #: A recorded world: what was read from the bag (None for a simulated one).
    counts: ScanCounts | None = None


def node_view(spec: NodeSpec) -> CameraView | None:
    """The rectangle a node sees (``view``), or None."""
    v = view_of(spec.params, required=False)
    return None if v is None else CameraView(spec.name, *v)


def _frame_times(spec: NodeSpec, duration: float) -> Array:
    if spec.sensor is None or spec.rate <= 0:
        return np.zeros(0)
    n = int(np.floor((duration - spec.phase) * spec.rate + 1e-9)) + 1
    ts = np.round(spec.phase + np.arange(max(n, 0)) / spec.rate, 9)
    return np.array([t for t in ts if spec.is_active(float(t))])


def simulate_targets(sc: Scenario) -> TargetWorld:
    """Sample the world of multi-target scenario ``sc`` (deterministic by ``sc.seed``; module docstring)."""
    times = np.round(sc.dt * np.arange(sc.steps + 1), 9)
    paths = {}
    for target in sc.targets:
        ts = np.array([t for t in times if target.present(float(t))])
        if ts.size:
            paths[target.name] = (ts, np.array([target.position(float(t)) for t in ts]))
    world = TargetWorld(times, [], TruthPaths(paths))
    names = sorted(sc.nodes)
    rngs = dict(zip(names, (np.random.default_rng(s) for s in np.random.SeedSequence(sc.seed).spawn(len(names)))))
    for name in names:
        spec = sc.nodes[name]
        rng = rngs[name]
        view = node_view(spec)
        std = float(spec.params.get("std", 0.3 if spec.sensor_kind == "detections" else 1.0))
        for t in _frame_times(spec, sc.duration):
            t = float(t)
            if spec.sensor_kind == "detections":
                world.frames.append(_camera_frame(sc, spec, view, std, t, rng, world))
            elif spec.sensor_kind == "tags":
                tagged = set(spec.params["targets"])
                frame = NodeFrame(t, name)
                for target in sc.targets:
                    if target.name in tagged and target.present(t):
                        p = target.position(t)
                        if (view is None or view.contains(p)) and rng.uniform() < spec.detection:
                            frame.readings.append(TagReading(target.name, p + std * rng.standard_normal(2)))
                world.readings += len(frame.readings)
                world.frames.append(frame)
    world.frames.sort(key=lambda f: (f.t, f.node))
    return world


def _camera_frame(sc: Scenario, spec: NodeSpec, view: CameraView, std: float, t: float, rng: np.random.Generator,
                  world: TargetWorld) -> NodeFrame:
    zs, who = [], []
    for target in sc.targets:
        if target.present(t):
            p = target.position(t)
            if view.contains(p) and rng.uniform() < spec.detection:
                zs.append(p + std * rng.standard_normal(2))
                who.append(target.name)
    clutter = float(spec.params.get("clutter", 0.0))
    k = int(rng.poisson(clutter)) if clutter > 0 else 0
    for _ in range(k):
        zs.append(np.array([rng.uniform(view.x0, view.x1), rng.uniform(view.y0, view.y1)]))
        who.append("")
    order = rng.permutation(len(zs))
    z = np.array(zs, dtype=float).reshape(-1, 2)[order]
    world.detections += len(zs) - k
    world.false_detections += k
    scan = Scan(t, z, spec.sensor, max(clutter / view.area, MIN_CLUTTER_DENSITY), spec.detection, None, spec.name, view.probability_inside)
    return NodeFrame(t, spec.name, scan, tuple(who[i] for i in order))


def detection_topic(sc: Scenario, topic: str, node: str, convert: Callable[[Any, float], Any] | None = None
                    ) -> DetectionTopic:
    """The :class:`~dfusion.bags.detections.DetectionTopic` of a bag topic feeding camera node
    ``node`` of multi-target scenario ``sc``: the node's ``std``, ``detection``, clutter density
    and ``view``."""
    spec = sc.nodes.get(node)
    if spec is None or spec.sensor_kind != "detections":
        cams = sorted(n for n, s in sc.nodes.items() if s.sensor_kind == "detections")
        raise ValidationError(f"--topic {topic}={node}: {node!r} is not a camera node (sensor = \"detections\") of "
                              f"{sc.path}; those are {', '.join(cams) or 'none'}")
    view = node_view(spec)
    assert view is not None
    density = max(float(spec.params.get("clutter", 0.0)) / view.area, MIN_CLUTTER_DENSITY)
    return DetectionTopic(topic, node, convert, std=float(spec.params.get("std", 0.3)),
                          detection_probability=max(spec.detection, 1e-9), clutter_density=density,
                          view=(view.x0, view.x1, view.y0, view.y1))


def world_from_bag(sc: Scenario, bag: str | Path | Bag, topics: Sequence[tuple[str, str, Callable | None]], *,
                   truth_topics: Sequence[str] = (), frame: str = "map", origin_ns: int | None = None,
                   msgdefs=None) -> TargetWorld:
    """The world of multi-target scenario ``sc`` read from a bag (module docstring): ``topics`` are
    ``(topic, camera node, converter or None)``; times are seconds after ``origin_ns`` (default: the
    earliest stamp of the topics), up to the scenario's duration."""
    from dfusion.sim.track_replay import open_detection_bag, truth_tracks

    dtopics = [detection_topic(sc, t, n, f) for t, n, f in topics]
    if not dtopics:
        raise ValidationError("a replay of a multi-target scenario needs at least one --topic TOPIC=CAMERA_NODE")
    bag, origin_ns = open_detection_bag(bag, dtopics, truth_topics, origin_ns, msgdefs=msgdefs)
    truth = truth_tracks(bag, truth_topics, frame, origin_ns) if truth_topics else {}
    times = np.round(sc.dt * np.arange(sc.steps + 1), 9)
    world = TargetWorld(times, [], TruthPaths(truth), counts=ScanCounts())
    for node, scan in scans_from_bag(bag, dtopics, frame=frame, origin_ns=origin_ns, duration=sc.duration,
                                     counts=world.counts):
        world.frames.append(NodeFrame(float(scan.time), node, scan))
        world.detections += len(scan.detections)
    world.frames.sort(key=lambda f: (f.t, f.node))
    return world
