r"""A run as an MCAP recording for Foxglove (``dfusion simulate --mcap``, ``docs/ros.md``).

The file is written with the ``mcap`` library (the format's reference implementation).
Foxglove's types (``foxglove.PoseInFrame``, ``foxglove.SceneUpdate``) are Foxglove's
official schemas: protobuf-encoded with the descriptors Foxglove publishes
(``foxglove-schemas-protobuf``), so opening the file in Foxglove shows the run in the 3D
panel (frame ``map``, metres) without any set-up. ``/diagnostics`` is ROS 2's
``diagnostic_msgs/msg/DiagnosticArray`` (CDR, its definition from rosbags' type store),
what ROS users' diagnostics tools read. Numbers to plot (covariances, NEES, gaps) travel
in small ``dfusion/*`` JSON messages (JSON Schema) that Foxglove's Plot and Raw Message
panels read by field path.

Topics (one message per filter step unless said otherwise; time = scenario time plus
``start_ns``: a replay passes the bag's stamp of its time 0, so the recording lies on
the source bag's time line and overlays it):

=================================  ====================  ===================================
topic                              schema                what
=================================  ====================  ===================================
``/truth``                         foxglove.PoseInFrame  the true position (heading: the
                                                         direction of motion)
``/nodes/<name>/pose``             foxglove.PoseInFrame  the node's estimate
``/nodes/<name>/estimate``         dfusion/Estimate      mean, covariance (row-major),
                                                         standard deviations, NEES, gaps to
                                                         the centralized EKF (m, m/s)
``/centralized/pose``,             as above              the centralized EKF
``/centralized/estimate``
``/scene/estimates``               foxglove.SceneUpdate  every node's 3-sigma ellipse and
                                                         label, the truth as a sphere
``/scene/sensors``                 foxglove.SceneUpdate  at t = 0: camera footprints,
                                                         receivers, beacons, the true path
``/scene/tree``                    foxglove.SceneUpdate  the tree's links between the nodes'
                                                         anchors (green up, red down), at 0
                                                         and at each change
``/tree``                          dfusion/Tree          nodes and links with their state,
                                                         at 0 and at each change
``/detections``                    foxglove.SceneUpdate  each measurement that gives a point
                                                         on the ground, for 1 s (green used,
                                                         red gated, refused or lost; blue in
                                                         a multi-process run: delivered to
                                                         its node, which judged it there)
``/diagnostics``                   diagnostic_msgs/      gates, refused measurements, link
                                   DiagnosticArray       outages beginning and ending (one
                                                         status: WARN, or OK when a link
                                                         comes back)
=================================  ====================  ===================================

**Many targets** (:func:`record_tracks_mcap`, from a :class:`~dfusion.tracking.TrackHistory`
and the truth's :class:`~dfusion.tracking.TruthPaths`): one message per node per recorded
time on each of

=================================  ====================  ===================================
topic                              schema                what
=================================  ====================  ===================================
``/nodes/<name>/tracks``           foxglove.SceneUpdate  one entity per track, id
                                                         ``track/<node>/<identity>``: a
                                                         sphere at the estimate, the 3-sigma
                                                         ellipse and the identity as text, in
                                                         the identity's colour
                                                         (:func:`dfusion.viz.tracks.identity_color`);
                                                         a track gone since the node's last
                                                         message is deleted by id
``/nodes/<name>/track_estimates``  dfusion/Tracks        every track's identity (text, origin,
                                                         serial), mean, covariance (row-major)
                                                         and standard deviations
``/truth/targets``                 foxglove.SceneUpdate  each target present (grey sphere,
                                                         name), at every recorded time
``/scene/static``                  foxglove.SceneUpdate  at 0: every true path (grey) and the
                                                         camera views
=================================  ====================  ===================================

The 3D panel draws the SceneUpdates as they are (every track of every node, in its
identity's colour, with the truth); toggling a node's ``/nodes/<name>/tracks`` topic shows
one node's view. The Plot and Raw Message panels read the numbers of
``/nodes/<name>/track_estimates`` by field path (e.g. ``.tracks[0].std[0]``).

A node's *anchor* (where the tree draws it) is its camera's position, its receivers'
centroid, its beacon; nodes without a place are put in a row above the scene.
"""
from __future__ import annotations

