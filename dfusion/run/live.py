r"""A fusion node live on a machine: ROS 2 topics in, fused estimate and health out (``nodes/``).

The programs of ``nodes/`` (``python nodes/robot_localizer.py NODE_FILE``, ...) call :func:`main`
with their kind. The node is the one ``dfusion run`` runs, built the same way (the scenario's
:class:`~dfusion.fusion.FusionNode` and front end, :mod:`dfusion.scenario.build`) and driven by the
same loop (:class:`~dfusion.run.node_process.NodeProcess` in a
:class:`~dfusion.run.node_process.Host`: predict every ``dt``, fuse, exchange with the neighbours of
the scenario's tree over Zenoh, final phase at the end). What differs is where measurements come
from and where the estimate goes:

* **in**: the node file's input topics (:class:`~dfusion.ros2.link.Ros2Link`, on the node's own
  Zenoh session, keys of the chosen convention). At every step the messages that arrived are
  taken (step ``k`` runs ``latency`` seconds after its time ``start + k dt``: a message on its
  way that long is still fused before the estimate of its time goes out, which is that much
  later); a message's measurement time is its header stamp, in scenario time
  ``t = (stamp - start)``, ``start`` the wall-clock time of scenario time 0 (so stamps are
  wall-clock times, as a robot's drivers give them; the nodes of one network share ``start``:
  their node files give it, else a node alone starts its clock when it starts); it reaches the
  node at the step it was taken (at its stamp when that is ahead), and the delayed-state filter
  fuses it at its own time (or refuses it, counted, when it is older than the window). A message stamped before the start or more than :data:`FUTURE_TOLERANCE` s after now
  is refused and counted. A position message's own covariance replaces the node's noise
  (:func:`dfusion.ros2.inputs.reading_of`).
* **out**: after every step, the fused estimate (the policy's output when the policy is not plain
  fusion) as ``nav_msgs/Odometry`` and ``geometry_msgs/PoseWithCovarianceStamped`` in the node
  file's frame, stamped ``start + t``; every ``diagnostics_period`` seconds (and at the end) a
  ``diagnostic_msgs/DiagnosticArray`` with the node's health: ``OK``, ``WARN`` when no input was
  fused for ``stale_after`` seconds or inputs were refused since the last one, ``ERROR`` when the
  node stops on a signal; its values are the node's counters.

The node runs for the node file's ``duration`` (default a day), then does the final phase and
writes ``--result`` (JSON), or until SIGTERM/SIGINT (exit 0).
"""
from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zenoh

from dfusion.errors import DfusionError, ValidationError
from dfusion.frontends.base import EIFFrontEnd
from dfusion.models.base import MeasurementModel
from dfusion.run.common import Status, load_network_key
from dfusion.run.measurements import OwnMeasurement
from dfusion.run.node_process import Host, NodeProcess
from dfusion.run.nodefile import NodeFile, kind_of, load_node_file
from dfusion.ros2.codec import diagnostics, estimate_messages, register_definition, type_hash
from dfusion.ros2.inputs import Z_SIZE
from dfusion.ros2.link import Ros2Link
from dfusion.scenario.loader import load_scenario
from dfusion.scenario.security import SecurityOptions
from dfusion.scenario.spec import Scenario
from dfusion.transport.zenoh import ZenohConfig, ZenohTransport

log = logging.getLogger("dfusion.live")

__all__ = ["LiveNodeProcess", "MessageNoise", "main", "FUTURE_TOLERANCE"]

#: Seconds a message's stamp may be ahead of the node's clock (clock offsets between machines).
FUTURE_TOLERANCE = 1.0


class MessageNoise(MeasurementModel):
    """The node's sensor model with the noise covariance a message states (``R``), otherwise the same."""

    def __init__(self, sensor: MeasurementModel, R: np.ndarray) -> None:
        self.sensor, self._R = sensor, np.asarray(R, dtype=float)
        self.dim_z = sensor.dim_z
        self.is_linear = getattr(sensor, "is_linear", False)

    def h(self, x: np.ndarray) -> np.ndarray:
        return self.sensor.h(x)

    def H(self, x: np.ndarray) -> np.ndarray:
        return self.sensor.H(x)

    @property
    def R(self) -> np.ndarray:
        return self._R


