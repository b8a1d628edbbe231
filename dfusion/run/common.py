"""What the node processes, the monitor and the launcher share.

* the network key (HMAC of fusion and monitor messages): ``--network-key-file``
  or the environment (:data:`ENV_KEY_FILE`, :data:`ENV_KEY`); a fresh random one
  per run (:func:`generate_network_key`, a file of mode 0600);
* the security options of a run (:class:`SecurityOptions`: the key file, mutual
  TLS), from the command line (:func:`add_tls_arguments`) or a scenario's
  ``[security]`` table (:func:`security_options`);
* the monitor message (msgpack; authenticated like fusion messages when a key is set);
* the number of rounds of the final phase.
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import logging
import os
import secrets
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack
import networkx as nx
import numpy as np

from dfusion.errors import MessageError, ValidationError
from dfusion.scenario.spec import Scenario

if TYPE_CHECKING:
    from dfusion.transport.zenoh import TlsFiles

log = logging.getLogger(__name__)

#: Environment variable naming a file that holds the network key.
ENV_KEY_FILE = "DFUSION_NETWORK_KEY_FILE"
#: Environment variable holding the network key itself (UTF-8 text).
ENV_KEY = "DFUSION_NETWORK_KEY"
MONITOR_VERSION = 1
#: Default wall-clock seconds a node waits for a neighbour's message of a final-phase round.
ROUND_TIMEOUT = 10.0


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


#: Keys of a scenario's ``[security]`` table, and of its ``[security.tls]`` sub-table.
SECURITY_KEYS = frozenset({"network_key_file", "tls"})
TLS_KEYS = frozenset({"dir", "ca", "cert", "key"})


@dataclass(frozen=True)
class SecurityOptions:
    """Who may take part in a run, and whether what they say is readable by others.

    Attributes
    ----------
    network_key_file : str, optional
        HMAC key of every fusion and monitor message (``dfusion run`` makes a random
        one per run when none is given).
    tls_dir : str, optional
        A directory made by ``python -m dfusion.run.certs``: ``ca.pem``, and for each
        process ``NAME.pem``/``NAME.key`` (a node's name, ``launcher``,
        ``monitor``), else the shared ``node.pem``/``node.key``.
    tls_ca, tls_cert, tls_key : str, optional
        Explicit files: the CA, and one certificate and key for every process
        (each overrides what ``tls_dir`` would give).

    TLS is on when any ``tls_*`` is set; it is then always mutual (see
    :class:`~dfusion.transport.zenoh.TlsFiles`).
    """

    network_key_file: str | None = None
    tls_dir: str | None = None
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None

    @property
    def tls(self) -> bool:
        return any((self.tls_dir, self.tls_ca, self.tls_cert, self.tls_key))

    def over(self, base: SecurityOptions) -> SecurityOptions:
        """These options, with ``base``'s (e.g. the scenario's) where these have none.

        TLS settings are taken as a whole: command-line TLS replaces the scenario's.
        """
        out = self if self.network_key_file else replace(self, network_key_file=base.network_key_file)
        if not self.tls:
            out = replace(out, tls_dir=base.tls_dir, tls_ca=base.tls_ca, tls_cert=base.tls_cert, tls_key=base.tls_key)
        return out

    def tls_files(self, name: str) -> TlsFiles | None:
        """The CA, certificate and key of process ``name`` (``None`` without TLS).

        Raises :class:`ValidationError` when TLS is on but a file is missing.
        """
        if not self.tls:
            return None
        from dfusion.transport.zenoh import TlsFiles   # Zenoh is loaded only by the processes that use it

        d = Path(self.tls_dir) if self.tls_dir else None
        ca = self.tls_ca or (str(d / "ca.pem") if d else None)
        cert, key = self.tls_cert, self.tls_key
        if d is not None and cert is None and key is None:
            own = d / f"{name}.pem", d / f"{name}.key"
            shared = d / "node.pem", d / "node.key"
            pick = own if own[0].exists() and own[1].exists() else shared
            cert, key = str(pick[0]), str(pick[1])
        missing = [what for what, v in (("CA (--tls-ca)", ca), ("certificate (--tls-cert)", cert),
                                        ("private key (--tls-key)", key)) if not v]
        if missing:
            raise ValidationError(f"TLS for {name!r} needs a {', a '.join(missing)}, or --tls-dir")
        return TlsFiles(ca, cert, key)


def security_options(table: Mapping[str, Any] | None, base_dir: str | Path | None = None) -> SecurityOptions:
    """The :class:`SecurityOptions` of a scenario's ``[security]`` table.

    ::

        [security]
        network_key_file = "secrets/network.key"   # optional
        [security.tls]                              # optional: mutual TLS
        dir = "certs"                               # made by python -m dfusion.run.certs
        # or explicit files (each overrides what dir gives):
        ca = "certs/ca.pem"
        cert = "certs/node.pem"
        key = "certs/node.key"

    Relative paths start at ``base_dir`` (the scenario file's directory). Unknown
    keys and values that are not non-empty strings raise :class:`ValidationError`
    naming the key.
    """
    if table is None:
        return SecurityOptions()
    if not isinstance(table, Mapping):
        raise ValidationError(f"[security] must be a table, got {type(table).__name__}")

    def path(where: str, value: Any) -> str:
        if not isinstance(value, str) or not value.strip():
            raise ValidationError(f"{where} must be a file or directory path (a non-empty string), got {value!r}")
        p = Path(value).expanduser()
        return str(p if p.is_absolute() or base_dir is None else Path(base_dir) / p)

    for key in table:
        if key not in SECURITY_KEYS:
            raise ValidationError(f"security.{key}: unknown key; known: {', '.join(sorted(SECURITY_KEYS))}")
    key_file = path("security.network_key_file", table["network_key_file"]) if "network_key_file" in table else None
    tls = table.get("tls")
    if tls is None:
        return SecurityOptions(network_key_file=key_file)
    if not isinstance(tls, Mapping):
        raise ValidationError(f"security.tls must be a table ([security.tls]), got {tls!r}")
    for key in tls:
        if key not in TLS_KEYS:
            raise ValidationError(f"security.tls.{key}: unknown key; known: {', '.join(sorted(TLS_KEYS))}")
    if not tls:
        raise ValidationError("security.tls is empty: give dir, or ca, cert and key")
    got = {k: path(f"security.tls.{k}", v) for k, v in tls.items()}
    return SecurityOptions(key_file, got.get("dir"), got.get("ca"), got.get("cert"), got.get("key"))


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


def security_from_args(args: argparse.Namespace) -> SecurityOptions:
    """The :class:`SecurityOptions` of parsed :func:`add_tls_arguments` (and ``--network-key-file``)."""
    return SecurityOptions(getattr(args, "network_key_file", None), getattr(args, "tls_dir", None),
                           args.tls_ca, args.tls_cert, args.tls_key)


def final_rounds(sc: Scenario) -> int:
    """Rounds of the final phase: ``diameter + 1`` (as in ``dfusion.sim.runner.final_rounds``)."""
    return (nx.diameter(sc.graph) if sc.graph.number_of_nodes() > 1 else 0) + 1


@dataclass
class Status:
    """What a node publishes for the monitor (``dfusion/NET/monitor/<node>``).

    ``phase`` is ``"ready"`` (waiting for the start), ``"run"`` (step ``k`` at
    scenario time ``t``), ``"final"`` (after the final phase: the final
    estimate) or ``"stopped"`` (stopped by a signal). ``output`` is the node's policy
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

    def encode(self, key: bytes | None = None) -> bytes:
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
            },
            use_bin_type=True,
        )
        mac = hmac.new(key, body, hashlib.sha256).digest() if key else None
        return msgpack.packb({"v": MONITOR_VERSION, "body": body, "mac": mac}, use_bin_type=True)

    @classmethod
    def decode(cls, data: bytes, key: bytes | None = None) -> Status:
        try:
            env = msgpack.unpackb(data, raw=False)
            if env.get("v") != MONITOR_VERSION:
                raise MessageError(f"unknown monitor message version {env.get('v')!r}")
            body = env["body"]
            if key and not (isinstance(env.get("mac"), bytes)
                            and hmac.compare_digest(env["mac"], hmac.new(key, body, hashlib.sha256).digest())):
                raise MessageError("monitor message not authenticated")
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
            return cls(str(d["node"]), int(d["epoch"]), str(d["phase"]), int(d["k"]), float(d["t"]), mean, cov,
                       float(d["started"]), dict(d["stats"]), list(d["lost"]), output)
        except MessageError:
            raise
        except Exception as exc:
            raise MessageError(f"malformed monitor message: {type(exc).__name__}: {exc}") from None

    def to_json(self) -> dict[str, Any]:
        return {
            "node": self.node, "epoch": self.epoch, "phase": self.phase, "k": self.k, "t": self.t,
            "started": self.started, "stats": self.stats, "lost": self.lost,
            "mean": None if self.mean is None else self.mean.tolist(),
            "cov": None if self.cov is None else self.cov.tolist(),
            "output": None if self.output is None else [self.output[0], self.output[1].tolist(),
                                                        self.output[2].tolist()],
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Status:
        mean = None if d.get("mean") is None else np.asarray(d["mean"], float)
        cov = None if d.get("cov") is None else np.asarray(d["cov"], float)
        out = d.get("output")
        output = None if out is None else (str(out[0]), np.asarray(out[1], float), np.asarray(out[2], float))
        return cls(d["node"], int(d["epoch"]), d["phase"], int(d["k"]), float(d["t"]), mean, cov,
                   float(d.get("started", 0.0)), dict(d.get("stats", {})), list(d.get("lost", [])), output)
