"""The fusion message: msgpack, versioned, validated, optionally authenticated.

A message from node ``src`` to its neighbour ``dst`` carries, for each state
time ``t_i`` it covers, one block of *single-state information*
``(Lambda_i, y_i)`` (see :mod:`dfusion.fusion.node` for what it means). Layout of
version 1 (all floats IEEE-754 float64 little-endian; "packed" symmetric blocks
store the upper triangle row by row, ``n(n+1)/2`` numbers)::

    envelope = msgpack map {
        "v":    1,                  # format version
        "body": bin,                # msgpack map below, as bytes
        "mac":  bin | nil,          # HMAC-SHA256(key, body) when a network key is set
    }
    body = msgpack map {
        "src": str, "dst": str,     # sender and recipient node names
        "epoch": int,               # random 63-bit id of the sender's incarnation
        "seq": int,                 # per-link sequence number, strictly increasing per epoch
        "n": int,                   # state dimension
        "start": float,             # oldest state time the sender still holds
        "sent_at": float,           # sender's clock when the message was made
        "times": bin,               # m float64, strictly increasing
        "info": bin,                # m * n(n+1)/2 float64: packed Lambda_i
        "vec": bin,                 # m * n float64: y_i
    }

:func:`decode` rejects, with :class:`~dfusion.errors.MessageError`: anything that
is not such a map, an unknown version, wrong types or sizes, non-finite numbers,
times that are not strictly increasing, an information block that is not
positive semi-definite (scaled test, :func:`_not_psd`), a time beyond
:data:`MAX_ABS_TIME` or two times closer than :data:`TIME_RESOLUTION`, entries
beyond :data:`MAX_ABS_INFO` / :data:`MAX_ABS_VEC`, and, when a key is
configured, a missing or wrong MAC (compared in constant time).
"""
from __future__ import annotations

import hashlib
import hmac
import math
from dataclasses import dataclass
from functools import lru_cache

import msgpack
import numpy as np

from dfusion.errors import MessageError
from dfusion.linalg import Array

VERSION = 1
#: Positive semi-definiteness check on received blocks (see ``_not_psd``): the floor added
#: to the diagonal, relative to the block's largest entry, and the tolerance on the
#: smallest eigenvalue of the diagonally scaled block.
PSD_RTOL = 1e-9
PSD_SCALED_ATOL = 1e-6
#: Largest message accepted (bytes); guards against memory exhaustion.
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_STATE_DIM = 64
#: Largest |time| accepted (seconds): time keys (integer nanoseconds) stay in int64.
MAX_ABS_TIME = 9.2e9
#: Resolution of state times: two times of a message must be at least this far apart.
TIME_RESOLUTION = 1e-9
#: Largest |entry| of an information block, and of an information vector. Information of
#: 1e12 is a standard deviation of 1e-6 (in the state's units); far larger values are
#: refused because replacing them later would cancel every other digit.
MAX_ABS_INFO = 1e12
MAX_ABS_VEC = 1e18
#: Relative margin of the diagonal-dominance shortcut of ``_not_psd`` (covers the rounding
#: of a row sum of up to ``MAX_STATE_DIM`` terms with room to spare).
_DOMINANCE_RTOL = 1e-9

_F8 = np.dtype("<f8")


@lru_cache(maxsize=16)
def _triu(n: int) -> tuple[Array, Array]:
    return np.triu_indices(n)


@dataclass(frozen=True)
class InfoMessage:
    """A decoded fusion message (see the module docstring for the fields)."""

    src: str
    dst: str
    epoch: int
    seq: int
    start: float
    sent_at: float
    times: Array       # (m,)
    info: Array        # (m, n, n), symmetric
    vec: Array         # (m, n)

    @property
    def n(self) -> int:
        return self.vec.shape[1]

    def __len__(self) -> int:
        return self.times.shape[0]


def encode(msg: InfoMessage, key: bytes | None = None) -> bytes:
    """Serialize ``msg``; with ``key`` the envelope carries HMAC-SHA256 of the body."""
    m, n = msg.vec.shape
    iu = _triu(n)
    body = msgpack.packb(
        {
            "src": msg.src,
            "dst": msg.dst,
            "epoch": int(msg.epoch),
            "seq": int(msg.seq),
            "n": int(n),
            "start": float(msg.start),
            "sent_at": float(msg.sent_at),
            "times": np.ascontiguousarray(msg.times, dtype=_F8).tobytes(),
            "info": np.ascontiguousarray(msg.info[:, iu[0], iu[1]], dtype=_F8).tobytes(),
            "vec": np.ascontiguousarray(msg.vec, dtype=_F8).tobytes(),
        },
        use_bin_type=True,
    )
    mac = hmac.new(key, body, hashlib.sha256).digest() if key else None
    return msgpack.packb({"v": VERSION, "body": body, "mac": mac}, use_bin_type=True)


