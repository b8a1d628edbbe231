r"""The node file: what a program of ``nodes/`` needs to run one fusion node live on a machine.

A TOML file (``docs/ros.md``, "Live use", has a full example)::

    name = "robot"                       # the node of the scenario this machine runs
    kind = "robot"                       # camera | wsn | robot | relay (checked against the scenario)
    scenario = "robot.scenario.toml"     # the models: node table, target motion, prior, dt, window, tree, links
    network = "dfusion"                  # Zenoh key space of the fusion messages (dfusion/NETWORK/...)
    start = 1795000000.0                 # optional: UNIX time of scenario time 0, the same in every node
                                         # file of one network (default: when this node starts: alone)
    duration = 3600.0                    # optional: seconds to run (default 86400); then the final phase
    run_id = "plant-2026-11"             # optional: the run identifier the other nodes were given (their
                                         # --run-id): fusion messages are authenticated for it (default "")
    plugins = []                         # optional: modules or .py files with sensor kinds / policies

    [zenoh]
    mode = "peer"                        # peer | client (through routers)
    listen = ["tcp/127.0.0.1:7450"]
    connect = ["tcp/127.0.0.1:7451"]     # neighbours (peers) or routers
    options = { "transport/link/tx/lease" = 2000 }   # optional: further Zenoh configuration paths

    [security]                           # optional
    network_key_file = "network.key"     # HMAC key of fusion messages
    tls_ca = "ca.pem"                    # mutual TLS: all three, endpoints tls/...
    tls_cert = "robot.pem"
    tls_key = "robot.key"

    [ros]
    convention = "rmw_zenoh"             # rmw_zenoh | ros2dds (zenoh-bridge-ros2dds)
    domain_id = 0                        # rmw_zenoh's ROS_DOMAIN_ID
    namespace = ""                       # ros2dds: the bridge's namespace
    node_name = "dfusion_robot"          # the ROS 2 node name announced (default dfusion_NAME)
    frame = "map"                        # the frame of inputs (via /tf_static) and outputs
    child_frame = "base_link"            # the odometry's child frame
    diagnostics_period = 1.0             # seconds between DiagnosticArray messages
    latency = 0.2                        # seconds a step waits for late messages (the estimate is that late)
    stale_after = 2.0                    # warn when no input was fused for this long (s)

    [[inputs]]
    topic = "/odom"
    type = "nav_msgs/msg/Odometry"

    [[inputs]]                           # another type, or another z: a user function
    topic = "/detections"
    type = "vendor_msgs/msg/Detections"
    definition = "Detections.msg"        # a type rosbags does not know: its .msg definition
    convert = "my_convert.py:first_pixel"   # f(msg, stamp_s) -> z (None: skip the message)

    [outputs]                            # each optional; none: nothing published there
    odometry = "/dfusion/robot/odom"
    pose = "/dfusion/robot/pose"
    diagnostics = "/diagnostics"

Relative paths are relative to the node file. The loader is strict: an unknown key (with the
nearest known one suggested), a value of the wrong type, a number that is not finite or of the wrong sign
(checked by the scenario's :func:`dfusion.scenario.values.number`), a missing required key, a missing file or
an input type the node cannot take is one clear line (:class:`~dfusion.errors.ValidationError`).
"""
from __future__ import annotations

import difflib
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dfusion.errors import ValidationError
from dfusion.ros2.inputs import SUPPORTED_INPUTS
from dfusion.ros2.keys import Convention, check_topic
from dfusion.scenario.values import number

__all__ = ["NodeFile", "Ros2Settings", "load_node_file", "NODE_KINDS", "kind_of", "DEFAULT_DURATION"]

