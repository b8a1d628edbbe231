r"""A ROS 2 participant on an open Zenoh session: subscriptions, publishers, liveliness tokens.

:class:`Ros2Link` subscribes to a node's input topics and to ``/tf_static``, and publishes its
outputs, on the keys of the chosen convention (:mod:`dfusion.ros2.keys`), with CDR payloads
(:mod:`dfusion.ros2.codec`). It declares the liveliness tokens of a ROS 2 node and of each of its
subscriptions and publishers, so ``ros2 node list`` and ``ros2 topic list`` (rmw_zenoh, or through
the bridge) show them.

Zenoh delivers samples in its own threads: the callbacks only append the raw bytes to a bounded
queue (:data:`QUEUE_LIMIT` samples and :data:`QUEUE_BYTES` bytes; the oldest are shed and counted
when the node falls behind; a sample over :data:`MAX_SAMPLE_BYTES` is refused before it is
copied), and
the node's thread decodes them in :meth:`Ros2Link.take`.

``/tf_static`` is *transient local* in ROS 2: its publishers keep their last messages for
subscriptions that come later. rmw_zenoh implements this with Zenoh's advanced publishers (a cache)
and advanced subscriptions (a history query to every publisher, also to those detected later); the
link subscribes to ``/tf_static`` the same way (``zenoh.ext.declare_advanced_subscriber`` with
``HistoryConfig(detect_late_publishers=True)``), so a node started after the robot's static
transforms were published still gets them from an rmw_zenoh publisher. Through
``zenoh-bridge-ros2dds`` only what is published after the node subscribed is certain to arrive.

Bytes that do not decode, and messages whose frame is not connected to the node's, are counted and
logged (rate-limited), never fused.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import zenoh
import zenoh.ext

from dfusion.bags.reader import stamp_ns
from dfusion.bags.tf import StaticTransforms
from dfusion.errors import ValidationError
from dfusion.ros2.codec import decode, encode
from dfusion.ros2.inputs import Reading, reading_of
from dfusion.ros2.keys import RMW_ZENOH, Convention, rmw_attachment

log = logging.getLogger(__name__)

__all__ = ["Ros2Link", "Received", "QUEUE_LIMIT", "TF_STATIC"]

#: Samples held per link between two looks of the node (the oldest are shed beyond it).
QUEUE_LIMIT = 10_000
#: Bytes held per link between two looks of the node (the oldest are shed beyond it).
QUEUE_BYTES = 64 * 1024 * 1024
#: A larger sample is refused before it is copied (a 4,000-beam float32 scan is 16 kB; an image would not fit).
MAX_SAMPLE_BYTES = 4 * 1024 * 1024
TF_STATIC = ("/tf_static", "tf2_msgs/msg/TFMessage")
#: Seconds between two log lines about refused input messages.
LOG_PERIOD = 5.0


@dataclass(frozen=True)
class Received:
    """An input message taken by the node: its topic, header stamp (ns) and :class:`Reading`."""

    topic: str
    stamp_ns: int
    reading: Reading


class Ros2Link:
    """ROS 2 in and out for one node over ``session`` (see the module docstring).

    Parameters
    ----------
    session : zenoh.Session
    convention : Convention
    ros_node : str
        The ROS 2 node name announced (``ros2 node list``).
    frame : str
        The node's frame: input poses are expressed in it, outputs are stamped with it.
    inputs : mapping topic -> message type
    outputs : mapping topic -> message type
    converters : mapping topic -> ``f(msg, stamp_s) -> z or None``, optional
        User functions for inputs of other types, or another ``z`` (a camera's pixel, a WSN's
        RSSI vector); ``stamp_s`` is the header stamp in seconds since the epoch, ``None`` skips
        the message (counted). Their ``z`` is taken as it is (no frame change, the node's noise).
    """

    def __init__(self, session: Any, convention: Convention, ros_node: str, frame: str,
                 inputs: dict[str, str], outputs: dict[str, str],
                 converters: dict[str, Callable[[Any, float], Any]] | None = None) -> None:
        self.session, self.convention, self.ros_node, self.frame = session, convention, ros_node, frame
        self.inputs, self.outputs = dict(inputs), dict(outputs)
        self.converters = dict(converters or {})
        self.tf = StaticTransforms()
        self.counters = {"received": 0, "decode_errors": 0, "frame_errors": 0, "converter_errors": 0,
                         "skipped": 0, "shed": 0, "oversized": 0, "published": 0, "tf_static": 0}
        self._queue: deque[tuple[str, bytes]] = deque()
        self._bytes = 0
        self._lock = threading.Lock()
        self._last_log = 0.0
        self._seq = 0
        self._gid = os.urandom(16)
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._tokens: list[Any] = []
        zid = str(session.info.zid())
        self.session_id = zid
        try:
            tok = convention.node_token(zid, ros_node)
            if tok is not None:
                self._tokens.append(session.liveliness().declare_token(tok))
            entity = 1
            for topic, msgtype in [*self.inputs.items(), TF_STATIC]:
                key = convention.data_key(topic, msgtype)
                if topic == TF_STATIC[0]:   # transient local: also the samples published before we came
                    self._subs.append(zenoh.ext.declare_advanced_subscriber(
                        session, key, self._callback(topic),
                        history=zenoh.ext.HistoryConfig(detect_late_publishers=True)))
                else:
                    self._subs.append(session.declare_subscriber(key, self._callback(topic)))
                self._tokens.append(session.liveliness().declare_token(
                    convention.entity_token("MS", zid, ros_node, topic, msgtype, entity_id=entity)))
                entity += 1
            for topic, msgtype in self.outputs.items():
                self._pubs[topic] = session.declare_publisher(convention.data_key(topic, msgtype))
                self._tokens.append(session.liveliness().declare_token(
                    convention.entity_token("MP", zid, ros_node, topic, msgtype, entity_id=entity)))
                entity += 1
        except BaseException:
            self.close()
            raise

    def _callback(self, topic: str) -> Callable[[Any], None]:
        def on_sample(sample: Any) -> None:   # a Zenoh thread: keep it short
            if len(sample.payload) > MAX_SAMPLE_BYTES:   # before copying it
                with self._lock:
                    self.counters["oversized"] += 1
                return
            data = sample.payload.to_bytes()
            with self._lock:
                while self._queue and (len(self._queue) >= QUEUE_LIMIT or self._bytes + len(data) > QUEUE_BYTES):
                    self._bytes -= len(self._queue.popleft()[1])
                    self.counters["shed"] += 1
                self._queue.append((topic, data))
                self._bytes += len(data)
        return on_sample

    def _refused(self, what: str, exc: Exception) -> None:
        self.counters[what] += 1
        now = time.monotonic()
        if now - self._last_log >= LOG_PERIOD:
            self._last_log = now
            log.warning("%s: input refused (%s): %s (so far: decode errors %d, frame errors %d, converter errors %d)",
                        self.ros_node, what, exc, self.counters["decode_errors"], self.counters["frame_errors"],
                        self.counters["converter_errors"])

    def take(self) -> list[Received]:
        """The input messages that arrived since the last call, decoded, in arrival order
        (``/tf_static`` messages update :attr:`tf` and are not returned)."""
        with self._lock:
            items = list(self._queue)
            self._queue.clear()
            self._bytes = 0
        out: list[Received] = []
        for topic, data in items:
            if topic == TF_STATIC[0]:
                try:
                    self.counters["tf_static"] += self.tf.add_message(decode(data, TF_STATIC[1]))
                except ValidationError as exc:
                    self._refused("decode_errors", exc)
                continue
            msgtype = self.inputs[topic]
            try:
                msg = decode(data, msgtype)
                ns = stamp_ns(msg)
                if ns is None:
                    raise ValidationError(f"a {msgtype} on {topic} has no header stamp")
            except (ValidationError, AttributeError) as exc:
                self._refused("decode_errors", exc)
                continue
            fn = self.converters.get(topic)
            if fn is not None:
                try:
                    z = fn(msg, ns * 1e-9)
                    if z is None:
                        self.counters["skipped"] += 1
                        continue
                    z = np.atleast_1d(np.asarray(z, dtype=float))
                    if z.ndim != 1 or not np.all(np.isfinite(z)):
                        raise ValueError(f"z must be a finite vector, got shape {z.shape}")
                except Exception as exc:   # a user function: whatever it raises is its message's fault
                    self._refused("converter_errors", exc)
                    continue
                self.counters["received"] += 1
                out.append(Received(topic, ns, Reading(z, None, str(getattr(msg.header, "frame_id", "")))))
                continue
            try:
                reading = reading_of(msgtype, msg, self.frame, self.tf)
            except ValidationError as exc:
                self._refused("frame_errors", exc)
                continue
            self.counters["received"] += 1
            out.append(Received(topic, ns, reading))
        return out

    def publish(self, topic: str, msg: Any) -> None:
        """Publish ``msg`` on output ``topic`` (rmw_zenoh: with its attachment)."""
        data = encode(msg)
        self._seq += 1
        if self.convention.kind == RMW_ZENOH:
            self._pubs[topic].put(data, attachment=rmw_attachment(self._seq, time.time_ns(), self._gid))
        else:
            self._pubs[topic].put(data)
        self.counters["published"] += 1

    def close(self) -> None:
        """Undeclare everything (tokens first, so ROS 2 tools see the node go at once)."""
        for ent in [*self._tokens, *self._subs, *self._pubs.values()]:
            try:
                ent.undeclare()
            except Exception as exc:   # the session may be closed already
                log.debug("undeclare: %s", exc)
        self._tokens, self._subs, self._pubs = [], [], {}
