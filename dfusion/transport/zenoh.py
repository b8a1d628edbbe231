"""Fusion messages over Zenoh: one key expression per directed link, liveliness per node.

Key space of a network called ``NET`` (node names are Zenoh key chunks)::

    dfusion/NET/<src>/<dst>        fusion messages of the directed link src -> dst
    dfusion/NET/alive/<name>       liveliness token of each running node
    dfusion/NET/monitor/<name>     estimates published for the monitor (dfusion.run)
    dfusion/NET/monitor/<name>/batch  several nodes' estimates at once (a host process, first node <name>)

A :class:`ZenohTransport` serves the nodes that run in its process (usually
one). It opens one Zenoh session in **peer** mode, configured by
:class:`ZenohConfig`: by default it listens on loopback only
(``tcp/127.0.0.1:0``) with multicast and gossip scouting off, so nothing leaves
the machine and nothing is discovered by accident. To reach other hosts, give
explicit ``listen`` and ``connect`` endpoints (each node connects to its
neighbours' endpoints: peer mode delivers only over direct links), or connect
every node to a Zenoh router (``mode="client"`` or a router endpoint in
``connect``); see ``docs/zenoh.md``.

Pitfalls handled here (measured in this project; ``docs/background.md#7-zenoh-what-can-silently-lose-data-or-hang``):

* Subscribers are callback subscribers that only append to this object's
  deques (never block); :meth:`ZenohTransport.receive` drains them.
* **Cheap checks before queueing.** A local node may register a check
  (:meth:`ZenohTransport.set_check`, in practice :meth:`dfusion.fusion.FusionNode.check_frame`:
  size, header, checksum and MAC, a few microseconds). The callback runs it on every copy
  that arrives and drops a failing one at once, counted by reason
  (:meth:`ZenohTransport.take_rejections`): garbage and forged traffic never take queue
  space, never push genuine messages out of a full queue (:data:`MAX_QUEUE` copies and
  :data:`MAX_QUEUE_BYTES` bytes per local node, oldest dropped first, counted:
  :meth:`ZenohTransport.queue_report`) and are never counted as delivered. The size is checked
  before the payload is copied. A copy that passed is delivered with ``Delivery.checked`` set,
  so that the node does not compute its checksum and MAC a second time
  (``FusionNode.receive(data, checked=True)``).
* The session is always closed: :meth:`ZenohTransport.close` (idempotent), the context
  manager, and every user of this class closes it in ``finally`` (an open
  session with callback subscribers keeps the process from exiting).
* ``transport/unicast/open_timeout`` is 1000 ms, so :meth:`ZenohTransport.close` does not
  block for seconds when a reconnection is in flight; and :meth:`ZenohTransport.close` gives
  up after :data:`CLOSE_TIMEOUT` seconds when messages are queued towards a
  frozen peer (Zenoh would block about 10 s; see :func:`close_session`).
* The lowlatency transport is refused (it drops payloads over 49,144 bytes).
* Publications use ``CongestionControl.DROP``: ``send`` never blocks. A message
  published while a link is down is lost (Zenoh does not buffer); the fusion
  protocol tolerates that (the next message carries the same window).

Liveliness: each local node declares ``dfusion/NET/alive/<name>``; one
liveliness subscriber (``history=True``) follows the local nodes' and their neighbours'
tokens (other names are ignored as they arrive). Loss of a
neighbour is logged with ``logging.warning`` (``info`` once
:attr:`ZenohTransport.quiet_loss` is set, e.g. at a normal end of run), its
return with ``info``, at most one line of each per neighbour a second
(:class:`~dfusion.transport.base.LineBudget`), and both are exposed through :meth:`ZenohTransport.alive`
and callbacks registered with :meth:`ZenohTransport.on_liveliness` (called in
the thread that calls :meth:`ZenohTransport.receive` or :meth:`ZenohTransport.poll`, never in Zenoh's).
"""
from __future__ import annotations

import json
import logging
import math
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import zenoh

from dfusion.errors import MessageError, ValidationError
from dfusion.transport.base import (
    Delivery,
    LineBudget,
    LinkKey,
    StatsReport,
    Transport,
    TransportStats,
)

log = logging.getLogger(__name__)