#: The node kinds, one program of ``nodes/`` each.
NODE_KINDS = ("camera", "wsn", "robot", "relay")
#: Seconds a live node runs when its node file gives no ``duration`` (a day).
DEFAULT_DURATION = 86400.0
OUTPUT_TYPES = {"odometry": "nav_msgs/msg/Odometry", "pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
                "diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}

_TOP = {"name": str, "kind": str, "scenario": str, "network": str, "start": float, "duration": float, "run_id": str,
        "plugins": list,
        "zenoh": dict, "security": dict, "ros": dict, "inputs": list, "outputs": dict}
_ZENOH = {"mode": str, "listen": list, "connect": list, "options": dict}
_SECURITY = {"network_key_file": str, "tls_ca": str, "tls_cert": str, "tls_key": str}
_ROS = {"convention": str, "domain_id": int, "namespace": str, "node_name": str, "frame": str,
        "child_frame": str, "diagnostics_period": float, "stale_after": float, "latency": float}
_INPUT = {"topic": str, "type": str, "convert": str, "definition": str}
_OUTPUTS = {k: str for k in OUTPUT_TYPES}


def kind_of(sensor_kind: str | None) -> str:
    """The node kind of a scenario node's sensor kind: no sensor -> ``relay``; a camera kind
    (``camera``, ``robot_camera``, ``robot_env_camera``) -> ``camera``; ``wsn_*`` -> ``wsn``;
    every other (``position``, ``robot_mcl``, ``robot_icp``, plug-ins) -> ``robot``."""
    if sensor_kind is None:
        return "relay"
    if "camera" in sensor_kind:
        return "camera"
    if sensor_kind.startswith("wsn"):
        return "wsn"
    return "robot"


@dataclass(frozen=True)
class Ros2Settings:
    """The ``[ros]`` table, ``[[inputs]]`` and ``[outputs]`` of a node file."""

    convention: Convention
    node_name: str
    frame: str = "map"
    child_frame: str = "base_link"
    diagnostics_period: float = 1.0
    stale_after: float = 2.0
    #: Wall-clock seconds each step of the node waits after its time for messages still on their way
    latency: float = 0.2
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    #: input topic -> (Python file, function name) of its user converter
    converters: dict[str, tuple[str, str]] = field(default_factory=dict)
    #: message type -> its .msg definition file (types rosbags does not know)
    definitions: dict[str, str] = field(default_factory=dict)

    def output_types(self) -> dict[str, str]:
        """Output topic -> message type."""
        return {topic: OUTPUT_TYPES[what] for what, topic in self.outputs.items()}


@dataclass(frozen=True)
class NodeFile:
    """A loaded node file (see the module docstring)."""

    path: Path
    name: str
    kind: str
    scenario: Path
    network: str
    start: float | None
    duration: float
    plugins: tuple[str, ...]
    mode: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    zenoh_options: dict[str, Any]
    network_key_file: str | None
    tls_ca: str | None
    tls_cert: str | None
    tls_key: str | None
    ros: Ros2Settings
    run_id: str | None = None


def _check(table: dict, schema: dict[str, type], where: str, src: Path) -> None:
    for key, value in table.items():
        if key not in schema:
            near = difflib.get_close_matches(key, list(schema), n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else f" (known: {', '.join(schema)})"
            raise ValidationError(f"{src}: unknown key '{where}{key}'{hint}")
        want = schema[key]
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool)) if want is float else \
            (isinstance(value, int) and not isinstance(value, bool)) if want is int else isinstance(value, want)
        if not ok:
            raise ValidationError(f"{src}: {where}{key} must be {want.__name__}, got {type(value).__name__} "
                                  f"{value!r}")


def _number(table: dict, key: str, default: float | None, where: str, src: Path, **sign: bool) -> float:
    """``table[key]`` (or ``default``) through the scenario's checks (:func:`dfusion.scenario.values.number`:
    finite, and the sign asked for), the error naming the file and the key."""
    try:
        return number(table, key, default, **sign)
    except ValidationError as exc:
        raise ValidationError(f"{src}: {where}{exc}") from None


def _strings(values: list, what: str, src: Path) -> tuple[str, ...]:
    bad = [v for v in values if not isinstance(v, str)]
    if bad:
        raise ValidationError(f"{src}: {what} must be a list of strings, got {bad[0]!r}")
    return tuple(values)


def _path(base: Path, value: str | None) -> str | None:
    if value is None:
        return None
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else base / p)


