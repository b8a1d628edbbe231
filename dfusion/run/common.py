"""What the node processes, the monitor and the launcher share.

* the network key (HMAC of fusion and monitor messages): ``--network-key-file``
  or the environment (:data:`ENV_KEY_FILE`, :data:`ENV_KEY`); a fresh random one
  per run (:func:`generate_network_key`, a file of mode 0600);
* the security options of a run from the command line (:func:`add_tls_arguments`;
  a scenario's ``[security]`` table is :mod:`dfusion.scenario.security`);
* the monitor message (msgpack; authenticated like fusion messages when a key is set, with
  the key of the network and the run, :class:`Status`);
* the number of rounds of the final phase.
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import logging
import math
import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from dfusion.errors import MessageError, ValidationError
from dfusion.scenario.security import SecurityOptions
from dfusion.scenario.spec import Scenario
from dfusion.topology import settling_rounds
from dfusion.wire import FrameKey

log = logging.getLogger(__name__)

#: Environment variable naming a file that holds the network key.
ENV_KEY_FILE = "DFUSION_NETWORK_KEY_FILE"
#: Environment variable holding the network key itself (UTF-8 text).
ENV_KEY = "DFUSION_NETWORK_KEY"
#: Version 2: the MAC is keyed for the network and the run (version 1 used the network key itself).
MONITOR_VERSION = 2
#: Longest monitor publication accepted (bytes): a step's estimate and counters take a few hundred.
MAX_STATUS_BYTES = 1 << 20
#: What a publication holds besides its estimates, tree and lost times (bytes): the envelope and
#: MAC (about 60), names, phase, times (about 100), the counters (about 40 of them: about 1.5 kB).
STATUS_BASE_BYTES = 16 * 1024
#: Most publications in one batch (:func:`encode_status_batch`): a host's nodes that stepped together.
MAX_STATUS_BATCH = 64
#: Domain of a monitor publication's MAC (fusion frames start with b"DF": the two never collide).
_STATUS_DOMAIN = b"dfusion-monitor/2\0"
PHASES = ("ready", "run", "final", "stopped")
#: Default wall-clock seconds a node waits for a neighbour's message of a final-phase round.
ROUND_TIMEOUT = 10.0


#: A node process writes at most this many bytes of log lines per incarnation (``logs/NAME.log``
#: collects every incarnation's output); past it, lines below ERROR are dropped and counted
#: (``log_lines_dropped`` in the run's JSON). Errors are always written.
MAX_LOG_BYTES = 8 << 20


class LogByteCap(logging.Filter):
    """A filter on a handler that lets through at most ``max_bytes`` of formatted log lines.

    Past the cap it writes one line saying so, then drops every record below ``ERROR`` and
    counts it in :attr:`dropped`: a flood of rejections or liveliness changes cannot fill the
    disk, and nothing is dropped silently. The size counted is that of the formatted line.
    """

    def __init__(self, handler: logging.Handler, max_bytes: int = MAX_LOG_BYTES) -> None:
        super().__init__()
        self.handler, self.max_bytes = handler, int(max_bytes)
        self.written = 0
        self.dropped = 0
        self._announced = False

    def filter(self, record: logging.LogRecord) -> bool:
        if self.written >= self.max_bytes and record.levelno < logging.ERROR:
            self.dropped += 1
            if not self._announced:
                self._announced = True
                self.handler.stream.write(f"log output reached its cap of {self.max_bytes} bytes: lines below "
                                          "ERROR are dropped from here on and counted (log_lines_dropped)\n")
            return False
        self.written += len(self.handler.format(record)) + 1
        return True


def load_network_key(path: str | Path | None = None) -> bytes | None:
    """The network key: from ``path``, else ``$DFUSION_NETWORK_KEY_FILE``, else ``$DFUSION_NETWORK_KEY``.

    A key file's bytes are used as they are, except that surrounding
    whitespace (a final newline) is stripped. ``None`` when nothing is set.
    """
    source = None
    if path is None and os.environ.get(ENV_KEY_FILE):
        path = os.environ[ENV_KEY_FILE]
    if path is not None:
        key = Path(path).read_bytes().strip()
        source = str(path)
    elif os.environ.get(ENV_KEY):
        key = os.environ[ENV_KEY].strip().encode()
        source = f"${ENV_KEY}"
    else:
        return None
    if not key:
        raise ValidationError(f"the network key from {source} is empty")
    if len(key) < 16:
        log.warning("the network key from %s has only %d bytes: use at least 16 random bytes", source, len(key))
    return key


def write_secret(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to a new file of mode 0600 (created so: never readable by others, even briefly)."""
    path = Path(path)
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    return path