@dataclass(frozen=True)
class LiveMeasurement(OwnMeasurement):
    """A measurement from a message, with the message's covariance (``None``: the node's own)."""

    R: np.ndarray | None = None


class LiveNodeProcess(NodeProcess):
    """:class:`NodeProcess` fed from ROS 2 topics and publishing to them (module docstring)."""

    def __init__(self, sc: Scenario, name: str, nf: NodeFile, **kw: Any) -> None:
        #: input topic -> user converter; loaded (and the .msg definitions registered) here, before
        #: the node joins the network (:meth:`attach`), so a bad one stops it with one line first
        self.converters = load_ros_types(nf)
        if kw.get("start") is not None:   # each step runs `latency` after its time (module docstring)
            kw["start"] = kw["start"] + nf.ros.latency
        super().__init__(sc, name, measurements=[], **kw)
        self.nf = nf
        self.ros: Ros2Link | None = None
        self.counters.update(inputs_before_start=0, inputs_from_future=0, inputs_wrong_size=0,
                             inputs_with_covariance=0)
        self._last_fused = -math.inf
        self._diag_due = 0.0
        self._refused_seen = 0
        sensor = sc.nodes[name].sensor
        self._dim = getattr(sensor, "dim_z", None)

    @property
    def origin_ns(self) -> int:
        """Scenario time 0 as a ROS time stamp (nanoseconds since the epoch; 0 before the start is known):
        the start, ``latency`` before the wall-clock time of the node's step 0."""
        return int(round((self.start - self.nf.ros.latency) * 1e9)) if self.start is not None else 0

    def attach(self, tr: ZenohTransport) -> None:
        super().attach(tr)
        r = self.nf.ros
        self.ros = Ros2Link(tr.session, r.convention, r.node_name, r.frame, r.inputs, r.output_types(),
                            self.converters)

    def collect(self, t: float) -> None:
        if self.ros is None:
            return
        self.forget_fused()   # live, the list of measurements would grow for as long as the node runs
        batch = []
        for rec in self.ros.take():
            tm = round((rec.stamp_ns - self.origin_ns) * 1e-9, 9)
            if tm <= 0.0:
                self.counters["inputs_before_start"] += 1
                continue
            if tm > t + FUTURE_TOLERANCE:
                self.counters["inputs_from_future"] += 1
                continue
            z = rec.reading.z
            if self._dim is not None and z.size != self._dim:   # never cut or padded: refused, counted
                self.counters["inputs_wrong_size"] += 1
                if self.counters["inputs_wrong_size"] == 1:
                    log.warning("%s: a message of %s gives %d values, the node's sensor takes %d: refused (counted "
                                "in inputs_wrong_size)", self.name, rec.topic, z.size, self._dim)
                continue
            # it reaches the node now, or at its stamp when that is ahead of the node's clock (another
            # machine's clock): never fused before the filter has reached its time
            batch.append(LiveMeasurement(tm, z, max(t, tm), rec.reading.R))
        batch.sort(key=lambda m: m.t)
        self.meas.extend(batch)

    def fuse_one(self, m: OwnMeasurement) -> None:
        R = getattr(m, "R", None)
        sensor = getattr(self.front, "sensor", None)
        if R is not None and type(self.front) is EIFFrontEnd and getattr(sensor, "dim_z", None) == R.shape[0]:
            self.node.update(m.t, m.z, MessageNoise(sensor, R))
            self.front.stats.processed += 1
            self.front.stats.contributed += 1
            self.counters["inputs_with_covariance"] += 1
        else:
            super().fuse_one(m)
        self._last_fused = m.arrival

    def published(self, status: Status) -> None:
        if self.ros is None or status.phase == "ready":
            return
        stamp = self.origin_ns + int(round(status.t * 1e9))
        mean, cov = (status.output[1], status.output[2]) if status.output is not None else (status.mean, status.cov)
        outs = self.nf.ros.outputs
        try:
            if mean is not None and ("odometry" in outs or "pose" in outs):
                odom, pose = estimate_messages(mean, cov, stamp, self.nf.ros.frame, self.nf.ros.child_frame)
                if "odometry" in outs:
                    self.ros.publish(outs["odometry"], odom)
                if "pose" in outs:
                    self.ros.publish(outs["pose"], pose)
            now = time.monotonic()
            if "diagnostics" in outs and (status.phase != "run" or now >= self._diag_due):
                self._diag_due = now + self.nf.ros.diagnostics_period
                self.ros.publish(outs["diagnostics"], self._health(status, stamp))
        except Exception as exc:   # a closed session at shutdown: the estimate is in the result file
            log.warning("%s: ROS 2 publication failed: %s", self.name, exc)

    def _health(self, status: Status, stamp: int) -> Any:
        """The DiagnosticArray of the node's health (module docstring)."""
        c = dict(self.stats())
        c.update({f"ros_{k}": v for k, v in self.ros.counters.items()})
        refused = sum(c[k] for k in ("measurements_refused", "inputs_before_start", "inputs_from_future",
                                     "inputs_wrong_size", "ros_decode_errors", "ros_frame_errors",
                                     "ros_converter_errors", "ros_shed", "ros_oversized"))
        quiet = status.t - self._last_fused if self.nf.ros.inputs else 0.0
        if status.phase == "stopped":
            level, msg = "error", f"stopped: {self.stop_reason}"
        elif quiet > self.nf.ros.stale_after:
            level, msg = "warn", (f"no input fused for {quiet:.1f} s" if math.isfinite(quiet)
                                  else f"no input fused yet (inputs: {', '.join(self.nf.ros.inputs)})")
        elif refused > self._refused_seen:
            level, msg = "warn", f"{refused - self._refused_seen} inputs refused since the last report"
        else:
            level, msg = "ok", "final estimate" if status.phase == "final" else "fusing"
        self._refused_seen = refused
        values = {"phase": status.phase, "t": f"{status.t:.3f}", "start_ns": self.origin_ns, **c}
        if status.mean is not None:
            values["position_std_m"] = f"{math.sqrt(max(0.0, float(np.trace(status.cov[:2, :2])) / 2)):.4f}"
        return diagnostics(stamp, f"dfusion/{self.name}", self.nf.ros.node_name, level, msg, values)

    def close(self) -> None:
        if self.ros is not None:
            self.ros.close()
            self.ros = None
        super().close()


