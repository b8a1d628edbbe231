r"""The track bundle: what one multi-target node sends one neighbour at a time.

A :class:`~dfusion.fusion.tracking_node.TrackingNode` keeps one
:class:`~dfusion.fusion.node.FusionNode` per track (its delayed-state filter and its channel
filter per link). What it sends a neighbour is every track's fusion message for that
neighbour, each tagged with the track's identity and birth time, and the ends of tracks
(deletions and merges) the neighbour has to hear about::

    frame  = b"DT" | version (1 byte, 1) | flags (1 byte: KEYED) | body | crc32 | mac (keyed)
    body   = msgpack array [src, dst, epoch, sent_at, tracks, ended]
    tracks = [[origin, serial, born, message], ...]       message: a fusion frame (dfusion.wire), unkeyed
    ended  = [[origin, serial, into_origin, into_serial, into_born, at], ...]   into_origin "": deleted

The envelope is the fusion message's (:func:`dfusion.wire.seal_frame`): checksum, and with a
network key one MAC over the whole bundle, so the per-track messages inside need none (one
MAC per neighbour and send, not one per track), and a per-track message cannot be moved into
another track's slot without the key. ``docs/wire-format.md`` has the layout; ``docs/multi-target.md``
the protocol.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import msgpack

from dfusion.errors import MessageError
from dfusion.tracking.track import TrackId
from dfusion.wire import KEYED, MAX_ABS_TIME, MAX_MESSAGE_BYTES, MAX_SEQ, FrameKey, open_frame, seal_frame

__all__ = ["BUNDLE_MAGIC", "BUNDLE_VERSION", "MAX_TRACKS_PER_BUNDLE", "TrackBundle", "TrackEnd", "TrackMessage",
           "decode_bundle", "encode_bundle"]

BUNDLE_MAGIC = b"DT"
BUNDLE_VERSION = 1
#: Most tracks (and most track ends) one bundle may carry.
MAX_TRACKS_PER_BUNDLE = 4096
_MAX_NAME = 256


@dataclass(frozen=True)
class TrackMessage:
    """One track's fusion message for the recipient: the track, its birth time (the time of
    the common prior every node gives it), the fusion frame."""

    track: TrackId
    born: float
    frame: bytes


@dataclass(frozen=True)
class TrackEnd:
    """A track that ended at ``at`` (the deciding node's clock): deleted (``into`` is ``None``)
    or merged into ``into`` (born at ``into_born``)."""

    track: TrackId
    into: TrackId | None = None
    into_born: float = 0.0
    at: float = 0.0

    @property
    def merged(self) -> bool:
        return self.into is not None


@dataclass(frozen=True)
class TrackBundle:
    """A decoded bundle (module docstring)."""

    src: str
    dst: str
    epoch: int
    sent_at: float
    tracks: tuple[TrackMessage, ...] = ()
    ended: tuple[TrackEnd, ...] = ()


def encode_bundle(bundle: TrackBundle, key: FrameKey | None = None) -> bytes:
    """The frame of ``bundle``; keyed (with a MAC) when ``key`` is given."""
    body = msgpack.packb(
        [bundle.src, bundle.dst, int(bundle.epoch), float(bundle.sent_at),
         [[m.track.origin, int(m.track.serial), float(m.born), bytes(m.frame)] for m in bundle.tracks],
         [[e.track.origin, int(e.track.serial), e.into.origin if e.into else "", int(e.into.serial) if e.into else 0,
           float(e.into_born), float(e.at)] for e in bundle.ended]],
        use_bin_type=True)
    return seal_frame(body, key, magic=BUNDLE_MAGIC, version=BUNDLE_VERSION, flags=0)


def _reject(reason: str, detail: str) -> MessageError:
    err = MessageError(detail)
    err.reason = reason
    return err


def _name(v: object, what: str, empty: bool = False) -> str:
    if not isinstance(v, str) or len(v) > _MAX_NAME or (not v and not empty) or "#" in v:
        raise _reject("malformed", f"bundle field {what!r} must be a name of at most {_MAX_NAME} characters "
                                   "without '#'")
    return v


def _int(v: object, what: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v < hi:
        raise _reject("malformed", f"bundle field {what!r} must be an integer in [{lo}, {hi})")
    return v


def _time(v: object, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > MAX_ABS_TIME:
        raise _reject("malformed", f"bundle field {what!r} must be a finite time (|t| <= {MAX_ABS_TIME:g} s)")
    return float(v)


def decode_bundle(data: bytes | bytearray | memoryview, key: FrameKey | None = None,
                  max_bytes: int = MAX_MESSAGE_BYTES) -> TrackBundle:
    """Parse and validate a bundle; raises :class:`MessageError` (with ``reason``) on any defect.

    The per-track fusion messages are checked by the track's :class:`FusionNode` when it
    receives them; here: the envelope, every field's type and range, no track twice, no track
    merged into itself.
    """
    body, _ = open_frame(data, key, max_bytes, magic=BUNDLE_MAGIC, version=BUNDLE_VERSION, known_flags=KEYED)
    try:
        fields = msgpack.unpackb(body, raw=False, use_list=True, strict_map_key=True, max_bin_len=max_bytes,
                                 max_array_len=MAX_TRACKS_PER_BUNDLE, max_map_len=0, max_str_len=_MAX_NAME)
    except Exception as exc:  # msgpack raises many types on garbage
        raise _reject("malformed", f"not a msgpack body: {type(exc).__name__}: {exc}") from None
    if not isinstance(fields, list) or len(fields) != 6:
        raise _reject("malformed", "the bundle body must be an array of 6 fields")
    src, dst, epoch, sent_at, tracks, ended = fields
    src, dst = _name(src, "src"), _name(dst, "dst")
    epoch = _int(epoch, "epoch", 1, MAX_SEQ)
    sent_at = _time(sent_at, "sent_at")
    if not isinstance(tracks, list) or not isinstance(ended, list):
        raise _reject("malformed", "bundle fields 'tracks' and 'ended' must be arrays")
    messages = []
    seen: set[TrackId] = set()
    for item in tracks:
        if not isinstance(item, list) or len(item) != 4 or not isinstance(item[3], bytes):
            raise _reject("malformed", "a bundle track must be [origin, serial, born, message bytes]")
        tid = TrackId(_name(item[0], "origin"), _int(item[1], "serial", 0, MAX_SEQ))
        if tid in seen:
            raise _reject("malformed", f"track {tid} twice in one bundle")
        seen.add(tid)
        messages.append(TrackMessage(tid, _time(item[2], "born"), item[3]))
    ends = []
    for item in ended:
        if not isinstance(item, list) or len(item) != 6:
            raise _reject("malformed", "a track end must be [origin, serial, into_origin, into_serial, into_born, at]")
        tid = TrackId(_name(item[0], "origin"), _int(item[1], "serial", 0, MAX_SEQ))
        into_origin = _name(item[2], "into_origin", empty=True)
        into = TrackId(into_origin, _int(item[3], "into_serial", 0, MAX_SEQ)) if into_origin else None
        if into == tid:
            raise _reject("malformed", f"track {tid} merged into itself")
        ends.append(TrackEnd(tid, into, _time(item[4], "into_born"), _time(item[5], "at")))
    return TrackBundle(src, dst, epoch, sent_at, tuple(messages), tuple(ends))