def generate_network_key(path: str | Path) -> bytes:
    """A fresh random network key (32 bytes from :func:`secrets.token_bytes`, written as 64 hex
    characters) in a new file of mode 0600; returns the key as :func:`load_network_key` reads it."""
    key = secrets.token_bytes(32).hex().encode()
    write_secret(path, key + b"\n")
    return key


def new_run_id() -> str:
    """A random identifier of one run (16 hex characters)."""
    return secrets.token_hex(8)








def status_limit(sc: Scenario) -> int:
    """The longest monitor publication a node of ``sc`` can make (bytes), at most :data:`MAX_STATUS_BYTES`.

    ``STATUS_BASE_BYTES + 2 (9 (n + n^2) + 16) + 2 sum(len(name) + 3) + 36 max(rate * duration + 1)``:
    two estimates (the node's and its policy's output, ``n`` the state dimension; msgpack
    writes 8 bytes a float plus a header), a tree status listing every node at most twice,
    and the final publication's lost measurement times (9 bytes each, one per measurement
    time of the node, four times over for a margin). A longer publication cannot be a node's:
    the monitor drops it as it arrives, before copying it (``docs/processes.md``).
    """
    n = sc.target.motion.dim
    estimate = 9 * (n + n * n) + 16
    names = sum(len(name) + 3 for name in sc.nodes)
    lost = 36 * max((spec.rate * sc.duration + 1 for spec in sc.nodes.values()), default=1)
    return int(min(MAX_STATUS_BYTES, STATUS_BASE_BYTES + 2 * estimate + 2 * names + lost))


def encode_status_batch(publications: list[bytes]) -> bytes:
    """Several publications (:meth:`Status.encode`, each with its own MAC) as one Zenoh payload: a
    msgpack array of them. A host process sends the step publications of its nodes so, one put per
    step instead of one per node, on ``dfusion/NET/monitor/FIRST/batch``
    (:func:`dfusion.transport.zenoh.monitor_batch_key`, ``docs/processes.md``). At most
    :data:`MAX_STATUS_BATCH` of them."""
    if not 0 < len(publications) <= MAX_STATUS_BATCH:
        raise ValidationError(f"a batch holds 1 to {MAX_STATUS_BATCH} publications, got {len(publications)}")
    return msgpack.packb(list(publications), use_bin_type=True)


def split_status_batch(data: bytes, max_each: int) -> list[bytes]:
    """The publications of a batch (:func:`encode_status_batch`). Raises :class:`MessageError` (``malformed``) for
    a batch that is not an array of 1 to :data:`MAX_STATUS_BATCH` byte strings of at most
    ``max_each`` bytes each (``oversized``); nothing in it is authenticated yet."""
    try:
        parts = msgpack.unpackb(data, raw=False, max_array_len=MAX_STATUS_BATCH, max_bin_len=max_each,
                                max_map_len=0, max_str_len=0)
    except ValueError as exc:
        reason = "oversized" if "exceeds max_bin_len" in str(exc) else "malformed"
        raise _status_reject(reason, f"monitor batch: {exc}") from None
    except Exception as exc:
        raise _status_reject("malformed", f"malformed monitor batch: {type(exc).__name__}: {exc}") from None
    if not (isinstance(parts, list) and parts and all(isinstance(p, bytes) for p in parts)):
        raise _status_reject("malformed", f"a monitor batch is an array of 1 to {MAX_STATUS_BATCH} publications")
    return parts


def _status_mac(key: FrameKey, body: bytes) -> bytes:
    if not isinstance(key, FrameKey):
        raise ValidationError(f"a monitor message key is a dfusion.wire.FrameKey, got {type(key).__name__}")
    return hmac.new(key.derived, _STATUS_DOMAIN + body, hashlib.sha256).digest()