def load_ros_types(nf: NodeFile) -> dict[str, Callable[[Any, float], Any]]:
    """Register the node file's ``.msg`` definitions, check that every input and output type is
    known (a custom type needs its definition), and load the user converters; returns input
    topic -> converter. Runs before the node joins the network: a definition that does not parse, a
    type nobody defined or a converter file that does not load is one line naming the node file."""
    r = nf.ros
    try:
        for msgtype, path in r.definitions.items():
            register_definition(msgtype, Path(path).read_text())
        for msgtype in {*r.inputs.values(), *r.output_types().values()}:
            type_hash(msgtype)   # raises for a type the type store does not know
        if not r.converters:
            return {}
        from dfusion.sim.replay import load_function   # noqa: PLC0415  (the one loader of user converters)

        return {topic: load_function(path, func) for topic, (path, func) in r.converters.items()}
    except ValidationError as exc:
        raise ValidationError(f"{nf.path}: {exc}") from None


def check_inputs(nf: NodeFile, sc: Scenario) -> None:
    """Refuse (one line) an input whose messages give another number of values than the node's
    sensor takes (a pose for a range sensor, a range for a position sensor); a scan's beams are
    checked per message, a converter's ``z`` too."""
    spec = sc.nodes[nf.name]
    dim = getattr(spec.sensor, "dim_z", None)
    for topic, msgtype in nf.ros.inputs.items():
        size = Z_SIZE.get(msgtype)
        if topic not in nf.ros.converters and dim is not None and size is not None and size != dim:
            raise DfusionError(f"{nf.path}: input {topic} ({msgtype}) gives {size} value(s), but node {nf.name!r} "
                               f"({spec.sensor_kind}) takes {dim}: give a converter (convert = \"FILE.py:FUNCTION\")")