KEY_ROOT = "dfusion"
#: Key chunks with a meaning of their own: not allowed as node names.
RESERVED_NAMES = frozenset({"alive", "monitor", "control"})
_BAD_CHARS = frozenset("/*$?#@ \t\n\r")
#: Copies waiting per local node before the oldest are discarded (counted as dropped).
MAX_QUEUE = 10_000
#: Bytes of copies waiting per local node before the oldest are discarded (counted as dropped and
#: in :meth:`ZenohTransport.queue_report`): 16 full windows of a 400-time window of a 4-state model
#: are about 3 MB; a flood of genuine-looking copies costs at most this much memory per node.
MAX_QUEUE_BYTES = 64 * 1024 * 1024
_T_SENT = struct.Struct("<d")


def check_name(name: str, what: str = "node name") -> str:
    """Return ``name`` if it can be one key chunk, else raise :class:`ValidationError`."""
    if not isinstance(name, str) or not name or _BAD_CHARS & set(name) or name in RESERVED_NAMES:
        raise ValidationError(
            f"invalid {what} {name!r}: must be a non-empty key chunk without / * $ ? # @ or blanks, "
            f"and not one of {sorted(RESERVED_NAMES)}"
        )
    return name


def link_key(network: str, src: str, dst: str) -> str:
    """Key expression of the directed link ``src -> dst``."""
    return f"{KEY_ROOT}/{network}/{src}/{dst}"


def alive_key(network: str, name: str = "*") -> str:
    """Key expression of a node's liveliness token (``*``: every node)."""
    return f"{KEY_ROOT}/{network}/alive/{name}"


def monitor_key(network: str, name: str = "*") -> str:
    """Key expression on which a node publishes its estimates for the monitor."""
    return f"{KEY_ROOT}/{network}/monitor/{name}"


def monitor_batch_key(network: str, name: str = "*") -> str:
    """Key expression of a host process's batches of its nodes' publications for the monitor,
    ``name`` the first node of the batch (``dfusion.run.common.encode_status_batch``)."""
    return f"{KEY_ROOT}/{network}/monitor/{name}/batch"


def free_tcp_endpoints(count: int, host: str = "127.0.0.1", scheme: str = "tcp") -> list[str]:
    """``count`` endpoints ``SCHEME/HOST:PORT`` on TCP ports that were free a moment ago.

    ``scheme`` is ``tcp`` or ``tls`` (TLS runs over TCP). The ports are found by
    binding to port 0; another program may take one before Zenoh binds it
    (unlikely on a test machine).
    """
    if scheme not in ("tcp", "tls"):
        raise ValidationError(f"scheme must be tcp or tls, got {scheme!r}")
    socks = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind((host, 0))
            socks.append(s)
        return [f"{scheme}/{host}:{s.getsockname()[1]}" for s in socks]
    finally:
        for s in socks:
            s.close()


#: Zenoh configuration path of the TLS settings (zenoh 1.x).
TLS_PATH = "transport/link/tls"


@dataclass(frozen=True)
class TlsFiles:
    """Mutual TLS for one Zenoh session: the CA that signs every member, this session's
    certificate and private key (PEM files).

    The same certificate serves both sides of a link: as a server certificate on
    the session's ``tls/`` listen endpoints and as a client certificate on its
    ``tls/`` connections. ``enable_mtls`` is always on: a listener then refuses any
    peer that does not present a certificate signed by ``ca``. Without it, anyone
    holding the (public) CA certificate could connect and read everything
    (measured: ``tests/transport/test_zenoh.py::test_mutual_tls_refuses_strangers``).
    """

    ca: str
    cert: str
    key: str

    def __post_init__(self) -> None:
        for what in ("ca", "cert", "key"):
            path = getattr(self, what)
            if not isinstance(path, str) or not path:
                raise ValidationError(f"TLS {what} must be a file path, got {path!r}")
            try:
                with open(path, "rb") as f:
                    head = f.read(4096)
            except OSError as exc:
                raise ValidationError(f"TLS {what} file {path!r}: {exc.strerror or exc}") from None
            if b"-----BEGIN " not in head:
                raise ValidationError(f"TLS {what} file {path!r} is not PEM")

    def zenoh_values(self) -> dict[str, Any]:
        """The ``transport/link/tls/...`` configuration values."""
        return {
            f"{TLS_PATH}/root_ca_certificate": self.ca,
            f"{TLS_PATH}/listen_certificate": self.cert,
            f"{TLS_PATH}/listen_private_key": self.key,
            f"{TLS_PATH}/connect_certificate": self.cert,
            f"{TLS_PATH}/connect_private_key": self.key,
            f"{TLS_PATH}/enable_mtls": True,
        }