def load_node_file(path: str | Path) -> NodeFile:
    """Read and check a node file (see the module docstring).

    Raises
    ------
    ValidationError
        One line naming the file and the key at fault.
    """
    src = Path(path)
    try:
        data = tomllib.loads(src.read_text())
    except OSError as exc:
        raise ValidationError(f"cannot read the node file {src}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValidationError(f"{src}: not TOML: {exc}") from None
    _check(data, _TOP, "", src)
    for key in ("name", "kind", "scenario"):
        if key not in data:
            raise ValidationError(f"{src}: missing key {key!r}")
    if data["kind"] not in NODE_KINDS:
        raise ValidationError(f"{src}: kind must be one of {', '.join(NODE_KINDS)}, got {data['kind']!r}")
    base = src.resolve().parent
    z, sec, ros = data.get("zenoh", {}), data.get("security", {}), data.get("ros", {})
    _check(z, _ZENOH, "zenoh.", src)
    _check(sec, _SECURITY, "security.", src)
    _check(ros, _ROS, "ros.", src)
    mode = z.get("mode", "peer")
    if mode not in ("peer", "client"):
        raise ValidationError(f"{src}: zenoh.mode must be peer or client, got {mode!r}")
    tls = [sec.get(k) for k in ("tls_ca", "tls_cert", "tls_key")]
    if any(tls) and not all(tls):
        raise ValidationError(f"{src}: mutual TLS needs all of security.tls_ca, tls_cert and tls_key")
    duration = _number(data, "duration", DEFAULT_DURATION, "", src, positive=True)
    start = _number(data, "start", None, "", src, positive=True) if "start" in data else None
    inputs: dict[str, str] = {}
    converters: dict[str, tuple[str, str]] = {}
    definitions: dict[str, str] = {}
    for i, item in enumerate(data.get("inputs", [])):
        if not isinstance(item, dict):
            raise ValidationError(f"{src}: inputs[{i}] must be a table with topic and type")
        _check(item, _INPUT, f"inputs[{i}].", src)
        if "topic" not in item or "type" not in item:
            raise ValidationError(f"{src}: inputs[{i}] needs topic and type")
        if item["type"] not in SUPPORTED_INPUTS and "convert" not in item:
            raise ValidationError(f"{src}: inputs[{i}].type {item['type']!r} is not supported "
                                  f"(supported: {', '.join(SUPPORTED_INPUTS)}; other types need convert = "
                                  "\"FILE.py:FUNCTION\")")
        topic = _topic(item["topic"], f"inputs[{i}].topic", src)
        if topic in inputs:
            raise ValidationError(f"{src}: input topic {topic} is given twice")
        inputs[topic] = item["type"]
        if "convert" in item:
            file, sep, func = item["convert"].rpartition(":")
            if not sep or not file.endswith(".py") or not func.isidentifier():
                raise ValidationError(f"{src}: inputs[{i}].convert must be FILE.py:FUNCTION, got {item['convert']!r}")
            if not Path(_path(base, file)).is_file():
                raise ValidationError(f"{src}: inputs[{i}].convert: {_path(base, file)} does not exist")
            converters[topic] = (_path(base, file), func)
        if "definition" in item:
            definition = _path(base, item["definition"])
            if not Path(definition).is_file():
                raise ValidationError(f"{src}: inputs[{i}].definition: {definition} does not exist")
            definitions[item["type"]] = definition
    outputs = data.get("outputs", {"odometry": f"/dfusion/{data['name']}/odom",
                                   "pose": f"/dfusion/{data['name']}/pose", "diagnostics": "/diagnostics"})
    _check(outputs, _OUTPUTS, "outputs.", src)
    outputs = {k: _topic(v, f"outputs.{k}", src) for k, v in outputs.items()}
    try:
        convention = Convention(ros.get("convention", "rmw_zenoh"), ros.get("domain_id", 0), ros.get("namespace", ""))
    except ValidationError as exc:
        raise ValidationError(f"{src}: ros.{exc}") from None
    periods = {k: _number(ros, k, d, "ros.", src, positive=True)
               for k, d in (("diagnostics_period", 1.0), ("stale_after", 2.0))}
    latency = _number(ros, "latency", 0.2, "ros.", src)
    if not 0 <= latency <= 10:
        raise ValidationError(f"{src}: ros.latency must be in [0, 10] seconds, got {latency}")
    settings = Ros2Settings(convention, ros.get("node_name", f"dfusion_{data['name']}"), ros.get("frame", "map"),
                            ros.get("child_frame", "base_link"), periods["diagnostics_period"],
                            periods["stale_after"], latency, inputs, outputs, converters, definitions)
    return NodeFile(src, data["name"], data["kind"], Path(_path(base, data["scenario"])),
                    data.get("network", "dfusion"), start, duration,
                    tuple(_path(base, p) if p.endswith(".py") else p
                          for p in _strings(data.get("plugins", []), "plugins", src)),
                    mode, _strings(z.get("listen", []), "zenoh.listen", src),
                    _strings(z.get("connect", []), "zenoh.connect", src), dict(z.get("options", {})),
                    _path(base, sec.get("network_key_file")), *(_path(base, v) for v in tls), settings,
                    data.get("run_id"))


def _topic(value: str, where: str, src: Path) -> str:
    try:
        return check_topic(value)
    except ValidationError as exc:
        raise ValidationError(f"{src}: {where}: {exc}") from None
