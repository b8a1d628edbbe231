r"""The fusion message, version 2: compact, checksummed, authenticated by default, validated.

A message from node ``src`` to its neighbour ``dst`` carries, for state times ``t_k``,
blocks of *single-state information* ``(Lambda_k, y_k)`` (see :mod:`dfusion.fusion.channel`
for what they mean and how they are exchanged). ``docs/wire-format.md`` describes the
format byte by byte; in short::

    frame = b"DF" | version (1 byte, 2) | flags (1 byte) | body | crc32 (4 bytes) | mac (16 bytes, keyed frames)
    body  = msgpack array [src, dst, epoch, dst_epoch, seq, ack, ack_mask, n, start, sent_at,
                           times, mask, values, cleared, tree_term, tree_root, parent, seq_start]

* ``times``: the blocks' time keys (integer nanoseconds): the first as int64, then the
  gaps as uint32 (int64 when a gap exceeds 4.29 s: flag ``WIDE_TIMES``);
* ``mask`` and ``values``: each block is the upper triangle of ``Lambda_k`` (row by row)
  followed by ``y_k``; ``mask`` has one bit per number (``n(n+1)/2 + n`` bits, padded to
  whole bytes per block), ``values`` the float64 numbers whose bit is set, little-endian:
  zero entries (a camera's information on the velocity) cost nothing;
* ``cleared``: int64 time keys whose information from ``src`` is now zero;
* ``tree_term``, ``tree_root``, ``parent``: the sender's tree epoch and its parent in it, for
  the tree rule over links that change (:mod:`dfusion.fusion.tree`); ``0, "", ""`` on a
  fixed tree. A *beacon* (flag ``BEACON``) carries only these: no blocks;
* ``seq_start``: the sequence number at which the sender's channel for this link started
  (``0 <= seq_start <= seq``). A node that starts a fresh channel for a link in the same
  incarnation (the tree rule dropped and re-made the link) numbers on from where the
  previous one stopped and sends the new start: the recipient then knows the sender forgot
  what it had sent it (``docs/fusion.md``, resynchronization);
* ``crc32`` (:func:`zlib.crc32`, little-endian) over every byte before it: corruption is
  detected without a key;
* ``mac``: ``HMAC-SHA256(K, frame up to and including the crc)`` truncated to 16 bytes,
  with the key ``K = HMAC-SHA256(network_key, "dfusion/2" 0 network 0 run)`` derived for
  one network and one run (:class:`FrameKey`): a message of another network or another
  run fails authentication even with the same network key. The MAC covers the version,
  the flags, the sender's incarnation (``epoch``) and the sequence number.

:func:`check_frame` runs the cheap checks (size, version, checksum, MAC) on raw bytes, so a
transport can drop garbage before it queues anything; :func:`decode` runs every check before
returning a message and raises :class:`~dfusion.errors.MessageError` naming the defect; its
``reason`` (``"malformed"``, ``"corrupt"``, ``"unauthenticated"``, ``"version"``,
``"oversized"``) is what rejection counters count.
"""
from __future__ import annotations

import hmac
import math
import struct
import zlib
from dataclasses import dataclass, field
from dataclasses import fields as _dataclass_fields
from functools import lru_cache

import msgpack
import numpy as np

from dfusion.errors import MessageError
from dfusion.linalg import Array

__all__ = [
    "VERSION",
    "InfoMessage",
    "FrameKey",
    "encode",
    "decode",
    "check_frame",
    "seal_frame",
    "open_frame",
    "clear_caches",
    "LAYOUT_CACHE_ENTRIES",
    "time_keys",
    "MAX_MESSAGE_BYTES",
    "MAX_BLOCKS",
    "MAX_SEQ",
    "MAX_STATE_DIM",
]

VERSION = 2
MAGIC = b"DF"
#: Flags (the fourth byte).
KEYED, FULL, NAIVE, WIDE_TIMES, BEACON = 1, 2, 4, 8, 16
_KNOWN_FLAGS = KEYED | FULL | NAIVE | WIDE_TIMES | BEACON
#: Fields of the body; :data:`_EARLIER_LAYOUTS` are the layouts before it (refused with their own message).
BODY_FIELDS = 18
_EARLIER_LAYOUTS = {14: "the layout before the tree fields", 17: "the layout before the channel start seq_start"}
_HEAD = 4
_CRC = 4
MAC_BYTES = 16