def _unpack(data: bytes) -> dict:
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES)
    except Exception as exc:  # msgpack raises many types on garbage
        raise MessageError(f"not a msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, dict):
        raise MessageError("message is not a map")
    return obj


def _field(d: dict, name: str, types: type | tuple) -> object:
    if name not in d:
        raise MessageError(f"message has no field {name!r}")
    v = d[name]
    if isinstance(v, bool) or not isinstance(v, types):
        raise MessageError(f"field {name!r} has type {type(v).__name__}")
    return v


def _floats(buf: bytes, count: int, name: str) -> tuple[Array, float]:
    """``count`` little-endian float64 from ``buf`` (a writable copy) and their largest ``|x|``.

    One reduction serves the finiteness check and, later, the magnitude limits:
    the maximum of ``|x|`` is NaN or inf exactly when some number is.
    """
    if len(buf) != 8 * count:
        raise MessageError(f"field {name!r} has {len(buf)} bytes, expected {8 * count}")
    a = np.frombuffer(buf, dtype=_F8).astype(np.float64)
    amax = float(np.abs(a).max()) if count else 0.0
    if not math.isfinite(amax):
        raise MessageError(f"field {name!r} contains NaN or inf")
    return a, amax


def _check_times(times: Array, start: float, sent_at: float, tmax: float) -> None:
    """Checks 15-18 of docs/wire-format.md on finite ``times`` (``tmax = max|times|``).

    Distinct, increasing nanosecond keys imply strictly increasing times (rounding
    is monotone), so one test covers both in the usual case; when it fails, the
    checks run one by one to report the first failure in the documented order.
    """
    m = times.shape[0]
    in_range = tmax <= MAX_ABS_TIME   # times / TIME_RESOLUTION cannot overflow
    ordered = m < 2 or (in_range and bool((np.diff(np.round(times / TIME_RESOLUTION)) > 0).all()))
    if not ordered and np.any(np.diff(times) <= 0):
        raise MessageError("state times are not strictly increasing")
    if not in_range or abs(start) > MAX_ABS_TIME or abs(sent_at) > MAX_ABS_TIME:
        raise MessageError(f"a time exceeds {MAX_ABS_TIME:g} s in magnitude")
    if not ordered:
        raise MessageError(f"two state times are closer than {TIME_RESOLUTION:g} s")
    if m and times[0] < start:
        raise MessageError("a state time precedes the window start")


@lru_cache(maxsize=16)
def _unpack_index(n: int) -> Array:
    """For each entry ``(i, j)`` of an ``n x n`` block (row-major), its index in the packed upper triangle."""
    idx = np.zeros((n, n), dtype=np.intp)
    iu = _triu(n)
    idx[iu] = np.arange(iu[0].size)
    idx[iu[1], iu[0]] = idx[iu]
    return idx.reshape(-1)


def decode(data: bytes, key: bytes | None = None) -> InfoMessage:
    """Parse and validate a message; raises :class:`MessageError` on any defect."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(f"message must be bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise MessageError(f"message of {len(data)} bytes exceeds the limit")
    env = _unpack(bytes(data))
    version = _field(env, "v", int)
    if version != VERSION:
        raise MessageError(f"unknown message version {version}")
    body = _field(env, "body", bytes)
    mac = env.get("mac")
    if key:
        if not isinstance(mac, bytes):
            raise MessageError("message is not authenticated (no MAC) but a network key is set")
        if not hmac.compare_digest(mac, hmac.new(key, body, hashlib.sha256).digest()):
            raise MessageError("message authentication failed (wrong MAC)")
    d = _unpack(body)
    src = _field(d, "src", str)
    dst = _field(d, "dst", str)
    epoch = _field(d, "epoch", int)
    seq = _field(d, "seq", int)
    n = _field(d, "n", int)
    if not (1 <= n <= MAX_STATE_DIM):
        raise MessageError(f"state dimension {n} out of range")
    if seq < 0 or epoch < 0:
        raise MessageError("negative sequence number or epoch")
    start = float(_field(d, "start", (int, float)))
    sent_at = float(_field(d, "sent_at", (int, float)))
    if not (math.isfinite(start) and math.isfinite(sent_at)):
        raise MessageError("non-finite start or sent_at")
    tb = _field(d, "times", bytes)
    if len(tb) % 8:
        raise MessageError("field 'times' is not a whole number of float64")
    m = len(tb) // 8
    times, tmax = _floats(tb, m, "times")
    _check_times(times, start, sent_at, tmax)
    k = n * (n + 1) // 2
    packed, info_max = _floats(_field(d, "info", bytes), m * k, "info")
    vec, vec_max = _floats(_field(d, "vec", bytes), m * n, "vec")
    if info_max > MAX_ABS_INFO:
        raise MessageError(f"an information entry exceeds {MAX_ABS_INFO:g} in magnitude")
    if vec_max > MAX_ABS_VEC:
        raise MessageError(f"an information-vector entry exceeds {MAX_ABS_VEC:g} in magnitude")
    info = packed.reshape(m, k)[:, _unpack_index(n)].reshape(m, n, n)
    bad = _not_psd(info)
    if bad is not None:
        raise MessageError(f"information block at t={times[bad]} is not positive semi-definite")
    return InfoMessage(src, dst, int(epoch), int(seq), start, sent_at, times, info, vec.reshape(m, n))


def _not_psd(info: Array) -> int | None:
    """Index of the first block that is not positive semi-definite, or None.

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
    if not len(info):
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