@dataclass(frozen=True)
class ZenohConfig:
    """How a dfusion process opens its Zenoh session.

    Attributes
    ----------
    mode : {"peer", "client", "router"}
        ``"peer"`` (default): direct links to the configured endpoints only.
        ``"client"``: everything goes through the router(s) in ``connect``.
    listen : sequence of str
        Endpoints to listen on; empty means ``tcp/127.0.0.1:0`` (loopback, a
        free port) in peer mode and nothing in client mode.
    connect : sequence of str
        Endpoints (neighbours, routers) to connect to; retried in the background
        every ``retry_period_ms`` (backing off to ``retry_max_ms``) until they answer,
        and again after a link is lost.
    multicast_scouting, gossip_scouting : bool
        Off by default: peers only know the endpoints they are given.
    open_timeout_ms : int
        ``transport/unicast/open_timeout``; low so that ``close()`` never hangs.
    lease_ms : int
        ``transport/link/tx/lease``: a frozen peer is declared gone after this.
        A killed one is detected at once (its TCP connection resets).
    extra : mapping
        Further configuration paths and JSON values, e.g.
        ``{"transport/link/tx/lease": 2000}``.
    tls : TlsFiles, optional
        Mutual TLS: every endpoint must then be a ``tls/`` one (the default
        listen endpoint becomes ``tls/127.0.0.1:0``), so nothing travels in clear
        and only holders of a certificate signed by the CA can connect.
    client_wait_ms : int
        Client mode: how long opening the session waits for a router in ``connect`` to answer
        (``connect/timeout_ms``; Zenoh's default for clients, 0, fails at once when the router
        is not up yet, e.g. started a moment later or restarting).
    report_endpoints : bool
        Turn on the session's admin space (read only) so that the session can tell
        which port the kernel gave a ``:0`` listen endpoint
        (:func:`dfusion.run.endpoints.bound_endpoints`). Off by default: a connected
        peer may then read the session's locators and configuration (no key: keys
        live in files), not write them.
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    gossip_scouting: bool = False
    open_timeout_ms: int = 1000
    lease_ms: int = 3000
    retry_period_ms: int = 200
    retry_max_ms: int = 500
    extra: Mapping[str, Any] = field(default_factory=dict)
    tls: TlsFiles | None = None
    report_endpoints: bool = False
    client_wait_ms: int = 10000

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise ValidationError(f"zenoh mode must be peer, client or router, got {self.mode!r}")
        object.__setattr__(self, "listen", tuple(self.listen))
        object.__setattr__(self, "connect", tuple(self.connect))
        for ep in self.listen + self.connect:
            if not isinstance(ep, str) or "/" not in ep:
                raise ValidationError(f"a zenoh endpoint looks like tcp/HOST:PORT, got {ep!r}")
        if self.extra.get("transport/unicast/lowlatency") not in (None, False):
            raise ValidationError("the lowlatency transport silently drops payloads over 49,144 bytes: not allowed")
        if self.mode == "client" and not self.connect:
            raise ValidationError("client mode needs at least one router endpoint in connect")
        if self.tls is not None:
            if not isinstance(self.tls, TlsFiles):
                raise ValidationError(f"tls must be a TlsFiles, got {type(self.tls).__name__}")
            clear = [ep for ep in self.listen + self.connect if not ep.startswith("tls/")]
            if clear:
                raise ValidationError(f"with TLS every endpoint must be tls/HOST:PORT (nothing in clear), got {clear}")
            overridden = sorted(k for k in self.extra if k.startswith(TLS_PATH + "/"))
            if overridden:
                raise ValidationError(f"TLS settings are given by tls=TlsFiles(...), not extra: {overridden}")

    def to_zenoh(self) -> zenoh.Config:
        """The ``zenoh.Config`` these settings describe."""
        default = "tls/127.0.0.1:0" if self.tls is not None else "tcp/127.0.0.1:0"
        listen = list(self.listen) or ([default] if self.mode != "client" else [])
        values: dict[str, Any] = {
            "mode": self.mode,
            "listen/endpoints": listen,
            "connect/endpoints": list(self.connect),
            "connect/exit_on_failure": False,
            "connect/retry": {"period_init_ms": self.retry_period_ms, "period_max_ms": self.retry_max_ms,
                              "period_increase_factor": 2},
            "scouting/multicast/enabled": self.multicast_scouting,
            "scouting/gossip/enabled": self.gossip_scouting,
            "scouting/delay": 0,
            "transport/unicast/open_timeout": self.open_timeout_ms,
            "transport/unicast/lowlatency": False,
            "transport/link/tx/lease": self.lease_ms,
            # express messages are one batch each: the default queue of 2 batches lost
            # 1-20% of 7 kB messages at 900 msg/s on loopback; 16 lost none
            "transport/link/tx/queue/size/data": 16,
        }
        if self.mode == "client":
            values["connect/timeout_ms"] = self.client_wait_ms
        if self.tls is not None:
            values.update(self.tls.zenoh_values())
        if self.report_endpoints:
            values["adminspace/enabled"] = True
            values["adminspace/permissions"] = {"read": True, "write": False}
        values.update(self.extra)
        cfg = zenoh.Config()
        for path, value in values.items():
            cfg.insert_json5(path, json.dumps(value))
        return cfg

    def with_endpoints(self, listen: Iterable[str] = (), connect: Iterable[str] = ()) -> ZenohConfig:
        """A copy with other endpoints."""
        return replace(self, listen=tuple(listen), connect=tuple(connect), extra=dict(self.extra))


def open_session(config: ZenohConfig | None = None) -> zenoh.Session:
    """Open a Zenoh session with ``config`` (loopback defaults). Close it with :func:`close_session`."""
    return zenoh.open((config or ZenohConfig()).to_zenoh())


#: Seconds :func:`close_session` waits for ``Session.close()``.
CLOSE_TIMEOUT = 1.0


def close_session(session: zenoh.Session, timeout: float = CLOSE_TIMEOUT) -> bool:
    """Close ``session``, waiting at most ``timeout`` seconds; True if the close finished.

    ``Session.close()`` blocks for about 10 s when messages are still queued
    towards a frozen peer (SIGSTOPped, or a hung host), whatever
    ``open_timeout``, the lease or the congestion settings (measured with
    zenoh 1.10.2). The close therefore runs in a daemon thread; if it does not
    finish in time it is abandoned with a warning, and the process can still
    exit at once (measured: exit 0 about 1.1 s after the close began).
    """
    errors: list[BaseException] = []

    def run() -> None:
        try:
            session.close()
        except Exception as exc:  # already closed
            errors.append(exc)

    th = threading.Thread(target=run, name="zenoh-close", daemon=True)
    th.start()
    th.join(timeout)
    if th.is_alive():
        log.warning("zenoh session close still blocked after %.1f s (a peer is frozen with messages queued "
                    "towards it): abandoned", timeout)
        return False
    if errors:
        log.debug("zenoh close: %s", errors[0])
    return True


class ZenohTransport(Transport):
    """:class:`Transport` over Zenoh for the nodes of this process.

    Parameters
    ----------
    network : str
        Name of the network (one key chunk); nodes of different networks never
        see each other's messages.
    nodes : mapping
        ``{local node: its neighbours}`` for every node run by this process.
    config : ZenohConfig, optional
        Session settings (default: loopback only, a free port).
    clock : callable, optional
        Returns the local time used to stamp arrivals (``Delivery.t_arrival``)
        and compared with ``until`` in :meth:`receive`; ``time.monotonic`` by
        default (the node program passes its scenario clock).
    express : bool
        Publish fusion messages without batching (lower latency). Default true.
    session : zenoh.Session, optional
        Use an existing session instead of opening one (it is then not closed
        by :meth:`close`).

    ``send`` never blocks and never raises for a lost message; ``receive``
    returns the copies that arrived for a local node. See the module docstring.
    """

    def __init__(
        self,
        network: str,
        nodes: Mapping[str, Iterable[str]],
        config: ZenohConfig | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        express: bool = True,
        session: zenoh.Session | None = None,
    ) -> None:
        self.network = check_name(network, "network name")
        self.neighbors: dict[str, tuple[str, ...]] = {}
        for name, nbrs in nodes.items():
            nb = tuple(check_name(n) for n in nbrs)
            if check_name(name) in nb or len(set(nb)) != len(nb):
                raise ValidationError(f"invalid neighbours of {name!r}: {nb}")
            self.neighbors[name] = nb
        if not self.neighbors:
            raise ValidationError("a ZenohTransport needs at least one local node")
        self.config = config or ZenohConfig()
        self.clock = clock
        self.quiet_loss = False
        self._lock = threading.Lock()
        self._event = threading.Event()
        self._queues: dict[str, deque[Delivery]] = {n: deque() for n in self.neighbors}
        #: per local node: [bytes queued now, peak bytes, copies shed, bytes shed]
        self._queue_bytes: dict[str, list[int]] = {n: [0, 0, 0, 0] for n in self.neighbors}
        self._stats: dict[LinkKey, TransportStats] = {}
        for name, nbrs in self.neighbors.items():
            for nb in nbrs:
                self._stats[(name, nb)] = TransportStats()
                self._stats[(nb, name)] = TransportStats()
        self._checks: dict[str, Callable[[bytes], object]] = {}
        self._max_bytes: dict[str, int] = {}
        self._rejected: dict[str, dict[str, int]] = {n: {} for n in self.neighbors}
        self._rejected_detail: dict[str, str] = {}
        self._alive: dict[str, bool] = {}
        #: the names whose liveliness is followed: the local nodes and their neighbours
        self._followed = frozenset(self.neighbors) | {nb for nbs in self.neighbors.values() for nb in nbs}
        self._alive_events: deque[tuple[str, bool]] = deque()
        #: at most one log line per neighbour's loss, one per return (and its first appearance) a second (``log_budget.held_back``: the rest)
        self.log_budget = LineBudget()
        self._callbacks: list[Callable[[str, bool], None]] = []
        self._publishers: dict[LinkKey, Any] = {}
        self._declared: list[Any] = []
        self._closed = False
        self._own_session = session is None
        self._session = open_session(self.config) if session is None else session
        try:
            z = self._session
            for name, nbrs in self.neighbors.items():
                for nb in nbrs:
                    self._declared.append(
                        z.declare_subscriber(link_key(self.network, nb, name), self._make_callback(nb, name)))
                    self._publishers[(name, nb)] = z.declare_publisher(
                        link_key(self.network, name, nb),
                        congestion_control=zenoh.CongestionControl.DROP,
                        reliability=zenoh.Reliability.RELIABLE,
                        priority=zenoh.Priority.DATA,
                        express=express,
                    )
            self._declared.append(z.liveliness().declare_subscriber(alive_key(self.network), self._on_liveliness,
                                                                     history=True))
            self._tokens = [z.liveliness().declare_token(alive_key(self.network, name)) for name in self.neighbors]
        except BaseException:
            self.close()
            raise
        log.debug("zenoh transport %s: nodes %s, config %s", self.network, list(self.neighbors), self.config)

    # ------------------------------------------------------------------ zenoh callbacks (never block)
    def _make_callback(self, src: str, dst: str) -> Callable[[zenoh.Sample], None]:
        queue = self._queues[dst]
        qbytes = self._queue_bytes[dst]
        stats = self._stats[(src, dst)]
        clock, event, lock = self.clock, self._event, self._lock
        checks, max_bytes, reject, all_stats = self._checks, self._max_bytes, self._reject, self._stats

        def on_sample(sample: zenoh.Sample) -> None:
            check = checks.get(dst)
            if check is not None:
                limit = max_bytes.get(dst)
                if limit is not None and len(sample.payload) > limit:   # before copying it
                    reject(dst, "oversized", f"message of {len(sample.payload)} bytes exceeds the limit of {limit}")
                    return
                data = sample.payload.to_bytes()
                checked = True
                try:
                    check(data)
                except MessageError as exc:
                    reject(dst, getattr(exc, "reason", "malformed"), str(exc))
                    return
                except Exception as exc:   # a defect of the check: the copy is still dropped, never fatal here
                    reject(dst, "internal", f"check failed: {type(exc).__name__}: {exc}")
                    return
            else:
                data, checked = sample.payload.to_bytes(), False
            att = sample.attachment
            t_sent = math.nan
            if att is not None:
                raw = att.to_bytes()
                if len(raw) == _T_SENT.size:
                    t_sent = _T_SENT.unpack(raw)[0]
            with lock:
                while queue and (len(queue) >= MAX_QUEUE or qbytes[0] + len(data) > MAX_QUEUE_BYTES):
                    old = queue.popleft()
                    qbytes[0] -= len(old.data)
                    qbytes[2] += 1
                    qbytes[3] += len(old.data)
                    all_stats[(old.src, old.dst)].dropped += 1
                queue.append(Delivery(clock(), src, dst, data, t_sent, checked))
                qbytes[0] += len(data)
                qbytes[1] = max(qbytes[1], qbytes[0])
            event.set()

        return on_sample

    def _reject(self, dst: str, reason: str, detail: str) -> None:
        """Count a copy for ``dst`` that failed its check (called in Zenoh's threads)."""
        with self._lock:
            counts = self._rejected[dst]
            counts[reason] = counts.get(reason, 0) + 1
            self._rejected_detail[dst] = detail
        # no wake-up: a flood must not spin the node's loop; the counts are taken at its next receive

    def set_check(self, node: str, check: Callable[[bytes], object] | None, max_bytes: int | None = None) -> None:
        """Run ``check(data)`` on every copy for local ``node`` as it arrives, in Zenoh's callback.

        A copy for which it raises :class:`~dfusion.errors.MessageError` is dropped and counted
        by the error's ``reason`` (:meth:`take_rejections`); it is not queued and not delivered.
        A copy longer than ``max_bytes`` is rejected (``oversized``) before its payload is
        copied. ``check`` must be cheap and thread-safe (it runs in Zenoh's threads, while the
        node's thread works): :meth:`dfusion.fusion.FusionNode.check_frame` is. ``None`` removes it.
        """
        if node not in self._queues:
            raise ValidationError(f"{node!r} is not a node of this transport")
        if check is None:
            self._checks.pop(node, None)
            self._max_bytes.pop(node, None)
            return
        if max_bytes is not None:
            self._max_bytes[node] = int(max_bytes)
        self._checks[node] = check

    def take_rejections(self, node: str) -> tuple[dict[str, int], str]:
        """The copies for ``node`` rejected by its check since the last call: ``({reason: count},
        the last one's detail)``; the counts are reset."""
        with self._lock:
            counts = self._rejected[node]
            if not counts:
                return {}, ""
            self._rejected[node] = {}
            return counts, self._rejected_detail.pop(node, "")

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name not in self._followed:   # tokens of other names take no memory (a flood of them is ignored)
            return
        self._alive_events.append((name, sample.kind == zenoh.SampleKind.PUT))
        self._event.set()

    # ------------------------------------------------------------------ Transport
    def send(self, src: str, dst: str, data: bytes, t: float) -> None:
        """Publish ``data`` on ``dfusion/NET/src/dst`` (``t`` travels as an attachment)."""
        pub = self._publishers.get((src, dst))
        if pub is None:
            if self._closed:
                return
            raise ValidationError(f"there is no local link {src!r} -> {dst!r}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise ValidationError(f"data must be bytes, got {type(data).__name__}")
        payload = bytes(data)
        stats = self._stats[(src, dst)]
        stats.sent += 1
        stats.bytes_sent += len(payload)
        try:
            pub.put(payload, attachment=_T_SENT.pack(float(t)))
        except zenoh.ZError as exc:   # session closing: a lost message, as documented
            stats.dropped += 1
            log.debug("send %s -> %s failed: %s", src, dst, exc)

    def receive(self, node: str, until: float = math.inf) -> list[Delivery]:
        """Remove and return the copies for local ``node`` stamped at or before ``until``."""
        queue = self._queues.get(node)
        if queue is None:
            raise ValidationError(f"{node!r} is not a node of this transport")
        self.poll()
        out: list[Delivery] = []
        qbytes = self._queue_bytes[node]
        while queue and queue[0].t_arrival <= until:
            with self._lock:
                d = queue.popleft()
                qbytes[0] -= len(d.data)
            st = self._stats[(d.src, d.dst)]
            st.delivered += 1
            st.bytes_delivered += len(d.data)
            out.append(d)
        return out

    def pending(self, node: str | None = None) -> int:
        """Copies waiting in the local queues."""
        if node is None:
            return sum(len(q) for q in self._queues.values())
        return len(self._queues[node])

    def wait(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds until a message or liveliness change is waiting."""
        if self.pending() or self._alive_events:
            return True
        self._event.wait(max(0.0, timeout))
        self._event.clear()
        return bool(self.pending() or self._alive_events)

    def wake(self) -> None:
        """Make a pending or the next :meth:`wait` return at once (thread-safe)."""
        self._event.set()

    @property
    def stats(self) -> StatsReport:
        """Per directed link: ``sent``/``bytes_sent`` on outgoing links, ``delivered`` on incoming ones.

        A process only sees its own side: messages lost in transit are not
        counted here (``dropped`` counts local queue overflows and failed puts).
        """
        return StatsReport.from_links(self._stats)

    def queue_report(self, node: str) -> dict[str, int]:
        """Local ``node``'s receive queue: ``queued_bytes`` now, ``peak_bytes``, and the copies (and
        bytes) shed because more than :data:`MAX_QUEUE` copies or :data:`MAX_QUEUE_BYTES` bytes waited."""
        now, peak, shed, shed_bytes = self._queue_bytes[node]
        return {"queued_bytes": now, "peak_bytes": peak, "shed": shed, "shed_bytes": shed_bytes}

    def node_totals(self, node: str) -> TransportStats:
        """One local node's side: ``sent``/``bytes_sent`` summed over its outgoing links,
        ``delivered``/``bytes_delivered`` over its incoming ones (no copy of every link)."""
        out = TransportStats()
        for nb in self.neighbors[node]:
            o, i = self._stats[(node, nb)], self._stats[(nb, node)]
            out.sent += o.sent
            out.bytes_sent += o.bytes_sent
            out.dropped += o.dropped + i.dropped
            out.delivered += i.delivered
            out.bytes_delivered += i.bytes_delivered
        return out

    # ------------------------------------------------------------------ liveliness
    def poll(self) -> list[tuple[str, bool]]:
        """Apply pending liveliness changes, log them and call the callbacks; returns them."""
        changes = []
        while self._alive_events:
            name, up = self._alive_events.popleft()
            was = self._alive.get(name)
            self._alive[name] = up
            if was == up:
                continue
            changes.append((name, up))
            mine = [n for n, nb in self.neighbors.items() if name in nb]
            what = ("back" if was is False else "up") if up else "lost"
            write, held = self.log_budget.allow(f"{name}:{what}") if mine else (False, 0)
            if write:
                if up:
                    log.info("%s: neighbour %s is %s%s", ",".join(mine), name, what, LineBudget.suffix(held))
                else:
                    level = logging.INFO if self.quiet_loss else logging.WARNING
                    log.log(level, "%s: neighbour %s lost (liveliness token gone)%s", ",".join(mine), name,
                            LineBudget.suffix(held))
            for cb in list(self._callbacks):
                try:
                    cb(name, up)
                except Exception:  # a callback must not break the transport
                    log.exception("liveliness callback failed")
        return changes

    def alive(self, name: str) -> bool:
        """Whether ``name``'s liveliness token is currently seen."""
        self.poll()
        return self._alive.get(name, False)

    def alive_nodes(self) -> set[str]:
        """Every followed node (the local ones and their neighbours) whose token is currently seen."""
        self.poll()
        return {n for n, up in self._alive.items() if up}

    def on_liveliness(self, callback: Callable[[str, bool], None]) -> None:
        """Call ``callback(name, alive)`` on every change (from :meth:`poll`/:meth:`receive`)."""
        self._callbacks.append(callback)

    # ------------------------------------------------------------------ session
    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session (to declare more publishers, e.g. for the monitor)."""
        return self._session

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent, never hangs for long)."""
        if self._closed:
            return
        self._closed = True
        self._publishers.clear()
        if self._own_session:
            close_session(self._session)
        else:
            for ent in getattr(self, "_tokens", []) + self._declared:
                try:
                    ent.undeclare()
                except Exception as exc:
                    log.debug("zenoh undeclare: %s", exc)
        self._event.set()

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"ZenohTransport({self.network!r}, nodes={list(self.neighbors)}, mode={self.config.mode!r})"