#: Largest frame accepted (bytes), checked before anything is parsed.
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
#: Most blocks (and cleared times) a message may carry.
MAX_BLOCKS = 100_000
MAX_STATE_DIM = 64
#: Sequence numbers, incarnations and acknowledgements are below this (they fit int64).
MAX_SEQ = 2**63
#: Largest |time| accepted (seconds): time keys (integer nanoseconds) stay in int64.
MAX_ABS_TIME = 9.2e9
_MAX_KEY = int(MAX_ABS_TIME * 1e9)
#: Positive semi-definiteness check on received blocks (see ``_not_psd``): the floor added
#: to the diagonal, relative to the block's largest entry, and the tolerance on the
#: smallest eigenvalue of the diagonally scaled block.
PSD_RTOL = 1e-9
PSD_SCALED_ATOL = 1e-6
#: Largest |entry| of an information block, and of an information vector. Information of
#: 1e12 is a standard deviation of 1e-6 (in the state's units); far larger values are
#: refused because replacing them later would cancel every other digit.
MAX_ABS_INFO = 1e12
MAX_ABS_VEC = 1e18
_DOMINANCE_RTOL = 1e-9
#: Arrays of at most this many numbers are tested on Python floats (a numpy reduction costs more).
_SMALL = 64

_F8 = np.dtype("<f8")
_I8 = np.dtype("<i8")
_U4 = np.dtype("<u4")
_CRC_STRUCT = struct.Struct("<I")


def time_keys(times: Array) -> np.ndarray:
    """Integer nanoseconds of an array of times (round half to even): the keys blocks are stored under."""
    a = np.asarray(times, dtype=float)
    if a.shape == (1,):   # one time (a steady-state message): Python's round is half to even too
        k = float(a[0]) * 1e9
        if abs(k) < 2.0**62:
            return np.array([round(k)], dtype=np.int64)
    return np.rint(a * 1e9).astype(np.int64)


@dataclass(frozen=True)
class FrameKey:
    """The MAC key of one network and one run, derived from the shared network key.

    ``K = HMAC-SHA256(network_key, b"dfusion/2\\0" + network + b"\\0" + run)``: frames of
    another network or another run (a captured message replayed into a new run) fail
    authentication although both use the same network key.
    """

    network_key: bytes = field(repr=False)
    network: str = ""
    run: str = ""
    derived: bytes = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.network_key, (bytes, bytearray)) or len(self.network_key) < 16:
            raise MessageError("a network key must be at least 16 bytes")
        info = b"dfusion/2\0" + self.network.encode("utf-8") + b"\0" + self.run.encode("utf-8")
        object.__setattr__(self, "derived", hmac.digest(bytes(self.network_key), info, "sha256"))

    def mac(self, data: bytes | memoryview) -> bytes:
        return hmac.digest(self.derived, data, "sha256")[:MAC_BYTES]


@dataclass(frozen=True)
class InfoMessage:
    """A decoded fusion message (``docs/wire-format.md`` and :mod:`dfusion.fusion.channel`).

    Attributes
    ----------
    src, dst : str
        Sender and recipient.
    epoch : int
        The sender's incarnation (increases when the sender restarts).
    dst_epoch : int
        The recipient's incarnation that ``ack`` refers to (0: unknown).
    seq : int
        Per-link sequence number, from 0 in each incarnation (beacons and every channel of the
        link share the numbering: a fresh channel goes on from the previous one).
    ack : int
        Highest sequence number the sender applied from ``dst`` (-1: none).
    ack_mask : int
        Which of the 64 messages before ``ack`` the sender applied too: bit ``k`` is set
        when message ``ack - 1 - k`` was applied (a selective acknowledgement).
    start : float
        Oldest state time the sender holds.
    sent_at : float
        Sender's clock when the message was made (informational).
    times, info, vec : arrays ``(m,)``, ``(m, n, n)``, ``(m, n)``
        The blocks, by increasing time.
    cleared : (c,) float
        Times whose information from ``src`` is now zero.
    full : bool
        The message holds the sender's whole window from ``start``: a time it does not
        carry is zero. Otherwise it is partial: the times it carries replace what the
        recipient holds, the others stay as they are.
    naive : bool
        Naive fusion (no channel filter), for comparison only: the blocks are increments.
    tree_term, tree_root, parent : int, str, str
        The sender's tree epoch ``(tree_term, tree_root)`` and its parent in it (``""``: it
        is the root), for the tree rule (:mod:`dfusion.fusion.tree`); ``0, "", ""`` when
        the sender runs on a fixed tree.
    beacon : bool
        A beacon: only the tree fields mean something (no blocks; sent over links that
        are not tree links).
    seq_start : int
        The sequence number at which the sender's channel for this link started
        (``<= seq``); it changes when the sender starts a fresh channel for the link in the
        same incarnation, which tells the recipient that the sender forgot what the
        recipient had sent it (:mod:`dfusion.fusion.channel`).
    """

    src: str
    dst: str
    epoch: int
    seq: int
    start: float
    sent_at: float
    times: Array
    info: Array
    vec: Array
    dst_epoch: int = 0
    ack: int = -1
    ack_mask: int = 0
    cleared: Array = field(default_factory=lambda: np.zeros(0))
    full: bool = True
    naive: bool = False
    tree_term: int = 0
    tree_root: str = ""
    parent: str = ""
    beacon: bool = False
    seq_start: int = 0

    @property
    def n(self) -> int:
        return self.vec.shape[1]

    def __len__(self) -> int:
        return self.times.shape[0]