import functools
import importlib
import json
import math
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from dfusion.viz.topdown import camera_footprint, detection_point, ellipse_points, sensor_points

__all__ = ["SCHEMAS", "DIAGNOSTICS", "FOXGLOVE_TYPES", "record_mcap", "messages_of_result", "LiveView",
           "channel_schema", "encode", "record_tracks_mcap", "messages_of_tracks", "write_mcap"]

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
_NUM_OR_NULL = {"type": ["number", "null"]}   # null: unknown (no truth, no centralized estimate)


def _finite(x: float) -> float | None:
    """``x``, or None (JSON null) when it is not finite: JSON has no NaN."""
    return float(x) if math.isfinite(x) else None


def _obj(props: dict[str, Any], title: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object", "properties": props}
    if title:
        out["title"] = title
    return out


_TIME = _obj({"sec": _INT, "nsec": _INT})


def _arr(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


#: Foxglove's types used, written with Foxglove's published protobuf descriptors
#: (foxglove-schemas-protobuf; https://docs.foxglove.dev/docs/sdk/schemas).
FOXGLOVE_TYPES = ("foxglove.PoseInFrame", "foxglove.SceneUpdate")

#: ROS 2's diagnostics message (CDR): ``/diagnostics``.
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"

#: dfusion's own numeric messages (JSON Schema).
SCHEMAS: dict[str, dict[str, Any]] = {
    "dfusion/Estimate": _obj({"timestamp": _TIME, "t": _NUM, "node": _STR, "state": _arr(_STR), "mean": _arr(_NUM),
                              "covariance": _arr(_NUM), "std": _arr(_NUM), "nees": _NUM_OR_NULL,
                              "gap_position_m": _NUM_OR_NULL, "gap_velocity_mps": _NUM_OR_NULL}, "dfusion/Estimate"),
    "dfusion/Tree": _obj({"timestamp": _TIME, "nodes": _arr(_STR),
                          "links": _arr(_obj({"a": _STR, "b": _STR, "up": _BOOL}))}, "dfusion/Tree"),
    "dfusion/Tracks": _obj({"timestamp": _TIME, "t": _NUM, "node": _STR,
                            "tracks": _arr(_obj({"id": _STR, "origin": {"type": ["string", "null"]},
                                                 "serial": {"type": ["integer", "null"]}, "mean": _arr(_NUM),
                                                 "covariance": _arr(_NUM), "std": _arr(_NUM)}))}, "dfusion/Tracks"),
}


@functools.cache
def _proto_class(name: str):
    short = name.split(".", 1)[1]
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2"), short)


@functools.cache
def _ros2_types():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _descriptor_set(cls) -> bytes:
    """The ``FileDescriptorSet`` of a protobuf type with its dependencies (the schema data
    of an MCAP protobuf channel)."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds, seen = FileDescriptorSet(), set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()


@functools.cache
def channel_schema(name: str) -> tuple[str, str, bytes]:
    """``(schema encoding, message encoding, schema data)`` of a schema name."""
    if name in FOXGLOVE_TYPES:
        return "protobuf", "protobuf", _descriptor_set(_proto_class(name))
    if name == DIAGNOSTICS:
        return "ros2msg", "cdr", _ros2_types().generate_msgdef(name, ros_version=2)[0].encode()
    return "jsonschema", "json", json.dumps(SCHEMAS[name]).encode()


def _protobuf_json(value: Any, key: str | None = None) -> Any:
    """A message in Foxglove's JSON form -> protobuf's JSON mapping (a ``{sec, nsec}`` time
    as an RFC 3339 string, a ``lifetime`` as a ``"S.NNNNNNNNNs"`` duration)."""
    if isinstance(value, dict):
        if set(value) == {"sec", "nsec"}:
            if key == "lifetime":
                return f"{value['sec']}.{value['nsec']:09d}s"
            from google.protobuf.timestamp_pb2 import Timestamp

            ts = Timestamp()
            ts.FromNanoseconds(int(value["sec"]) * 1_000_000_000 + int(value["nsec"]))
            return ts.ToJsonString()
        return {k: _protobuf_json(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_protobuf_json(v, key) for v in value]
    return value


def _diagnostics_cdr(msg: dict[str, Any]) -> bytes:
    ts = _ros2_types()
    T = ts.types
    h = msg["header"]
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=h["stamp"]["sec"],
                                                                             nanosec=h["stamp"]["nanosec"]),
                                      frame_id=h["frame_id"])
    status = [T["diagnostic_msgs/msg/DiagnosticStatus"](
        level=int(st["level"]), name=st["name"], message=st["message"], hardware_id=st["hardware_id"],
        values=[T["diagnostic_msgs/msg/KeyValue"](key=kv["key"], value=kv["value"]) for kv in st["values"]])
        for st in msg["status"]]
    return bytes(ts.serialize_cdr(T[DIAGNOSTICS](header=header, status=status), DIAGNOSTICS))


def encode(name: str, msg: dict[str, Any]) -> bytes:
    """A message (a dict in its type's field names) in its channel's encoding
    (:func:`channel_schema`): protobuf for Foxglove's types, CDR for ``/diagnostics``,
    JSON for dfusion's own."""
    if name in FOXGLOVE_TYPES:
        from google.protobuf import json_format

        return json_format.ParseDict(_protobuf_json(msg), _proto_class(name)(),
                                     ignore_unknown_fields=False).SerializeToString()
    if name == DIAGNOSTICS:
        return _diagnostics_cdr(msg)
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


_DIAG_OK, _DIAG_WARN = 0, 1   # diagnostic_msgs/DiagnosticStatus levels
_LINE_STRIP, _LINE_LOOP, _LINE_LIST = 0, 1, 2
_PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76),
            (0.09, 0.75, 0.81), (0.74, 0.74, 0.13), (0.84, 0.15, 0.16), (0.5, 0.5, 0.5), (0.0, 0.0, 0.5)]


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": int(ns // 1_000_000_000), "nsec": int(ns % 1_000_000_000)}


def _color(rgb: tuple[float, float, float], a: float = 1.0) -> dict[str, float]:
    return {"r": float(rgb[0]), "g": float(rgb[1]), "b": float(rgb[2]), "a": float(a)}


def _pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> dict[str, Any]:
    return {"position": {"x": float(x), "y": float(y), "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)}}


def _p3(xy: Iterable[float], z: float = 0.0) -> dict[str, float]:
    x, y = list(xy)[:2]
    return {"x": float(x), "y": float(y), "z": float(z)}


def _entity(ns: int, eid: str, *, lifetime_ns: int = 0, lines=(), spheres=(), cubes=(), texts=(), triangles=(),
            metadata: dict[str, str] | None = None) -> dict[str, Any]:
    return {"timestamp": _stamp(ns), "frame_id": "map", "id": eid, "lifetime": _stamp(lifetime_ns),
            "frame_locked": False, "metadata": [{"key": k, "value": v} for k, v in (metadata or {}).items()],
            "arrows": [], "cubes": list(cubes), "spheres": list(spheres), "cylinders": [], "lines": list(lines),
            "triangles": list(triangles), "texts": list(texts), "models": []}


def _line(points, rgb, *, kind: int = _LINE_STRIP, thickness: float = 2.0, a: float = 1.0) -> dict[str, Any]:
    return {"type": kind, "pose": _pose(), "thickness": thickness, "scale_invariant": True,
            "points": [_p3(p) for p in points], "color": _color(rgb, a), "colors": [], "indices": []}


def _sphere(xy, rgb, size: float = 0.3, a: float = 1.0) -> dict[str, Any]:
    return {"pose": _pose(*list(xy)[:2]), "size": {"x": size, "y": size, "z": size}, "color": _color(rgb, a)}


def _text(xy, text: str, rgb=(0.1, 0.1, 0.1), size: float = 14.0) -> dict[str, Any]:
    x, y = list(xy)[:2]
    p = _pose(x, y)
    p["position"]["z"] = 0.4
    return {"pose": p, "billboard": True, "font_size": size, "scale_invariant": True, "color": _color(rgb),
            "text": text}


def _anchors(sc, names: list[str], truth: np.ndarray) -> dict[str, np.ndarray]:
    """Where the tree draws each node (module docstring)."""
    out: dict[str, np.ndarray] = {}
    for n in names:
        sensor = sc.nodes[n].sensor
        pts = sensor_points(sensor) if sensor is not None else None
        if pts is not None:
            out[n] = pts.mean(axis=0)
    truth = np.asarray(truth, float).reshape(-1, 2) if np.size(truth) else np.zeros((0, 2))
    finite = truth[np.all(np.isfinite(truth), axis=1)]
    ref = np.vstack([finite, *out.values()]) if (finite.size or out) else np.zeros((1, 2))
    lo, hi = ref.min(axis=0), ref.max(axis=0)
    rest = [n for n in names if n not in out]
    for i, n in enumerate(rest):
        out[n] = np.array([lo[0] + (i + 1) / (len(rest) + 1) * (hi[0] - lo[0] or 1.0), hi[1] + 0.1 * (hi[1] - lo[1]) + 2.0])
    return out


Message = tuple[str, str, int, dict[str, Any]]


class _Builder:
    """The messages of one scenario, step by step (shared by the recording and the live view)."""

    def __init__(self, sc, names: list[str], start_ns: int = 0, truth_path: np.ndarray | None = None) -> None:
        from dfusion.sim.runner import state_parts

        self.sc, self.names, self.start_ns = sc, names, start_ns
        self.colors = {n: _PALETTE[i % len(_PALETTE)] for i, n in enumerate(names)}
        motion = sc.target.motion
        self.pos, self.vel = state_parts(motion.dim, sc.target.axes)
        self.resid = motion.residual if motion.angle_indices else None
        letters = "xyz"
        state = [f"{letters[i]} [m]" for i in self.pos] + [f"v{letters[i - len(self.pos)]} [m/s]" for i in self.vel]
        self.state = state + [f"x{i}" for i in range(len(state), motion.dim)]
        self.truth_path = np.zeros((0, 2)) if truth_path is None else np.asarray(truth_path, float)[:, :2]
        self.anchors = _anchors(sc, names, self.truth_path)

    def ns(self, t: float) -> int:
        return self.start_ns + int(round(float(t) * 1e9))

    @staticmethod
    def heading(x: np.ndarray) -> float:
        return math.atan2(x[3], x[2]) if len(x) >= 4 and np.all(np.isfinite(x[2:4])) else 0.0

    def step(self, t: float, estimates: dict[str, tuple[np.ndarray, np.ndarray]], truth: np.ndarray,
             central_mean: np.ndarray) -> list[Message]:
        """Poses, estimates and ellipses at ``t``; ``estimates`` includes ``"centralized"``."""
        from dfusion.metrics import nees

        ns = self.ns(t)
        stamp = _stamp(ns)
        out: list[Message] = []
        truth = np.asarray(truth, float)
        known = bool(np.all(np.isfinite(truth[:2])))
        if known:
            out.append(("/truth", "foxglove.PoseInFrame", ns,
                        {"timestamp": stamp, "frame_id": "map", "pose": _pose(truth[0], truth[1], self.heading(truth))}))
        ents = []
        for n, (mk, Pk) in estimates.items():
            mk, Pk = np.asarray(mk, float), np.asarray(Pk, float)
            if not (np.all(np.isfinite(mk)) and np.all(np.isfinite(Pk))):
                continue   # a step a node did not report (dfusion run): nothing to draw
            topic = "/centralized" if n == "centralized" else f"/nodes/{n}"
            out.append((f"{topic}/pose", "foxglove.PoseInFrame", ns,
                        {"timestamp": stamp, "frame_id": "map", "pose": _pose(mk[0], mk[1], self.heading(mk))}))
            d = mk - np.asarray(central_mean, float)
            e = float(nees(mk[None], Pk[None], truth[None], self.resid)[0]) if np.all(np.isfinite(truth)) else math.nan
            est = {"timestamp": stamp, "t": float(t), "node": n, "state": self.state, "mean": mk.tolist(),
                   "covariance": Pk.ravel().tolist(), "std": np.sqrt(np.maximum(np.diag(Pk), 0.0)).tolist(),
                   "nees": _finite(e), "gap_position_m": _finite(np.linalg.norm(d[self.pos])),
                   "gap_velocity_mps": _finite(np.linalg.norm(d[self.vel])) if self.vel else None}
            out.append((f"{topic}/estimate", "dfusion/Estimate", ns, est))
            rgb = (0.0, 0.0, 0.0) if n == "centralized" else self.colors[n]
            ell = ellipse_points(mk[:2], Pk[:2, :2], 3.0, 48)
            ents.append(_entity(ns, f"ellipse/{n}", lines=[_line(ell, rgb, kind=_LINE_STRIP, thickness=2.0)],
                                spheres=[_sphere(mk[:2], rgb, 0.15)],
                                texts=[_text(mk[:2] + np.array([0.3, 0.3]), n, rgb, 12.0)],
                                metadata={"node": n, "meaning": "estimate and its 3-sigma ellipse"}))
        if known:
            ents.append(_entity(ns, "truth", spheres=[_sphere(truth[:2], (0.17, 0.63, 0.17), 0.35)],
                                metadata={"meaning": "true position"}))
        out.append(("/scene/estimates", "foxglove.SceneUpdate", ns, {"deletions": [], "entities": ents}))
        return out

    def sensors(self) -> list[Message]:
        """The static scene at time 0: footprints, receivers, beacons, the true path."""
        ns = self.start_ns
        ents = []
        for n in self.names:
            sensor = self.sc.nodes[n].sensor
            if sensor is None:
                continue
            fp = camera_footprint(sensor)
            if fp is not None:
                ents.append(_entity(ns, f"footprint/{n}", lines=[_line(fp, self.colors[n], kind=_LINE_LOOP,
                                                                        thickness=1.5)],
                                    texts=[_text(fp.mean(axis=0), f"{n} view", self.colors[n], 12.0)],
                                    metadata={"node": n, "meaning": "the ground the camera sees"}))
            pts = sensor_points(sensor)
            if pts is not None:
                ents.append(_entity(ns, f"sensor/{n}", spheres=[_sphere(p, self.colors[n], 0.4) for p in pts],
                                    metadata={"node": n, "meaning": "sensor positions (camera, receivers, beacon)"}))
        finite = self.truth_path[np.all(np.isfinite(self.truth_path), axis=1)]
        if len(finite) > 1:
            ents.append(_entity(ns, "truth/path", lines=[_line(finite, (0.17, 0.63, 0.17), thickness=1.0, a=0.5)],
                                metadata={"meaning": "the whole true path"}))
        return [("/scene/sensors", "foxglove.SceneUpdate", ns, {"deletions": [], "entities": ents})]

    def tree(self, t_end: float) -> list[Message]:
        """The tree at 0 and at every change of a link's state (outages), with logs."""
        sc = self.sc
        edges = sorted(tuple(sorted(e)) for e in sc.graph.edges)
        outages = list(sc.outages())
        out: list[Message] = []
        for tc in sorted({0.0, *(o[2] for o in outages), *(o[3] for o in outages)}):
            if tc > t_end + 1e-9:
                continue
            lns = self.ns(tc)
            up = {e: not any(set(e) == {a, b} and t0 <= tc + 1e-9 < t1 for a, b, t0, t1 in outages) for e in edges}
            out.append(("/tree", "dfusion/Tree", lns, {"timestamp": _stamp(lns), "nodes": self.names,
                                                         "links": [{"a": a, "b": b, "up": up[(a, b)]} for a, b in edges]}))
            ents = [_entity(lns, f"link/{a}-{b}",
                            lines=[_line([self.anchors[a], self.anchors[b]],
                                         (0.2, 0.6, 0.2) if up[(a, b)] else (0.85, 0.1, 0.1),
                                         kind=_LINE_LIST, thickness=3.0 if up[(a, b)] else 2.0)],
                            metadata={"link": f"{a} - {b}", "state": "up" if up[(a, b)] else "down"})
                    for a, b in edges]
            ents += [_entity(lns, f"node/{n}", spheres=[_sphere(self.anchors[n], self.colors[n], 0.6)],
                             texts=[_text(self.anchors[n] + np.array([0.0, 0.6]), n, self.colors[n], 14.0)],
                             metadata={"node": n}) for n in self.names]
            out.append(("/scene/tree", "foxglove.SceneUpdate", lns, {"deletions": [], "entities": ents}))
            if tc > 0:
                for a, b, t0, t1 in outages:
                    if abs(t0 - tc) < 1e-9 or abs(t1 - tc) < 1e-9:
                        what = "down" if abs(t0 - tc) < 1e-9 else "up again"
                        out.append(_diagnostic(lns, _DIAG_WARN if what == "down" else _DIAG_OK, f"link {a} - {b}",
                                               f"link {a} - {b} {what} (outage {t0:g}-{t1:g} s)",
                                               {"link": f"{a} - {b}", "state": "down" if what == "down" else "up",
                                                "outage_s": f"{t0:g}-{t1:g}"}))
        return out

    def event(self, i: int, ev: dict[str, Any]) -> list[Message]:
        """A processed measurement: its point on the ground, and a log line when not used."""
        n = ev["node"]
        lns = self.ns(ev["t"])
        outcome = list(ev["outcome"])
        sensor = self.sc.nodes[n].sensor if n in self.sc.nodes else None
        p = detection_point(sensor, ev["z"]) if sensor is not None else None
        used = "contributed" in outcome
        # a multi-process run knows only that the measurement reached its node's process
        # (the node's front end judged it there): drawn in blue, no log line
        delivered = outcome == ["delivered"]
        out: list[Message] = []
        if p is not None:
            rgb = (0.1, 0.7, 0.1) if used else (0.2, 0.4, 0.9) if delivered else (0.85, 0.1, 0.1)
            out.append(("/detections", "foxglove.SceneUpdate", lns,
                        {"deletions": [], "entities": [_entity(lns, f"det/{n}/{i}", lifetime_ns=1_000_000_000,
                                                               spheres=[_sphere(p, rgb, 0.25, 0.8)],
                                                               metadata={"node": n, "outcome": ",".join(outcome)})]}))
        if not used and not delivered:
            why = ", ".join(outcome) or "no information"
            out.append(_diagnostic(lns, _DIAG_WARN, n,
                                   f"{n}: measurement of t={float(ev['t_meas']):.3f} s not used ({why})",
                                   {"t_measurement_s": f"{float(ev['t_meas']):.9f}", "outcome": why}))
        return out


def _diagnostic(ns: int, level: int, name: str, message: str, values: dict[str, str]) -> Message:
    """A ``/diagnostics`` message: one ``DiagnosticStatus`` (``name`` under ``dfusion/``, the
    node or link as its ``hardware_id``)."""
    return ("/diagnostics", DIAGNOSTICS, ns,
            {"header": {"stamp": {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)},
                        "frame_id": "map"},
             "status": [{"level": level, "name": f"dfusion/{name}", "message": message, "hardware_id": name,
                         "values": [{"key": k, "value": v} for k, v in values.items()]}]})


def messages_of_result(result, *, start_ns: int = 0) -> list[Message]:
    """Every message of the recording: ``(topic, schema, log_time_ns, message)``, sorted by time."""
    names = sorted(result.node_mean)
    b = _Builder(result.scenario, names, start_ns, result.truth[:, :2])
    out: list[Message] = []
    for k, tk in enumerate(result.times):
        est = {n: (result.node_mean[n][k], result.node_cov[n][k]) for n in names}
        est["centralized"] = (result.central_mean[k], result.central_cov[k])
        out += b.step(float(tk), est, result.truth[k], result.central_mean[k])
    out += b.sensors()
    out += b.tree(float(result.times[-1]))
    for i, ev in enumerate(getattr(result, "events", []) or []):
        out += b.event(i, ev)
    out.sort(key=lambda e: e[2])
    return out


class LiveView:
    """A running scenario served to Foxglove over its WebSocket protocol (foxglove-sdk,
    ``pip install 'dfusion[live]'``): the topics of the recording, step by step, paced so
    that scenario time runs ``speed`` times as fast as the wall clock.

    ``sink(topic, schema, log_ns, message)`` replaces the server (tests, other outputs).
    Use as the ``on_step`` of :func:`dfusion.sim.runner.run_scenario`.
    """

    def __init__(self, sc, *, port: int = 8765, speed: float = 1.0, sink=None, host: str = "127.0.0.1") -> None:
        import time

        self.sc, self.speed = sc, float(speed)
        self._builder = _Builder(sc, sorted(sc.nodes), 0)
        self._server = None
        self._channels: dict[str, Any] = {}
        if sink is None:
            try:
                import foxglove
            except ImportError:
                raise ImportError("the live view needs foxglove-sdk: pip install 'dfusion[live]'") from None
            self._foxglove = foxglove
            self._server = foxglove.start_server(host=host, port=port, name="dfusion")
            sink = self._to_server
        self._sink = sink
        self._wall0 = time.monotonic()
        self._events = 0
        for m in self._builder.sensors() + self._builder.tree(sc.duration):
            self._sink(*m)

    def _to_server(self, topic: str, schema: str, log_ns: int, msg: dict[str, Any]) -> None:
        ch = self._channels.get(topic)
        if ch is None:
            schema_encoding, message_encoding, data = channel_schema(schema)
            ch = self._channels[topic] = self._foxglove.Channel(
                topic, schema=self._foxglove.Schema(name=schema, encoding=schema_encoding, data=data),
                message_encoding=message_encoding)
        ch.log(encode(schema, msg), log_time=log_ns)

    def __call__(self, t: float, estimates: dict[str, tuple[np.ndarray, np.ndarray]], truth: np.ndarray,
                 events: list[dict[str, Any]] = ()) -> None:
        """One step: ``estimates`` with ``"centralized"``; ``events`` the measurements processed since."""
        import time

        for m in self._builder.step(t, estimates, truth, estimates["centralized"][0]):
            self._sink(*m)
        for ev in events:
            for m in self._builder.event(self._events, ev):
                self._sink(*m)
            self._events += 1
        if self.speed > 0:
            wait = self._wall0 + t / self.speed - time.monotonic()
            if wait > 0:
                time.sleep(wait)

    def node_estimate(self, name: str, t: float, mean: np.ndarray, cov: np.ndarray) -> None:
        """One node's estimate at ``t`` as it arrives (``dfusion run``: a
        :class:`~dfusion.run.monitor.Monitor` listener); no truth, NEES or gaps then."""
        mean, cov = np.asarray(mean, float), np.asarray(cov, float)
        nan = np.full_like(mean, np.nan)
        for m in self._builder.step(t, {name: (mean, cov)}, nan, nan):
            if m[0] == "/scene/estimates":   # only this node's entity: the others keep theirs
                m[3]["entities"] = [e for e in m[3]["entities"] if e["id"] == f"ellipse/{name}"]
            self._sink(*m)

    def close(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None


def record_mcap(result, path: str | Path, *, start_ns: int = 0) -> Path:
    """Write the run ``result`` (:class:`~dfusion.sim.runner.SimulationResult`) as an MCAP
    file (module docstring for the topics); log times and stamps are ``start_ns`` plus
    the scenario time (``dfusion replay``: the bag's stamp of time 0)."""
    return write_mcap(messages_of_result(result, start_ns=start_ns), path)


def write_mcap(msgs: Iterable[Message], path: str | Path) -> Path:
    """Write messages ``(topic, schema, log_time_ns, message)`` (in time order) as an MCAP file:
    one channel per topic in its schema's encoding (:func:`channel_schema`, :func:`encode`)."""
    from mcap.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="dfusion")
        schema_ids: dict[str, int] = {}
        channels: dict[str, int] = {}
        seq: dict[str, int] = {}
        for topic, schema, log_ns, msg in msgs:
            if topic not in channels:
                schema_encoding, message_encoding, data = channel_schema(schema)
                if schema not in schema_ids:
                    schema_ids[schema] = w.register_schema(schema, schema_encoding, data)
                channels[topic] = w.register_channel(topic, message_encoding, schema_ids[schema])
                seq[topic] = 0
            seq[topic] += 1
            w.add_message(channels[topic], log_ns, encode(schema, msg), log_ns, seq[topic])
        w.finish()
    return path


# --- many targets: every node's tracks ----------------------------------------------------------------------------

_TRUTH_GREY = (0.55, 0.55, 0.55)
_MATCHING_ID = 0   # foxglove.SceneEntityDeletion.Type.MATCHING_ID


def _deletions(ns: int, ids: Iterable[str]) -> list[dict[str, Any]]:
    return [{"timestamp": _stamp(ns), "type": _MATCHING_ID, "id": i} for i in sorted(ids)]


def messages_of_tracks(history, truth=None, *, start_ns: int = 0, views: Iterable[Any] = ()) -> list[Message]:
    """Every message of a many-target recording (:func:`record_tracks_mcap`), sorted by time.

    ``history``: a :class:`~dfusion.tracking.TrackHistory`; ``truth``: a
    :class:`~dfusion.tracking.TruthPaths` or None; ``views``: objects with ``name, x0, x1, y0, y1``
    (:class:`~dfusion.sim.plaza.CameraView`), drawn at time 0.
    """
    from dfusion.tracking.track import TrackId
    from dfusion.viz.tracks import identity_color

    out: list[Message] = []
    for node, series in history.nodes.items():
        shown: set[str] = set()
        for t, rows in series:
            ns = start_ns + int(round(float(t) * 1e9))
            stamp = _stamp(ns)
            ents, data = [], []
            for tid, m, P in rows:
                rgb = identity_color(tid)
                eid = f"track/{node}/{tid}"
                ellipse = ellipse_points(m[:2], P[:2, :2], 3.0, 48)
                ents.append(_entity(ns, eid, lines=[_line(ellipse, rgb, thickness=2.0)],
                                    spheres=[_sphere(m[:2], rgb, 0.35)],
                                    texts=[_text(m[:2] + np.array([0.4, 0.4]), str(tid), rgb, 12.0)],
                                    metadata={"node": node, "track_id": str(tid),
                                              "meaning": "track: estimate and its 3-sigma ellipse"}))
                is_id = isinstance(tid, TrackId)
                data.append({"id": str(tid), "origin": tid.origin if is_id else None,
                             "serial": int(tid.serial) if is_id else None, "mean": m.tolist(),
                             "covariance": P.ravel().tolist(), "std": np.sqrt(np.maximum(np.diag(P), 0.0)).tolist()})
            now = {e["id"] for e in ents}
            out.append((f"/nodes/{node}/tracks", "foxglove.SceneUpdate", ns,
                        {"deletions": _deletions(ns, shown - now), "entities": ents}))
            out.append((f"/nodes/{node}/track_estimates", "dfusion/Tracks", ns,
                        {"timestamp": stamp, "t": float(t), "node": node, "tracks": data}))
            shown = now
    ents = []
    for v in views:
        rect = [(v.x0, v.y0), (v.x1, v.y0), (v.x1, v.y1), (v.x0, v.y1)]
        ents.append(_entity(start_ns, f"view/{v.name}", lines=[_line(rect, (0.4, 0.4, 0.4), kind=_LINE_LOOP,
                                                                      thickness=1.0)],
                            texts=[_text((v.x0 + 0.5, v.y1 - 0.5), f"{v.name} view", (0.4, 0.4, 0.4), 11.0)],
                            metadata={"view": v.name, "meaning": "the ground the camera sees"}))
    if truth is not None:
        for name, (_, xy) in truth.paths.items():
            ents.append(_entity(start_ns, f"truth_path/{name}", lines=[_line(xy, _TRUTH_GREY, thickness=1.0, a=0.6)],
                                metadata={"target": name, "meaning": "the whole true path"}))
        shown = set()
        for t in history.times():
            ns = start_ns + int(round(float(t) * 1e9))
            names, pos = truth.at(float(t))
            tents = [_entity(ns, f"truth/{n}", spheres=[_sphere(p, _TRUTH_GREY, 0.25)],
                             texts=[_text(p - np.array([0.0, 0.6]), n, _TRUTH_GREY, 10.0)],
                             metadata={"target": n, "meaning": "true position"}) for n, p in zip(names, pos)]
            now = {e["id"] for e in tents}
            out.append(("/truth/targets", "foxglove.SceneUpdate", ns,
                        {"deletions": _deletions(ns, shown - now), "entities": tents}))
            shown = now
    if ents:
        out.append(("/scene/static", "foxglove.SceneUpdate", start_ns, {"deletions": [], "entities": ents}))
    out.sort(key=lambda e: e[2])
    return out


def record_tracks_mcap(history, path: str | Path, truth=None, *, start_ns: int = 0, views: Iterable[Any] = ()) -> Path:
    """Write every node's tracks (a :class:`~dfusion.tracking.TrackHistory`) and the truth as an
    MCAP file for Foxglove (module docstring, "Many targets")."""
    return write_mcap(messages_of_tracks(history, truth, start_ns=start_ns, views=views), path)