def build_parser(kind: str | None) -> argparse.ArgumentParser:
    prog = f"nodes/{kind}" if kind else "python -m dfusion.run.live"
    p = argparse.ArgumentParser(prog=prog, description="Run one dfusion node live: ROS 2 topics in, fused estimate, "
                                                       "DiagnosticArray and liveliness out, over Zenoh.")
    p.add_argument("node_file", help="the node file (TOML; docs/ros.md, Live use)")
    p.add_argument("--result", default=None, help="write the final estimate and counters here (JSON)")
    p.add_argument("--duration", type=float, default=None, help="override the node file's duration (s)")
    p.add_argument("--start-time", type=float, default=None,
                   help="override the node file's start: UNIX time of scenario time 0, the same for every node")
    p.add_argument("-v", "--verbose", action="count", default=0)
    return p


def main(argv: list[str] | None = None, kind: str | None = None) -> int:
    """Run the node of a node file (``kind``: the program's node kind, checked against the file)."""
    args = build_parser(kind).parse_args(sys.argv[1:] if argv is None else argv)
    level = [logging.INFO, logging.DEBUG][min(args.verbose, 1)]
    logging.basicConfig(level=level, stream=sys.stderr, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    host: Host | None = None
    early: list[str] = []

    def on_signal(signum, frame):   # only sets a flag; the loop looks at it every POLL seconds
        (host.request_stop if host is not None else early.append)(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        nf = load_node_file(args.node_file)
        if kind is not None and nf.kind != kind:
            raise DfusionError(f"{nf.path}: kind is {nf.kind!r}, but this is the {kind} program (nodes/)")
        sc = load_scenario(nf.scenario, duration=args.duration or nf.duration, plugins=list(nf.plugins))
        if nf.name not in sc.nodes:
            raise DfusionError(f"{nf.path}: node {nf.name!r} is not in {nf.scenario} (nodes: {sorted(sc.nodes)})")
        actual = kind_of(sc.nodes[nf.name].sensor_kind if sc.nodes[nf.name].sensor is not None else None)
        if actual != nf.kind:
            raise DfusionError(f"{nf.path}: kind is {nf.kind!r}, but node {nf.name!r} of {nf.scenario} is a "
                               f"{actual} node")
        if nf.kind == "relay" and nf.ros.inputs:
            raise DfusionError(f"{nf.path}: a relay node has no sensor: it takes no inputs")
        check_inputs(nf, sc)
        sec = SecurityOptions(nf.network_key_file, None, nf.tls_ca, nf.tls_cert, nf.tls_key)
        zc = ZenohConfig(mode=nf.mode, listen=nf.listen, connect=nf.connect, extra=nf.zenoh_options,
                         tls=sec.tls_files(nf.name))
        start = args.start_time if args.start_time is not None else nf.start
        proc = LiveNodeProcess(sc, nf.name, nf, network=nf.network, zconfig=zc, start=start, run_id=nf.run_id,
                               network_key=load_network_key(nf.network_key_file), result=args.result)
        host = Host([proc], network=nf.network, zconfig=zc, label=nf.name)
        if early:
            return 0
        log.info("%s: %s node of %s, inputs %s, outputs %s (%s)", nf.name, nf.kind, nf.scenario,
                 ", ".join(nf.ros.inputs) or "none", ", ".join(nf.ros.outputs.values()) or "none",
                 nf.ros.convention.kind)
        return host.run()
    except (DfusionError, OSError, zenoh.ZError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