_MESSAGE_FIELDS = tuple(f.name for f in _dataclass_fields(InfoMessage))


def _message(*values: object) -> InfoMessage:
    """``InfoMessage(*values)`` for values already validated, without the frozen dataclass's
    ``object.__setattr__`` per field (a few microseconds of a message's decoding). Falls back
    to the constructor unless every field is given."""
    if len(values) != len(_MESSAGE_FIELDS):
        return InfoMessage(*values)
    msg = object.__new__(InfoMessage)
    msg.__dict__.update(zip(_MESSAGE_FIELDS, values))
    return msg


@lru_cache(maxsize=16)
def _triu(n: int) -> tuple[Array, Array]:
    return np.triu_indices(n)


@lru_cache(maxsize=16)
def _unpack_index(n: int) -> Array:
    """For each entry ``(i, j)`` of an ``n x n`` block (row-major), its index in the packed upper triangle."""
    idx = np.zeros((n, n), dtype=np.intp)
    iu = _triu(n)
    idx[iu] = np.arange(iu[0].size)
    idx[iu[1], iu[0]] = idx[iu]
    return idx.reshape(-1)


_LAYOUTS: dict[tuple[bytes, int], tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = {}
#: Masks up to this many bytes have their layout cached (a node's messages repeat a few masks).
_LAYOUT_CACHE_BYTES = 64
#: At most this many layouts are cached (the cache is emptied when it is full): bounded memory
#: whatever masks arrive, hostile ones included.
LAYOUT_CACHE_ENTRIES = 256


def clear_caches() -> None:
    """Empty the decoder's layout cache (bounded by :data:`LAYOUT_CACHE_ENTRIES`; for memory
    measurements that must not count it)."""
    _LAYOUTS.clear()


def _layout(mask_raw: bytes, m: int, n: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray | None]:
    """Where the numbers of a ``mask`` go: ``(count, gather_info, gather_vec, diagonal)``.

    ``count`` is the number of set bits (of values carried); ``gather_info`` ``(m, n, n)`` and
    ``gather_vec`` ``(m, n)`` index the values followed by one zero (index ``count``), so that
    ``padded[gather_info]`` is every block's full symmetric matrix. ``diagonal``: when no
    off-diagonal information entry is carried (every block is diagonal), the indices of the
    values on the diagonals, else None. Small masks (a steady-state message's) are cached by
    their bytes: a node's messages repeat the same few layouts.
    """
    cacheable = len(mask_raw) <= _LAYOUT_CACHE_BYTES
    if cacheable:
        hit = _LAYOUTS.get((mask_raw, n))
        if hit is not None:
            return hit
    k = n * (n + 1) // 2
    width = k + n
    row_bytes = (width + 7) // 8
    mask = np.unpackbits(np.frombuffer(mask_raw, dtype=np.uint8).reshape(m, row_bytes), axis=1,
                         count=width, bitorder="little").astype(bool)
    count = int(mask.sum())
    slots = np.full((m, width), count, dtype=np.intp)
    slots[mask] = np.arange(count)
    gather_info = slots[:, :k][:, _unpack_index(n)].reshape(m, n, n)
    gather_vec = np.ascontiguousarray(slots[:, k:])
    iu = _triu(n)
    off = (iu[0] != iu[1])
    diagonal = None
    if not mask[:, :k][:, off].any():
        diagonal = slots[:, :k][:, ~off][mask[:, :k][:, ~off]]
    out = (count, gather_info, gather_vec, diagonal)
    if cacheable:
        gather_info.flags.writeable = gather_vec.flags.writeable = False
        if diagonal is not None:
            diagonal.flags.writeable = False
        if len(_LAYOUTS) >= LAYOUT_CACHE_ENTRIES:
            _LAYOUTS.clear()
        _LAYOUTS[mask_raw, n] = out
    return out


def _encode_times(keys: np.ndarray) -> tuple[bytes, bool]:
    if keys.size <= 1:   # no gap (a steady-state message: one block)
        return keys.astype(_I8).tobytes(), False
    gaps = np.diff(keys)
    wide = bool(gaps.size and gaps.max() >= 2**32)
    head = keys[:1].astype(_I8).tobytes()
    return head + gaps.astype(_I8 if wide else _U4).tobytes(), wide


@lru_cache(maxsize=16)
def _triu_flat(n: int) -> tuple[int, ...]:
    """Row-major indices in an ``n x n`` block of its upper triangle, row by row (the order on the wire)."""
    iu = _triu(n)
    return tuple((iu[0] * n + iu[1]).tolist())


def _one_block(info: Array, vec: Array, n: int) -> tuple[bytes, bytes]:
    """``(mask, values)`` of a message of one block, on Python floats: the same bytes as the
    array path of :func:`encode` (``!= 0.0`` per number, bits little-endian, float64
    little-endian), without its joins and reductions, which cost more than one block."""
    flat = info.ravel().tolist()
    row = [flat[i] for i in _triu_flat(n)] + vec.ravel().tolist()
    mask = bytearray((len(row) + 7) // 8)
    values = []
    for i, v in enumerate(row):
        if v != 0.0:
            mask[i >> 3] |= 1 << (i & 7)
            values.append(v)
    return bytes(mask), struct.pack(f"<{len(values)}d", *values)


def encode(msg: InfoMessage, key: FrameKey | None = None) -> bytes:
    """The frame of ``msg``; keyed (with a MAC) when ``key`` is given."""
    m, n = msg.vec.shape
    key1 = float(msg.times[0]) * 1e9 if m == 1 else math.nan
    if abs(key1) < 2.0**62:   # the steady-state message: one block (at a time whose key fits)
        mask_b, values_b = _one_block(msg.info, msg.vec, n)
        times, wide = struct.pack("<q", round(key1)), False   # round half to even, as time_keys
    else:
        iu = _triu(n)
        rows = np.concatenate([msg.info[:, iu[0], iu[1]], msg.vec], axis=1) if m else np.zeros((0, iu[0].size + n))
        mask = rows != 0.0
        times, wide = _encode_times(time_keys(msg.times))
        mask_b = np.packbits(mask, axis=1, bitorder="little").tobytes()
        values_b = np.ascontiguousarray(rows[mask], dtype=_F8).tobytes()
    body = msgpack.packb(
        [msg.src, msg.dst, int(msg.epoch), int(msg.dst_epoch), int(msg.seq), int(msg.ack), int(msg.ack_mask), int(n),
         float(msg.start), float(msg.sent_at), times, mask_b, values_b,
         time_keys(msg.cleared).astype(_I8).tobytes() if len(msg.cleared) else b"",
         int(msg.tree_term), msg.tree_root, msg.parent, int(msg.seq_start)],
        use_bin_type=True,
    )
    flags = (FULL if msg.full else 0) | (NAIVE if msg.naive else 0) | (WIDE_TIMES if wide else 0) \
        | (BEACON if msg.beacon else 0)
    return seal_frame(body, key, magic=MAGIC, version=VERSION, flags=flags)


def _reject(reason: str, detail: str) -> MessageError:
    err = MessageError(detail)
    err.reason = reason
    return err


def check_frame(data: bytes | bytearray | memoryview, key: FrameKey | None = None,
                max_bytes: int = MAX_MESSAGE_BYTES) -> memoryview:
    """The cheap checks, before any parsing: size, magic and version, flags, checksum, MAC.

    Returns the body's bytes (a view). Raises :class:`MessageError` with ``reason``
    ``"oversized"``, ``"version"``, ``"malformed"``, ``"corrupt"`` or ``"unauthenticated"``.
    A few microseconds for a valid frame of a few kilobytes: a transport may call it in
    its receive callback and drop garbage before it takes queue space.
    """
    return _check_frame(data, key, max_bytes)[0]


def _check_frame(data: bytes | bytearray | memoryview, key: FrameKey | None,
                 max_bytes: int, verify: bool = True) -> tuple[memoryview, int]:
    """:func:`check_frame`; returns the body and the flags (``verify=False``: without the checksum
    and the MAC, :func:`open_frame`)."""
    if isinstance(data, (bytes, bytearray, memoryview)) and 0 < len(data) <= max_bytes:
        view = memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)
        if (len(data) < _HEAD + 1 + _CRC or bytes(view[:2]) != MAGIC) and (
                view[0] in (0x80 | 3, 0xDE, 0xDF) or 0x80 <= view[0] <= 0x8F):
            raise _reject("version", "a version-1 message (msgpack map): this node speaks version 2 only")
    return open_frame(data, key, max_bytes, magic=MAGIC, version=VERSION, known_flags=_KNOWN_FLAGS, verify=verify)


def seal_frame(body: bytes, key: FrameKey | None, *, magic: bytes, version: int, flags: int) -> bytes:
    """``magic | version | flags | body | crc32 | mac``: the envelope every dfusion frame kind
    shares (the fusion message here, the track bundle of :mod:`dfusion.fusion.bundle`); the
    flag ``KEYED`` is set when ``key`` is given."""
    frame = magic + bytes((version, flags | (KEYED if key is not None else 0))) + body
    frame += _CRC_STRUCT.pack(zlib.crc32(frame))
    if key is not None:
        frame += key.mac(frame)
    return frame


def open_frame(data: bytes | bytearray | memoryview, key: FrameKey | None, max_bytes: int, *,
               magic: bytes, version: int, known_flags: int, verify: bool = True) -> tuple[memoryview, int]:
    """The checks of :func:`seal_frame`'s envelope (size, magic, version, flags, checksum, MAC);
    returns the body (a view) and the flags, or raises :class:`MessageError` with ``reason``.

    ``verify=False`` skips the checksum and the MAC (the other checks run): only for bytes that
    passed this function with ``verify=True`` and the same key already (a transport's check on
    arrival, ``Delivery.checked``), so that one frame's MAC is computed once."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _reject("malformed", f"message must be bytes, got {type(data).__name__}")
    size = len(data)
    if size > max_bytes:
        raise _reject("oversized", f"message of {size} bytes exceeds the limit of {max_bytes}")
    view = memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)
    if size < _HEAD + 1 + _CRC or bytes(view[:2]) != magic:
        raise _reject("malformed", f"not a dfusion message (no {magic.decode('ascii')} header)")
    got, flags = view[2], view[3]
    if got != version:
        raise _reject("version", f"message version {got}: this node speaks version {version} only")
    if flags & ~known_flags:
        raise _reject("malformed", f"unknown flags {flags:#04x}")
    keyed = bool(flags & KEYED)
    end = size - (MAC_BYTES if keyed else 0)
    if end - _CRC < _HEAD + 1:
        raise _reject("malformed", "message too short")
    if verify:
        (crc,) = _CRC_STRUCT.unpack_from(view, end - _CRC)
        if zlib.crc32(view[:end - _CRC]) != crc:
            raise _reject("corrupt", "checksum mismatch: the message was corrupted")
    if key is not None:
        if not keyed:
            raise _reject("unauthenticated", "message is not authenticated (no MAC) but a network key is set")
        if verify and not hmac.compare_digest(bytes(view[end:]), key.mac(view[:end])):
            raise _reject("unauthenticated", "message authentication failed (wrong key, network or run)")
    elif keyed:
        raise _reject("unauthenticated", "message is authenticated (keyed network) but this node has no key")
    return view[_HEAD:end - _CRC], flags


def _int(v: object, name: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _reject("malformed", f"field {name!r} has type {type(v).__name__}")
    if not lo <= v < hi:
        raise _reject("malformed", f"field {name!r} = {v} is outside [{lo}, {hi})")
    return v


def _float(v: object, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _reject("malformed", f"field {name!r} has type {type(v).__name__}")
    f = float(v)
    if not math.isfinite(f) or abs(f) > MAX_ABS_TIME:
        raise _reject("malformed", f"field {name!r} = {v!r} is not a finite time below {MAX_ABS_TIME:g} s")
    return f


def _bin(v: object, name: str) -> bytes:
    if not isinstance(v, bytes):
        raise _reject("malformed", f"field {name!r} has type {type(v).__name__}")
    return v


def _str(v: object, name: str, empty: bool = False) -> str:
    if not isinstance(v, str) or (not v and not empty) or len(v.encode("utf-8")) > 256:
        raise _reject("malformed", f"field {name!r} must be a {'' if empty else 'non-empty '}name of at most "
                                   "256 bytes")
    return v


def _tree_fields(src: str, term: object, root: object, parent: object, flags: int,
                 m: int, cleared: int) -> tuple[int, str, str]:
    """The checked tree fields (``docs/wire-format.md``)."""
    term = _int(term, "tree_term", 0, MAX_SEQ)
    root, parent = _str(root, "tree_root", empty=True), _str(parent, "parent", empty=True)
    if not root:
        if term or parent or flags & BEACON:
            raise _reject("malformed", "a message without a tree root (a fixed tree) has tree_term 0, no parent "
                                       "and is no beacon")
    elif parent == src:
        raise _reject("malformed", f"{src!r} names itself as its parent")
    elif (not parent) != (root == src):
        raise _reject("malformed", "a node without a parent must be the root of its tree epoch, and the root "
                                   "has no parent")
    if flags & BEACON and (m or cleared or flags & (FULL | NAIVE)):
        raise _reject("malformed", "a beacon carries no blocks, clears nothing and is neither full nor naive")
    return term, root, parent


def _decode_keys(buf: bytes, name: str, wide: bool) -> np.ndarray:
    """Strictly increasing int64 keys of a ``times`` field (first key, then gaps)."""
    if not buf:
        return np.zeros(0, dtype=np.int64)
    gap = 8 if wide else 4
    if len(buf) < 8 or (len(buf) - 8) % gap:
        raise _reject("malformed", f"field {name!r} has {len(buf)} bytes, not a first time and whole gaps")
    if len(buf) == 8:   # one time (a steady-state message): no gaps
        key = int.from_bytes(buf, "little", signed=True)
        if abs(key) > _MAX_KEY:
            raise _reject("malformed", f"a time exceeds {MAX_ABS_TIME:g} s in magnitude")
        return np.array([key], dtype=np.int64)
    first = np.frombuffer(buf, dtype=_I8, count=1)
    gaps = np.frombuffer(buf, dtype=_I8 if wide else _U4, offset=8).astype(np.int64)
    if gaps.size + 1 > MAX_BLOCKS:
        raise _reject("malformed", f"more than {MAX_BLOCKS} blocks")
    if gaps.size and (gaps.min() <= 0 or gaps.max() > 2 * _MAX_KEY):
        raise _reject("malformed", f"field {name!r}: times are not strictly increasing")
    keys = np.empty(gaps.size + 1, dtype=np.int64)
    keys[0] = first[0]
    if abs(int(first[0])) > _MAX_KEY:
        raise _reject("malformed", f"a time exceeds {MAX_ABS_TIME:g} s in magnitude")
    if gaps.size:
        np.cumsum(gaps, out=keys[1:])
        keys[1:] += keys[0]
        # int64 sums wrap around silently (wide gaps reach 2^63): every gap is below 2^63,
        # so a wrap shows as a key below the one before it
        if np.any(keys[1:] <= keys[:-1]):
            raise _reject("malformed", f"field {name!r}: times are not strictly increasing")
        if abs(int(keys[-1])) > _MAX_KEY:
            raise _reject("malformed", f"a time exceeds {MAX_ABS_TIME:g} s in magnitude")
    return keys


def decode(data: bytes | bytearray | memoryview, key: FrameKey | None = None,
           max_bytes: int = MAX_MESSAGE_BYTES, *, checked: bool = False) -> InfoMessage:
    """Parse and validate a frame; raises :class:`MessageError` (with ``reason``) on any defect.

    Every check of ``docs/wire-format.md`` runs before anything is returned: sizes, every
    integer's range, times, finiteness and magnitudes, symmetry (by construction: only the
    upper triangle travels) and positive semi-definiteness of every block. ``checked=True``:
    :func:`check_frame` with the same ``key`` has passed on these very bytes (immutable
    ``bytes``), so its checksum and MAC are not computed again; every other check runs.
    """
    if checked and not isinstance(data, bytes):
        raise _reject("internal", "only immutable bytes can be decoded as checked")
    body, flags = _check_frame(data, key, max_bytes, verify=not checked)
    try:
        fields = msgpack.unpackb(body, raw=False, use_list=True, strict_map_key=True, max_bin_len=max_bytes,
                                 max_array_len=32, max_map_len=0, max_str_len=256)
    except Exception as exc:  # msgpack raises many types on garbage
        raise _reject("malformed", f"not a msgpack body: {type(exc).__name__}: {exc}") from None
    if isinstance(fields, list) and len(fields) in _EARLIER_LAYOUTS:
        raise _reject("malformed", f"a body of {len(fields)} fields ({_EARLIER_LAYOUTS[len(fields)]}): this node "
                                   f"reads {BODY_FIELDS} (docs/wire-format.md)")
    if not isinstance(fields, list) or len(fields) != BODY_FIELDS:
        raise _reject("malformed", f"the body must be an array of {BODY_FIELDS} fields")
    (src, dst, epoch, dst_epoch, seq, ack, ack_mask, n, start, sent_at, times_b, mask_b, values_b, cleared_b,
     tree_term, tree_root, parent, seq_start) = fields
    src, dst = _str(src, "src"), _str(dst, "dst")
    epoch = _int(epoch, "epoch", 0, MAX_SEQ)
    dst_epoch = _int(dst_epoch, "dst_epoch", 0, MAX_SEQ)
    seq = _int(seq, "seq", 0, MAX_SEQ)
    seq_start = _int(seq_start, "seq_start", 0, seq + 1)
    ack = _int(ack, "ack", -1, MAX_SEQ)
    ack_mask = _int(ack_mask, "ack_mask", 0, 2**64)
    n = _int(n, "n", 1, MAX_STATE_DIM + 1)
    start, sent_at = _float(start, "start"), _float(sent_at, "sent_at")
    full, naive = bool(flags & FULL), bool(flags & NAIVE)
    keys = _decode_keys(_bin(times_b, "times"), "times", bool(flags & WIDE_TIMES))
    m = keys.size
    cleared_raw = _bin(cleared_b, "cleared")
    if len(cleared_raw) % 8:
        raise _reject("malformed", "field 'cleared' is not a whole number of int64")
    cleared = np.frombuffer(cleared_raw, dtype=_I8).astype(np.int64) if cleared_raw else np.zeros(0, dtype=np.int64)
    if cleared.size > MAX_BLOCKS:
        raise _reject("malformed", f"more than {MAX_BLOCKS} cleared times")
    if cleared.size:
        if full:
            raise _reject("malformed", "a full message clears no time (absent times are zero)")
        if np.any(np.diff(cleared) <= 0) or np.abs(cleared).max() > _MAX_KEY:
            raise _reject("malformed", "cleared times are not strictly increasing times")
        if np.intersect1d(cleared, keys, assume_unique=True).size:
            raise _reject("malformed", "a time is both cleared and carried")
    tree_term, tree_root, parent = _tree_fields(src, tree_term, tree_root, parent, flags, m, cleared.size)
    start_key = int(round(start * 1e9))
    if (m and keys[0] < start_key) or (cleared.size and cleared[0] < start_key):
        raise _reject("malformed", "a state time precedes the window start")
    k = n * (n + 1) // 2
    width = k + n
    row_bytes = (width + 7) // 8
    mask_raw = _bin(mask_b, "mask")
    if len(mask_raw) != m * row_bytes:
        raise _reject("malformed", f"field 'mask' has {len(mask_raw)} bytes, expected {m * row_bytes}")
    count, gather_info, gather_vec, diagonal = _layout(mask_raw, m, n)
    values_raw = _bin(values_b, "values")
    if len(values_raw) != 8 * count:
        raise _reject("malformed", f"field 'values' has {len(values_raw)} bytes, expected {8 * count}")
    values = np.frombuffer(values_raw, dtype=_F8)
    if count <= _SMALL:   # (on Python floats: cheaper than numpy's reductions; the same decision)
        listed = values.tolist()
        if not all(map(math.isfinite, listed)):
            raise _reject("malformed", "field 'values' contains NaN or inf")
        vmax = max(map(abs, listed)) if count else 0.0
    else:
        vmax = float(np.abs(values).max()) if count else 0.0
        if not math.isfinite(vmax):
            raise _reject("malformed", "field 'values' contains NaN or inf")
    # every number in place: the values, then a zero for the entries the mask leaves out
    padded = np.empty(count + 1)
    padded[:count] = values
    padded[count] = 0.0
    info = padded[gather_info]
    vec = padded[gather_vec]
    if vmax > MAX_ABS_INFO:   # (MAX_ABS_INFO < MAX_ABS_VEC: below it both bounds hold)
        if m and np.abs(info).max() > MAX_ABS_INFO:
            raise _reject("malformed", f"an information entry exceeds {MAX_ABS_INFO:g} in magnitude")
        if m and np.abs(vec).max() > MAX_ABS_VEC:
            raise _reject("malformed", f"an information-vector entry exceeds {MAX_ABS_VEC:g} in magnitude")
    times = keys / 1e9
    if not naive:
        bad = _not_psd(info, None if diagonal is None else values[diagonal])
        if bad is not None:
            raise _reject("malformed", f"information block at t={times[bad]} is not positive semi-definite")
    return _message(src, dst, epoch, seq, start, sent_at, times, info, vec, dst_epoch, ack, ack_mask,
                    cleared / 1e9 if cleared.size else np.zeros(0), full, naive, tree_term, tree_root, parent,
                    bool(flags & BEACON), seq_start)


def _not_psd(info: Array, diagonal: Array | None = None) -> int | None:
    """Index of the first block that is not positive semi-definite, or None.

    ``diagonal``: when every block of ``info`` is diagonal, the values on the diagonals (a
    message's, from its mask): if none is negative, every block passes the dominance test
    below (its row sums are ``|d_i|`` and ``2 d_i - (1 + rtol) d_i >= 0``), which is then
    decided without computing it.

    The test is on the diagonally scaled block ``S L S``, ``S = diag(1/sqrt(d_i + f))``
    with ``d_i`` the (non-negative part of the) diagonal and the floor
    ``f = PSD_RTOL * max|L|``: rounding errors of a difference of information
    matrices are relative to each entry's own diagonal, so the scaled block's
    smallest eigenvalue must be at least ``-PSD_SCALED_ATOL``. One huge diagonal
    entry therefore cannot hide a negative eigenvalue elsewhere, and a rank-one
    block with a tiny diagonal entry is still accepted.

    Blocks that are diagonally dominant with a non-negative diagonal (with a margin
    for the rounding of the row sums) are positive semi-definite by Gershgorin's
    theorem, so is their scaled block, and the scaled test could only return a
    smallest eigenvalue of order ``-1e-13``: they are accepted without computing
    it (diagonal blocks, such as position measurements, are the common case).
    The decision is the same as testing every block.
    """
    if not len(info) or (diagonal is not None and not (
            min(diagonal.tolist(), default=0.0) < 0 if diagonal.size <= _SMALL else (diagonal < 0).any())):
        return None
    rows = np.abs(info).sum(axis=2)
    d = np.diagonal(info, axis1=1, axis2=2)
    unsure = np.flatnonzero(((2.0 * d - (1.0 + _DOMINANCE_RTOL) * rows) < 0).any(axis=1))
    if not unsure.size:
        return None
    bad = _not_psd_scaled(info[unsure])
    return None if bad is None else int(unsure[bad])


def _not_psd_scaled(info: Array) -> int | None:
    """The scaled eigenvalue test of :func:`_not_psd` on every block of ``info``."""
    d = np.diagonal(info, axis1=1, axis2=2)
    floor = PSD_RTOL * np.abs(info).max(axis=(1, 2))
    s = 1.0 / np.sqrt(np.maximum(d, 0.0) + np.where(floor > 0, floor, 1.0)[:, None])
    scaled = info * s[:, :, None] * s[:, None, :]
    bad = np.linalg.eigvalsh(scaled)[:, 0] < -PSD_SCALED_ATOL
    return int(np.argmax(bad)) if bad.any() else None