def _status_reject(reason: str, detail: str) -> MessageError:
    err = MessageError(detail)
    err.reason = reason
    return err


def add_tls_arguments(parser: argparse.ArgumentParser, *, directory: bool = True) -> None:
    """``--tls-ca``, ``--tls-cert``, ``--tls-key`` (and ``--tls-dir``) on a command line."""
    g = parser.add_argument_group("mutual TLS (every endpoint tls/..., every peer needs a certificate of the CA)")
    if directory:
        g.add_argument("--tls-dir", default=None, metavar="DIR",
                       help="certificates made by python -m dfusion.run.certs: DIR/ca.pem, DIR/NAME.pem and .key "
                            "(else DIR/node.pem and .key)")
    g.add_argument("--tls-ca", default=None, metavar="PEM", help="the CA certificate every peer must be signed by")
    g.add_argument("--tls-cert", default=None, metavar="PEM", help="this process's certificate")
    g.add_argument("--tls-key", default=None, metavar="PEM", help="this process's private key")


def parse_zenoh_options(items: list[str]) -> dict:
    """``PATH=JSON`` strings (``--zenoh-option``) as a ``{path: value}`` mapping (a value that
    is not JSON is taken as a string)."""
    out = {}
    for item in items:
        path, sep, value = item.partition("=")
        if not sep:
            raise ValidationError(f"--zenoh-option needs PATH=JSON, got {item!r}")
        try:
            out[path] = json.loads(value)
        except ValueError:
            out[path] = value
    return out


def security_from_args(args: argparse.Namespace) -> SecurityOptions:
    """The :class:`SecurityOptions` of parsed :func:`add_tls_arguments` (and ``--network-key-file``)."""
    return SecurityOptions(getattr(args, "network_key_file", None), getattr(args, "tls_dir", None),
                           args.tls_ca, args.tls_cert, args.tls_key)


def final_rounds(sc: Scenario) -> int:
    """Rounds of the final phase: :func:`dfusion.topology.settling_rounds` (as in ``dfusion simulate``).

    Links that change (``sc.dynamic``): no node knows the tree the rule settles on, so the
    bound for ``n`` nodes: ``n + 1`` rounds for the tree rule to settle (a new epoch floods
    at most ``n - 1`` hops, one more round for the children to name their parent, one
    for the last change a link break made) and ``settling_rounds`` of the longest tree,
    ``(n - 1) + 2``: ``2 n + 2`` (``docs/processes.md``).
    """
    if sc.dynamic:
        return 2 * len(sc.nodes) + 2
    return settling_rounds(sc.tree)


@dataclass(frozen=True)
class TreeStatus:
    """A node's view of the tree rule (links that change), in its monitor publications: its tree
    epoch ``(term, root)``, its parent (None: the root), the links it has, its tree links."""

    term: int
    root: str
    parent: str | None
    links: tuple[str, ...]
    tree_links: tuple[str, ...]

    def to_list(self) -> list:
        return [int(self.term), self.root, self.parent or "", list(self.links), list(self.tree_links)]

    @classmethod
    def from_list(cls, v: list) -> TreeStatus:
        term, root, parent, links, tree_links = v
        return cls(int(term), str(root), str(parent) or None, tuple(map(str, links)), tuple(map(str, tree_links)))


@dataclass
class Status:
    """What a node publishes for the monitor (``dfusion/NET/monitor/<node>``).

    ``phase`` is ``"ready"`` (waiting for the start), ``"run"`` (step ``k`` at
    scenario time ``t``), ``"final"`` (after the final phase: the final
    estimate) or ``"stopped"`` (stopped by a signal). ``stats`` holds the node's
    counters; a ``"run"`` publication carries them about once a second (else empty). ``output`` is the node's policy
    output (:meth:`~dfusion.fusion.node.FusionNode.output`) when its policy is not plain
    fusion: ``(source name, mean, cov)``; ``None`` otherwise.
    """

    node: str
    epoch: int
    phase: str
    k: int = -1
    t: float = 0.0
    mean: np.ndarray | None = None
    cov: np.ndarray | None = None
    started: float = 0.0
    stats: dict[str, int] = field(default_factory=dict)
    lost: list[float] = field(default_factory=list)
    output: tuple[str, np.ndarray, np.ndarray] | None = None
    tree: TreeStatus | None = None

    def encode(self, key: FrameKey | None = None) -> bytes:
        """The publication; with ``key`` it carries ``HMAC-SHA256(K, "dfusion-monitor/2" 0x00 body)``,
        ``K`` the key derived for the network and the run (:class:`dfusion.wire.FrameKey`), so a
        publication of another run or network fails authentication although the network key is
        the same."""
        body = msgpack.packb(
            {
                "node": self.node, "epoch": int(self.epoch), "phase": self.phase, "k": int(self.k),
                "t": float(self.t), "started": float(self.started),
                "mean": None if self.mean is None else np.ascontiguousarray(self.mean, "<f8").tobytes(),
                "cov": None if self.cov is None else np.ascontiguousarray(self.cov, "<f8").tobytes(),
                "stats": {k: int(v) for k, v in self.stats.items()},
                "lost": [float(x) for x in self.lost],
                "output": None if self.output is None else [
                    self.output[0], np.ascontiguousarray(self.output[1], "<f8").tobytes(),
                    np.ascontiguousarray(self.output[2], "<f8").tobytes()],
                "tree": None if self.tree is None else self.tree.to_list(),
            },
            use_bin_type=True,
        )
        mac = _status_mac(key, body) if key is not None else None
        return msgpack.packb({"v": MONITOR_VERSION, "body": body, "mac": mac}, use_bin_type=True)

    @classmethod
    def decode(cls, data: bytes, key: FrameKey | None = None, dim: int | None = None) -> Status:
        """Read and validate a publication; raises :class:`MessageError` with a ``reason``
        (``oversized``, ``malformed``, ``version``, ``unauthenticated``, ``dimension``).

        With ``key`` the MAC must match; ``dim``: the state dimension every estimate must have.
        Every field is checked for type and range (an epoch in ``(0, 2^63)``, a known phase,
        finite numbers, a symmetric covariance of the right shape).
        """
        if not isinstance(data, (bytes, bytearray)) or len(data) > MAX_STATUS_BYTES:
            raise _status_reject("oversized" if isinstance(data, (bytes, bytearray)) else "malformed",
                                 f"monitor message of {len(data) if isinstance(data, (bytes, bytearray)) else '?'} "
                                 f"bytes exceeds {MAX_STATUS_BYTES}")
        return cls.from_body(cls.authenticate(data, key), dim)

    @classmethod
    def from_body(cls, body: bytes, dim: int | None = None) -> Status:
        """The publication whose envelope :meth:`authenticate` has checked and returned ``body`` of:
        the rest of :meth:`decode` (fields, types, ranges), without a second HMAC. Raises
        :class:`MessageError` with a ``reason`` (``malformed``, ``dimension``)."""
        try:
            d = msgpack.unpackb(body, raw=False)
            mean = None if d["mean"] is None else np.frombuffer(d["mean"], "<f8").copy()
            cov = None
            if d["cov"] is not None:
                cov = np.frombuffer(d["cov"], "<f8").copy().reshape(len(mean), len(mean))
            output = None
            if d.get("output") is not None:
                name, om, oc = d["output"]
                om = np.frombuffer(om, "<f8").copy()
                output = (str(name), om, np.frombuffer(oc, "<f8").copy().reshape(len(om), len(om)))
            tree = None if d.get("tree") is None else TreeStatus.from_list(d["tree"])
            st = cls(str(d["node"]), int(d["epoch"]), str(d["phase"]), int(d["k"]), float(d["t"]), mean, cov,
                     float(d["started"]), dict(d["stats"]), list(d["lost"]), output, tree)
        except MessageError:
            raise
        except Exception as exc:
            raise _status_reject("malformed", f"malformed monitor message: {type(exc).__name__}: {exc}") from None
        st._validate(d, dim)
        return st

    @staticmethod
    def authenticate(data: bytes, key: FrameKey | None = None) -> bytes:
        """The body of publication ``data`` once its envelope (version, MAC with ``key``) is checked:
        the cheap part of :meth:`decode` (an HMAC over the body), which the monitor runs as a
        publication arrives so that forged ones never take queue space. Raises :class:`MessageError`
        with a ``reason`` (``malformed``, ``version``, ``unauthenticated``)."""
        try:
            env = msgpack.unpackb(data, raw=False)
        except Exception as exc:
            raise _status_reject("malformed", f"malformed monitor message: {type(exc).__name__}: {exc}") from None
        if not isinstance(env, dict):
            raise _status_reject("malformed", "monitor message is not a map")
        if env.get("v") != MONITOR_VERSION:
            raise _status_reject("version", f"unknown monitor message version {env.get('v')!r}")
        body = env.get("body")
        if not isinstance(body, bytes):
            raise _status_reject("malformed", "monitor message body is not bytes")
        mac = env.get("mac")
        if key is not None:
            if not (isinstance(mac, bytes) and hmac.compare_digest(mac, _status_mac(key, body))):
                raise _status_reject("unauthenticated",
                                     "monitor message not authenticated (no MAC, or a wrong key, network or run)")
        elif mac is not None:
            raise _status_reject("unauthenticated", "monitor message is authenticated but the monitor has no key")
        return body

    def _validate(self, d: dict, dim: int | None) -> None:
        """The ranges and shapes of a decoded publication (see :meth:`decode`)."""
        def bad(what: str, reason: str = "malformed") -> MessageError:
            return _status_reject(reason, f"monitor message of {self.node!r}: {what}")

        if not isinstance(d["node"], str) or not 0 < len(d["node"]) <= 256:
            raise bad("invalid node name")
        if isinstance(d["epoch"], bool) or not isinstance(d["epoch"], int) or not 0 < d["epoch"] < 2**63:
            raise bad(f"epoch {d['epoch']!r} out of range")
        if self.phase not in PHASES:
            raise bad(f"unknown phase {self.phase!r}")
        if isinstance(d["k"], bool) or not isinstance(d["k"], int) or not -1 <= d["k"] < 2**31:
            raise bad(f"step {d['k']!r} out of range")
        if not (math.isfinite(self.t) and math.isfinite(self.started)):
            raise bad("non-finite time")
        if not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
                   for k, v in self.stats.items()):
            raise bad("counters must be str: int")
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in self.lost):
            raise bad("lost times must be finite numbers")
        for what, mean, cov in (("estimate", self.mean, self.cov),
                                ("output", *(self.output[1:] if self.output is not None else (None, None)))):
            if mean is None:
                continue
            n = mean.shape[0]
            if dim is not None and n != dim:
                raise bad(f"{what} of dimension {n}, expected {dim}", "dimension")
            if cov is None or cov.shape != (n, n) or not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
                raise bad(f"{what}: a finite mean and an n x n covariance are needed")
            if not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
                raise bad(f"{what}: covariance not symmetric")


    def to_json(self) -> dict[str, Any]:
        return {
            "node": self.node, "epoch": self.epoch, "phase": self.phase, "k": self.k, "t": self.t,
            "started": self.started, "stats": self.stats, "lost": self.lost,
            "mean": None if self.mean is None else self.mean.tolist(),
            "cov": None if self.cov is None else self.cov.tolist(),
            "output": None if self.output is None else [self.output[0], self.output[1].tolist(),
                                                        self.output[2].tolist()],
            "tree": None if self.tree is None else self.tree.to_list(),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Status:
        mean = None if d.get("mean") is None else np.asarray(d["mean"], float)
        cov = None if d.get("cov") is None else np.asarray(d["cov"], float)
        out = d.get("output")
        output = None if out is None else (str(out[0]), np.asarray(out[1], float), np.asarray(out[2], float))
        tree = None if d.get("tree") is None else TreeStatus.from_list(d["tree"])
        return cls(d["node"], int(d["epoch"]), d["phase"], int(d["k"]), float(d["t"]), mean, cov,
                   float(d.get("started", 0.0)), dict(d.get("stats", {})), list(d.get("lost", [])), output, tree)
