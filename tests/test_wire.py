"""The fusion message format, version 2 (dfusion.wire): layout, every rejection, checksum, MAC, sizes.

The frame is ``b"DF" | version 2 | flags | msgpack body | crc32 | mac (keyed frames)``
(docs/wire-format.md). The numbers claimed here are checked against independent
references written in this file: a reference encoder with plain Python loops
(:func:`reference_frame`), ``zlib.crc32`` and ``hmac`` for the checksum, the key
derivation and the MAC, the packed upper triangle written out by hand, the msgpack
specification for the sizes, and a brute-force eigenvalue test for positive
semi-definiteness.
"""
from __future__ import annotations

import hashlib
import hmac
import math
import re
import struct
import time
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion import wire
from dfusion.errors import DfusionError, MessageError
from dfusion.wire import (
    MAX_ABS_INFO,
    MAX_ABS_TIME,
    MAX_ABS_VEC,
    MAX_BLOCKS,
    MAX_MESSAGE_BYTES,
    MAX_STATE_DIM,
    PSD_RTOL,
    PSD_SCALED_ATOL,
    VERSION,
    FrameKey,
    InfoMessage,
    check_frame,
    decode,
    encode,
    time_keys,
)

NETWORK_KEY = b"network-key-for-the-wire-tests"
NETWORK, RUN = "plant-3", "2026-11-25T13:00"
KEY = FrameKey(NETWORK_KEY, NETWORK, RUN)
# the flag bits (the fourth byte), from docs/wire-format.md
KEYED, FULL, NAIVE, WIDE, BEACON = 1, 2, 4, 8, 16
FIELDS = ("src", "dst", "epoch", "dst_epoch", "seq", "ack", "ack_mask", "n", "start", "sent_at",
          "times", "mask", "values", "cleared", "tree_term", "tree_root", "parent", "seq_start")


# ---------------------------------------------------------------- independent references
def derived_key(network_key: bytes, network: str, run: str) -> bytes:
    """HMAC-SHA256(network_key, "dfusion/2" 0 network 0 run)."""
    info = b"dfusion/2\x00" + network.encode() + b"\x00" + run.encode()
    return hmac.new(network_key, info, hashlib.sha256).digest()


def reference_mac(frame_without_mac: bytes, network_key: bytes = NETWORK_KEY, network: str = NETWORK,
                  run: str = RUN) -> bytes:
    return hmac.new(derived_key(network_key, network, run), frame_without_mac, hashlib.sha256).digest()[:16]


def seal(head_and_body: bytes, keyed: bool, **key) -> bytes:
    """Append the crc32 (little-endian) and, for a keyed frame, the 16-byte MAC."""
    frame = head_and_body + struct.pack("<I", zlib.crc32(head_and_body))
    return frame + reference_mac(frame, **key) if keyed else frame


def frame_of(fields: list, flags: int = FULL, keyed: bool = False, version: int = VERSION, **key) -> bytes:
    """A frame around a body built from raw field values (valid or not), sealed correctly."""
    body = msgpack.packb(fields, use_bin_type=True)
    return seal(b"DF" + bytes((version, flags | (KEYED if keyed else 0))) + body, keyed, **key)


def upper_triangle(L) -> list[float]:
    """L[0][0], L[0][1], ..., L[0][n-1], L[1][1], ..., L[n-1][n-1] (row by row)."""
    n = len(L)
    return [float(L[i][j]) for i in range(n) for j in range(i, n)]


def reference_fields(msg: InfoMessage) -> tuple[list, int]:
    """The 18 body fields and the flags of ``msg``, by the rules of docs/wire-format.md, with
    plain Python (no numpy bit packing, no dfusion code)."""
    m, n = len(msg.times), msg.vec.shape[1]
    keys = [round(float(t) * 1e9) for t in msg.times]          # Python's round: half to even
    gaps = [b - a for a, b in zip(keys, keys[1:])]
    wide = any(g >= 2**32 for g in gaps)
    times = b""
    if m:
        times = struct.pack("<q", keys[0]) + b"".join(struct.pack("<q" if wide else "<I", g) for g in gaps)
    mask, values = bytearray(), bytearray()
    for b in range(m):
        numbers = upper_triangle(msg.info[b]) + [float(v) for v in msg.vec[b]]
        bits = [x != 0.0 for x in numbers]
        row = bytearray((len(bits) + 7) // 8)
        for i, bit in enumerate(bits):
            if bit:
                row[i // 8] |= 1 << (i % 8)
        mask += row
        values += b"".join(struct.pack("<d", x) for x in numbers if x != 0.0)
    cleared = b"".join(struct.pack("<q", round(float(t) * 1e9)) for t in msg.cleared)
    fields = [msg.src, msg.dst, int(msg.epoch), int(msg.dst_epoch), int(msg.seq), int(msg.ack), int(msg.ack_mask), n,
              float(msg.start), float(msg.sent_at), times, bytes(mask), bytes(values), cleared,
              int(msg.tree_term), msg.tree_root, msg.parent, int(msg.seq_start)]
    flags = (FULL if msg.full else 0) | (NAIVE if msg.naive else 0) | (WIDE if wide else 0) | \
        (BEACON if msg.beacon else 0)
    return fields, flags


def reference_frame(msg: InfoMessage, keyed: bool = False) -> bytes:
    fields, flags = reference_fields(msg)
    return frame_of(fields, flags, keyed)


def brute_force_indefinite(L: np.ndarray) -> bool:
    """Indefinite beyond the rounding the documented rule allows.

    The rule accepts ``L`` when ``S L S >= -PSD_SCALED_ATOL I``, ``S = diag(1/sqrt(d+ + f))``,
    ``d+`` the non-negative part of the diagonal, ``f = PSD_RTOL max|L|`` (or 1 for a zero
    block). By congruence (Sylvester's law of inertia) that is ``L + PSD_SCALED_ATOL
    (diag(d+) + f I)`` positive semi-definite: computed here on the unscaled matrix, without
    decode's scaling or its diagonal-dominance shortcut.
    """
    d = np.maximum(np.diag(L), 0.0)
    f = PSD_RTOL * np.abs(L).max(initial=0.0) or 1.0
    shifted = L + PSD_SCALED_ATOL * (np.diag(d) + f * np.eye(L.shape[0]))
    # eigvalsh's own error is a few eps times the largest entry
    return bool(np.linalg.eigvalsh(shifted).min() < -1e-13 * np.abs(shifted).max())


# ---------------------------------------------------------------- helpers
def sym_upper(S: np.ndarray) -> np.ndarray:
    """The symmetric matrices with the upper triangles of ``S`` (bit-exact symmetry)."""
    return np.triu(S) + np.swapaxes(np.triu(S, 1), -1, -2)


def make_msg(n: int = 2, m: int = 3, seed: int = 0, **kw) -> InfoMessage:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n, n))
    fields = dict(src="a", dst="b", epoch=12345, seq=7, start=0.25, sent_at=3.5,
                  times=0.5 + np.arange(m, dtype=float), info=sym_upper(A @ np.swapaxes(A, 1, 2)),
                  vec=rng.normal(size=(m, n)), dst_epoch=678, ack=4, ack_mask=0b1011, full=True)
    fields.update(kw)
    return InfoMessage(**fields)


def fields_of(msg: InfoMessage | None = None, **changes) -> list:
    """The reference body fields of ``msg`` (default :func:`make_msg`) with some replaced."""
    fields, _ = reference_fields(msg if msg is not None else make_msg())
    for name, value in changes.items():
        fields[FIELDS.index(name)] = value
    return fields


def tampered(flags: int = FULL, keyed: bool = False, msg: InfoMessage | None = None, **changes) -> bytes:
    """A correctly sealed frame of :func:`make_msg` with raw body fields replaced."""
    return frame_of(fields_of(msg, **changes), flags, keyed)


def rejected(data, key: FrameKey | None = None, reason: str | None = None, match: str | None = None,
             **kw) -> MessageError:
    with pytest.raises(MessageError, match=match) as info:
        decode(data, key, **kw)
    err = info.value
    assert isinstance(err, ValueError) and isinstance(err, DfusionError)
    assert str(err), "an empty error message is not a clear one"
    assert err.reason in ("malformed", "corrupt", "unauthenticated", "version", "oversized")
    if reason is not None:
        assert err.reason == reason, (err.reason, str(err))
    return err


def plain(x: np.ndarray) -> np.ndarray:
    """``x`` with -0.0 as 0.0 (a zero number is not sent, so it comes back as +0.0)."""
    return np.where(x == 0.0, 0.0, x)


def assert_same(out: InfoMessage, msg: InfoMessage) -> None:
    """Bit-exact equality of every field (times through their nanosecond keys, -0.0 as 0.0)."""
    for name in ("src", "dst", "epoch", "dst_epoch", "seq", "ack", "ack_mask", "full", "naive", "seq_start"):
        assert getattr(out, name) == getattr(msg, name), name
    for name in ("start", "sent_at"):
        assert struct.pack("<d", getattr(out, name)) == struct.pack("<d", getattr(msg, name)), name
    keys = np.array([round(float(t) * 1e9) for t in msg.times], dtype=np.int64)
    assert np.array_equal(out.times, keys / 1e9)
    cleared = np.array([round(float(t) * 1e9) for t in msg.cleared], dtype=np.int64)
    assert np.array_equal(out.cleared, cleared / 1e9)
    assert out.info.shape == msg.info.shape and out.vec.shape == msg.vec.shape
    assert out.info.tobytes() == plain(np.asarray(msg.info, "<f8")).tobytes()
    assert out.vec.tobytes() == plain(np.asarray(msg.vec, "<f8")).tobytes()


# ---------------------------------------------------------------- round trip
@st.composite
def messages(draw) -> InfoMessage:
    """Random valid messages over the whole range of every field."""
    n = draw(st.integers(1, 8))
    m = draw(st.integers(0, 30))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    naive = draw(st.booleans())
    full = draw(st.booleans()) and not naive
    # times as integer nanoseconds below 2^52, so that t = key / 1e9 gives the key back
    first = draw(st.integers(-(2**51), 2**51))
    wide = draw(st.booleans())
    gaps = rng.integers(1, 2**32 if not wide else 10**13, size=max(m - 1, 0))
    if m > 1 and wide:
        gaps[rng.integers(gaps.size)] = draw(st.integers(2**32, 10**13))
    keys = first + np.concatenate([[0], np.cumsum(gaps)]).astype(np.int64) if m else np.zeros(0, np.int64)
    # cleared times (partial messages only): distinct from the carried ones, after start
    cleared = np.zeros(0, np.int64)
    if not full and m:
        extra = keys[-1] + np.cumsum(rng.integers(1, 10**6, size=draw(st.integers(0, 5))))
        cleared = np.sort(np.concatenate([extra, (keys[:-1] + 1)[rng.random(m - 1) < 0.3]]))
    lo = min(keys[:1].tolist() + cleared[:1].tolist() + [first])
    start = (lo - draw(st.integers(0, 10**15))) / 1e9
    # blocks: A A^T over a random subset of the state's components (zero rows and columns
    # stay positive semi-definite and exercise the mask), over 150 orders of magnitude
    rank = draw(st.integers(1, n))
    scale = 10.0 ** draw(st.integers(-150, 9))
    A = rng.normal(size=(m, n, rank)) * np.sqrt(scale) * (rng.random((m, n, 1)) < 0.7)
    info = sym_upper(A @ np.swapaxes(A, 1, 2))
    if naive:   # increments: any symmetric block
        info = sym_upper(info - scale * rng.random((m, n, n)))
    info = np.clip(info, -MAX_ABS_INFO, MAX_ABS_INFO)
    vec = rng.normal(size=(m, n)) * scale * (rng.random((m, n)) < 0.7)
    seq = draw(st.integers(0, 2**63 - 1))
    return InfoMessage(
        src=draw(st.text(min_size=1, max_size=40)), dst=draw(st.text(min_size=1, max_size=40)),
        epoch=draw(st.integers(0, 2**63 - 1)), seq=seq, seq_start=draw(st.integers(0, seq)), start=start,
        sent_at=draw(st.floats(-MAX_ABS_TIME, MAX_ABS_TIME)), times=keys / 1e9, info=info, vec=vec,
        dst_epoch=draw(st.integers(0, 2**63 - 1)), ack=draw(st.integers(-1, 2**63 - 1)),
        ack_mask=draw(st.integers(0, 2**64 - 1)), cleared=cleared / 1e9, full=full, naive=naive)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(msg=messages(), keyed=st.booleans())
def test_round_trip_is_bit_exact(msg, keyed):
    key = KEY if keyed else None
    data = encode(msg, key)
    # the encoder writes exactly the layout of the reference encoder
    assert data == reference_frame(msg, keyed)
    out = decode(data, key)
    assert_same(out, msg)
    assert out.n == msg.vec.shape[1] and len(out) == len(msg.times)
    assert out.info.flags.writeable and out.vec.flags.writeable     # the receiver's own copies
    assert encode(out, key) == data


def test_round_trip_of_extreme_but_valid_values():
    tiny = np.finfo(float).smallest_subnormal
    msg = make_msg(n=2, m=3, start=-MAX_ABS_TIME, sent_at=MAX_ABS_TIME,
                   times=np.array([-MAX_ABS_TIME, 0.0, MAX_ABS_TIME]),
                   info=np.array([[[MAX_ABS_INFO, 0.0], [0.0, MAX_ABS_INFO]], [[tiny, 0.0], [0.0, 0.0]],
                                  np.zeros((2, 2))]),
                   vec=np.array([[-MAX_ABS_VEC, MAX_ABS_VEC], [tiny, -tiny], [0.0, 0.0]]),
                   epoch=2**63 - 1, dst_epoch=2**63 - 1, seq=2**63 - 1, ack=2**63 - 1, ack_mask=2**64 - 1,
                   seq_start=2**63 - 1, src="ñødé/α", dst="x" * 256)
    for key in (None, KEY):
        data = encode(msg, key)
        assert data == reference_frame(msg, key is not None)
        out = decode(data, key)
        assert_same(out, msg)
        assert out.times[-1] == MAX_ABS_TIME and out.vec[0, 0] == -MAX_ABS_VEC


def test_times_travel_as_integer_nanoseconds():
    """A time is sent as its key round(t * 1e9) (half to even, as Python's round):
    the decoded time is key / 1e9."""
    times = np.array([0.1, 0.2 + 1e-12, 1.0000000015, 1.0000000025, 7.3])
    rng = np.random.default_rng(1)
    more = np.sort(rng.uniform(-1e6, 1e6, 200))
    for t in (times, more):
        assert time_keys(t).tolist() == [round(x * 1e9) for x in t]
        msg = make_msg(n=1, m=len(t), times=t, start=float(t[0]) - 1, info=np.ones((len(t), 1, 1)),
                       vec=np.ones((len(t), 1)))
        out = decode(encode(msg))
        assert out.times.tolist() == [round(x * 1e9) / 1e9 for x in t]


def test_bytearray_and_memoryview_are_accepted():
    data = encode(make_msg(), KEY)
    for form in (bytearray(data), memoryview(data)):
        assert_same(decode(form, KEY), make_msg())


# ---------------------------------------------------------------- the layout, by hand
def test_a_frame_written_out_by_hand():
    """n = 2, one block: every byte of the frame from the specification."""
    msg = InfoMessage(src="a", dst="b", epoch=7, seq=3, start=0.5, sent_at=1.0, times=np.array([1.0]),
                      info=np.array([[[4.0, 0.5], [0.5, 2.0]]]), vec=np.array([[1.0, -2.0]]),
                      dst_epoch=9, ack=2, ack_mask=1, full=True)
    f8 = lambda x: struct.pack("<d", x)            # noqa: E731 (little-endian float64)
    body = (
        b"\xdc\x00\x12"                             # array 16 of 18 fields
        + b"\xa1a" + b"\xa1b"                       # fixstr "a", "b"
        + b"\x07" + b"\x09" + b"\x03" + b"\x02" + b"\x01" + b"\x02"   # epoch dst_epoch seq ack ack_mask n
        + b"\xcb" + struct.pack(">d", 0.5)          # start: msgpack float 64 (big-endian)
        + b"\xcb" + struct.pack(">d", 1.0)          # sent_at
        + b"\xc4\x08" + struct.pack("<q", 10**9)    # times: first key, no gaps
        + b"\xc4\x01" + bytes([0b11111])            # mask: L00 L01 L11 y0 y1 all non-zero
        + b"\xc4\x28" + f8(4.0) + f8(0.5) + f8(2.0) + f8(1.0) + f8(-2.0)
        + b"\xc4\x00"                               # cleared: none
        + b"\x00" + b"\xa0" + b"\xa0"                # tree_term 0, tree_root "", parent "": a fixed tree
        + b"\x00"                                   # seq_start 0: the channel's first number
    )
    head = b"DF\x02\x02" + body                     # version 2, flags FULL
    crc = struct.pack("<I", zlib.crc32(head))
    assert encode(msg) == head + crc
    mac = hmac.new(derived_key(NETWORK_KEY, NETWORK, RUN), b"DF\x02\x03" + body + struct.pack(
        "<I", zlib.crc32(b"DF\x02\x03" + body)), hashlib.sha256).digest()[:16]
    keyed = encode(msg, KEY)
    assert keyed == b"DF\x02\x03" + body + struct.pack("<I", zlib.crc32(b"DF\x02\x03" + body)) + mac
    assert len(keyed) == len(head) + 4 + 16


def test_packed_upper_triangle_is_row_major():
    """n = 3: the numbers of a block are L00 L01 L02 L11 L12 L22 y0 y1 y2; 9 bits: 2 mask bytes."""
    L = np.array([[11.0, 2.0, 3.0], [2.0, 14.0, 5.0], [3.0, 5.0, 16.0]])
    msg = make_msg(n=3, m=1, info=L[None], vec=np.array([[7.0, 8.0, 9.0]]), times=np.array([1.0]))
    body = msgpack.unpackb(encode(msg)[4:-4])
    assert np.frombuffer(body[12], "<f8").tolist() == [11.0, 2.0, 3.0, 14.0, 5.0, 16.0, 7.0, 8.0, 9.0]
    assert body[11] == b"\xff\x01"
    out = decode(encode(msg))
    assert np.array_equal(out.info[0], L)


def test_zero_numbers_are_not_sent():
    """A 2-D position fix on a constant-velocity state (n = 4): only L00, L11, y0, y1 are
    non-zero. Packed positions: L00 = 0, L11 = 4 (row 0 holds 4 numbers), y0 = 10, y1 = 11
    (after the 10 of the triangle): mask bytes 0b00010001, 0b00001100; 4 values."""
    L = np.diag([4.0, 4.0, 0.0, 0.0])
    msg = make_msg(n=4, m=1, info=L[None], vec=np.array([[2.0, -6.0, 0.0, 0.0]]), times=np.array([1.0]))
    body = msgpack.unpackb(encode(msg)[4:-4])
    assert body[11] == bytes([0b00010001, 0b00001100])
    assert np.frombuffer(body[12], "<f8").tolist() == [4.0, 4.0, 2.0, -6.0]
    assert_same(decode(encode(msg)), msg)


@pytest.mark.parametrize("gap, wide", [(2**32 - 1, False), (2**32, True)])
def test_time_gaps_are_uint32_until_they_need_int64(gap, wide):
    keys = np.array([5, 5 + gap, 5 + gap + 1], dtype=np.int64)
    msg = make_msg(n=1, m=3, times=keys / 1e9, start=0.0, info=np.ones((3, 1, 1)), vec=np.ones((3, 1)))
    data = encode(msg)
    assert bool(data[3] & WIDE) == wide
    body = msgpack.unpackb(data[4:-4])
    assert body[10] == struct.pack("<q", 5) + struct.pack("<qq" if wide else "<II", gap, 1)
    assert decode(data).times.tolist() == (keys / 1e9).tolist()


def test_checksum_is_zlib_crc32_of_everything_before_it():
    for key in (None, KEY):
        data = encode(make_msg(), key)
        end = len(data) - (16 if key else 0)
        assert struct.unpack("<I", data[end - 4:end])[0] == zlib.crc32(data[:end - 4])


def test_mac_is_truncated_hmac_sha256_with_the_derived_key():
    data = encode(make_msg(), KEY)
    assert data[3] & KEYED
    assert data[-16:] == reference_mac(data[:-16])
    assert KEY.derived == derived_key(NETWORK_KEY, NETWORK, RUN)
    assert NETWORK_KEY.hex() not in repr(KEY) and "derived" not in repr(KEY)


def test_check_frame_returns_the_body_without_parsing_it():
    for key in (None, KEY):
        data = encode(make_msg(), key)
        body = check_frame(data, key)
        assert bytes(body) == data[4:len(data) - 4 - (16 if key else 0)]
        # garbage inside a well-sealed frame passes the cheap checks; decode refuses it
        junk = seal(b"DF\x02" + bytes([FULL | (KEYED if key else 0)]) + b"\xc1 not msgpack", key is not None)
        assert bytes(check_frame(junk, key)) == b"\xc1 not msgpack"
        rejected(junk, key, "malformed", "not a msgpack body")


def test_a_checked_frame_is_decoded_without_a_second_mac_and_the_same_message(monkeypatch):
    """decode(checked=True): the bytes passed check_frame already (a transport's check on arrival),
    so neither the checksum nor the MAC is computed again; the message is the same, and every
    check of the body still runs."""
    data = encode(make_msg(), KEY)
    check_frame(data, KEY)
    calls = []
    real_mac, real_crc = FrameKey.mac, wire.zlib.crc32
    monkeypatch.setattr(FrameKey, "mac", lambda self, d: calls.append("mac") or real_mac(self, d))
    monkeypatch.setattr(wire.zlib, "crc32", lambda d: calls.append("crc") or real_crc(d))
    assert_same(decode(data, KEY, checked=True), decode(data, KEY))
    assert calls == ["crc", "mac"]   # only the unchecked decode computed them
    junk = seal(b"DF\x02" + bytes([FULL | KEYED]) + b"\xc1 not msgpack", True)
    check_frame(junk, KEY)
    with pytest.raises(MessageError, match="not a msgpack body"):
        decode(junk, KEY, checked=True)
    with pytest.raises(MessageError, match="immutable bytes"):   # a buffer could change after its check
        decode(bytearray(data), KEY, checked=True)


# ---------------------------------------------------------------- rejections: the frame
@pytest.mark.parametrize("data", ["text", None, 42, [b"DF"], {"v": 2}], ids=repr)
def test_not_bytes(data):
    rejected(data, reason="malformed", match="must be bytes")


@pytest.mark.parametrize("data", [b"", b"D", b"DF", b"DF\x02\x02", b"DF\x02\x02\x90\x00\x00\x00", b"XF\x02\x02" + b"\x00" * 20,
                                  b"\x00" * 40, b"\xc1" * 40], ids=repr)
def test_not_a_dfusion_frame(data):
    rejected(data, reason="malformed", match="not a dfusion message")


def test_a_version_1_message_is_rejected_with_a_clear_reason():
    """Version 1 was a msgpack map {"v": 1, "body": ..., "mac": ...}."""
    body = msgpack.packb({"src": "a", "dst": "b", "epoch": 1, "seq": 0, "n": 1, "start": 0.0, "sent_at": 0.0,
                          "times": b"", "info": b"", "vec": b""}, use_bin_type=True)
    for mac in (None, hmac.new(NETWORK_KEY, body, hashlib.sha256).digest()):
        v1 = msgpack.packb({"v": 1, "body": body, "mac": mac}, use_bin_type=True)
        for key in (None, KEY):
            rejected(v1, key, "version", "version-1 message .* this node speaks version 2 only")


@pytest.mark.parametrize("version", [0, 1, 3, 255])
def test_other_versions_are_rejected(version):
    data = frame_of(fields_of(), version=version)
    rejected(data, reason="version", match=f"message version {version}: this node speaks version 2 only")


@pytest.mark.parametrize("flags", [32, 64, 128, 0xE0 | FULL])
def test_unknown_flags_are_rejected(flags):
    rejected(frame_of(fields_of(), flags), reason="malformed", match="unknown flags")


def test_a_keyed_frame_too_short_for_its_mac():
    rejected(b"DF\x02\x03" + b"\x00" * 15, reason="malformed", match="message too short")


def test_oversized_frame_is_rejected_before_anything_is_read():
    big = b"DF\x02\x02" + b"\x00" * MAX_MESSAGE_BYTES
    rejected(big, reason="oversized", match=f"exceeds the limit of {MAX_MESSAGE_BYTES}")
    data = encode(make_msg())
    rejected(data, reason="oversized", max_bytes=len(data) - 1)
    assert decode(data, max_bytes=len(data)).seq == 7
    # no byte is read: a 4 MiB + 1 frame is refused in far less time than one pass over it
    # (medians and minima: robust to a loaded machine)
    refuse = []
    for _ in range(21):
        t0 = time.perf_counter()
        with pytest.raises(MessageError):
            check_frame(big)
        refuse.append(time.perf_counter() - t0)
    one_pass = []
    for _ in range(3):
        t0 = time.perf_counter()
        zlib.crc32(big)
        one_pass.append(time.perf_counter() - t0)
    assert np.median(refuse) < min(one_pass) / 10, (np.median(refuse), min(one_pass))


def test_every_truncation_is_rejected():
    for key in (None, KEY):
        data = encode(make_msg(), key)
        for cut in range(len(data)):
            err = rejected(data[:cut], key)
            assert err.reason in ("malformed", "corrupt") if cut >= 4 else err.reason == "malformed"


def test_extended_frames_are_rejected():
    for key in (None, KEY):
        data = encode(make_msg(), key)
        for extra in (b"\x00", b"\x00" * 16, data):
            rejected(data + extra, key, "corrupt" if key is None else None)


# bits of a frame and what flipping them breaks
def flip(data: bytes, bits) -> bytes:
    out = bytearray(data)
    for b in bits:
        out[b // 8] ^= 1 << (b % 8)
    return bytes(out)


def test_every_single_bit_flip_is_rejected_with_its_reason():
    """CRC-32 detects every single-bit error; the reason says which check failed."""
    for key in (None, KEY):
        data = encode(make_msg(n=4, m=5), key)
        end = len(data) - (16 if key else 0)
        for bit in range(8 * len(data)):
            err = rejected(flip(data, [bit]), key)
            byte = bit // 8
            if byte < 2:
                expected = {"malformed", "version"}       # magic: not a dfusion frame
            elif byte == 2:
                expected = {"version"}
            elif byte == 3:
                expected = {"malformed", "corrupt", "unauthenticated"}   # unknown flag, or KEYED moves the end
            elif byte < end:
                expected = {"corrupt"}
            else:
                expected = {"unauthenticated"}           # the MAC itself
            assert err.reason in expected, (bit, err.reason, str(err))


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_two_and_three_bit_flips_are_all_rejected(data):
    """CRC-32 (IEEE 802.3) detects every error of up to 3 bits in frames of up to 91,607 bits
    (Hamming distance 4; P. Koopman, "32-bit cyclic redundancy codes for Internet
    applications", DSN 2002); with a key the MAC rejects what the checksum might not."""
    keyed = data.draw(st.booleans())
    key = KEY if keyed else None
    frame = encode(make_msg(n=4, m=20), key)
    assert 8 * len(frame) < 91_607
    bits = data.draw(st.lists(st.integers(4 * 8, 8 * len(frame) - 1), min_size=2, max_size=3, unique=True))
    rejected(flip(frame, bits), key)


@settings(max_examples=200, deadline=None)
@given(pos=st.integers(0, 10_000), junk=st.binary(min_size=1, max_size=64), replace=st.booleans(),
       keyed=st.booleans())
def test_spliced_bytes_are_rejected(pos, junk, replace, keyed):
    key = KEY if keyed else None
    data = encode(make_msg(), key)
    pos %= len(data)
    end = pos + len(junk) if replace else pos
    spliced = data[:pos] + junk + data[end:]
    if spliced != data:
        rejected(spliced, key)


def test_frames_spliced_from_two_valid_ones_are_rejected():
    """The head of one valid frame with the tail of another: the checksum fails; and when a
    forger recomputes the checksum, the MAC fails."""
    for key in (None, KEY):
        x, y = encode(make_msg(seed=1), key), encode(make_msg(seed=2, seq=8), key)
        for cut in range(4, min(len(x), len(y)) - 1, 7):
            if x[:cut] + y[cut:] not in (x, y):
                rejected(x[:cut] + y[cut:], key)
    x, y = encode(make_msg(seed=1), KEY), encode(make_msg(seed=2, seq=8), KEY)
    for cut in range(4, len(x) - 20, 5):
        forged = seal(x[:cut] + y[cut:-20], keyed=False) + x[-16:]
        if forged != x:
            rejected(forged, KEY, "unauthenticated", "authentication failed")


# ---------------------------------------------------------------- authentication
def test_tampering_with_a_recomputed_checksum_fails_authentication():
    """A forger without the key can fix the checksum, not the MAC."""
    data = encode(make_msg(), KEY)
    for changes in (dict(seq=8), dict(epoch=12346), dict(src="c"), dict(ack=5)):
        body = msgpack.packb(fields_of(**changes), use_bin_type=True)
        forged = seal(b"DF\x02" + bytes([FULL | KEYED]) + body, keyed=False) + data[-16:]
        rejected(forged, KEY, "unauthenticated", "authentication failed")
    # the flags are covered too: the same frame claiming to be partial
    head = bytearray(data[:-20])
    head[3] &= ~FULL
    rejected(seal(bytes(head), keyed=False) + data[-16:], KEY, "unauthenticated")


@pytest.mark.parametrize("other", [dict(network_key=b"another-network-key-of-32-bytes!"), dict(network="plant-4"),
                                   dict(run="2026-11-25T14:00"), dict(network="", run="")],
                         ids=["network-key", "network", "run", "no-names"])
def test_a_frame_of_another_key_network_or_run_fails_authentication(other):
    params = dict(network_key=NETWORK_KEY, network=NETWORK, run=RUN) | other
    theirs = FrameKey(**params)
    data = encode(make_msg(), theirs)
    assert data[-16:] == reference_mac(data[:-16], **params)
    rejected(data, KEY, "unauthenticated", "authentication failed \\(wrong key, network or run\\)")
    assert_same(decode(data, theirs), make_msg())


def test_network_and_run_names_are_separated():
    """network "ab" + run "c" and network "a" + run "bc" derive different keys (0-separated)."""
    assert FrameKey(NETWORK_KEY, "ab", "c").derived != FrameKey(NETWORK_KEY, "a", "bc").derived


def test_an_unkeyed_frame_is_rejected_by_a_keyed_receiver():
    rejected(encode(make_msg()), KEY, "unauthenticated", "not authenticated \\(no MAC\\) but a network key is set")


def test_a_keyed_frame_is_rejected_by_a_receiver_without_a_key():
    rejected(encode(make_msg(), KEY), None, "unauthenticated", "this node has no key")


@pytest.mark.parametrize("key", [b"", b"short", b"x" * 15, "a string of 16+ chars"], ids=repr)
def test_network_keys_shorter_than_16_bytes_are_refused(key):
    with pytest.raises(MessageError, match="at least 16 bytes"):
        FrameKey(key, NETWORK, RUN)


def test_the_mac_is_checked_before_the_body_is_parsed():
    """A forged body is reported as an authentication failure, whatever is inside it."""
    junk = seal(b"DF\x02\x03\xc1 not msgpack", keyed=False) + b"\x00" * 16
    rejected(junk, KEY, "unauthenticated", "authentication failed")


# ---------------------------------------------------------------- rejections: the body
def test_body_not_msgpack_or_not_18_fields():
    raw = lambda body: seal(b"DF\x02\x02" + body, False)        # noqa: E731
    rejected(raw(b"\xc1"), reason="malformed", match="not a msgpack body")
    rejected(raw(msgpack.packb(fields_of()) + b"\x00"), reason="malformed", match="not a msgpack body")  # trailing
    rejected(raw(msgpack.packb(fields_of())[:-3]), reason="malformed", match="not a msgpack body")      # truncated
    for body in ([], fields_of()[:16], fields_of() + [0], {"src": "a"}, 18, "x" * 18, None):
        rejected(frame_of(body) if not isinstance(body, list) else frame_of(body), reason="malformed")
    for body in (fields_of()[:16], fields_of()[:13], fields_of() + [0], [None] * 18 + [0]):
        rejected(frame_of(body), reason="malformed", match="array of 18 fields")
    rejected(frame_of(fields_of()[:14]), reason="malformed", match="14 fields .the layout before the tree fields")
    rejected(frame_of(fields_of()[:17]), reason="malformed", match="17 fields .the layout before the channel start")
    rejected(raw(b"\xdc\x00\x21" + b"\x00" * 33), reason="malformed", match="not a msgpack body")  # 33 > 32 items


WRONG_TYPES = [
    ("epoch", 1.0), ("epoch", True), ("epoch", "1"), ("epoch", b"\x01"), ("epoch", None),
    ("dst_epoch", 0.0), ("dst_epoch", False), ("seq", 7.0), ("seq", [7]), ("seq", True),
    ("ack", -1.0), ("ack", None), ("ack_mask", 1.5), ("ack_mask", b""), ("n", 2.0), ("n", True), ("n", "2"),
    ("start", "0.25"), ("start", True), ("start", None), ("start", b"\x00" * 8), ("sent_at", [3.5]),
    ("sent_at", False), ("times", "x"), ("times", [0.5, 1.5, 2.5]), ("times", 0.5), ("times", None),
    ("mask", "x"), ("mask", 7), ("mask", [255]), ("values", 1.0), ("values", "v"), ("values", None),
    ("cleared", []), ("cleared", 0), ("cleared", "c"), ("seq_start", 1.0), ("seq_start", None),
    ("epoch", msgpack.ExtType(5, b"x")), ("start", msgpack.Timestamp(1, 0)),
]


@pytest.mark.parametrize("name,value", WRONG_TYPES, ids=[f"{n}={v!r}" for n, v in WRONG_TYPES])
def test_field_of_wrong_type(name, value):
    for keyed in (False, True):
        rejected(tampered(keyed=keyed, **{name: value}), KEY if keyed else None, "malformed",
                 f"field '{name}' has type {type(value).__name__}")


@pytest.mark.parametrize("value", [1, b"a", None, ["a"], "", True], ids=repr)
@pytest.mark.parametrize("name", ["src", "dst"])
def test_names_must_be_non_empty_strings(name, value):
    rejected(tampered(**{name: value}), reason="malformed", match=f"field '{name}' must be a non-empty name")


def test_names_longer_than_256_bytes_are_rejected():
    assert decode(tampered(src="é" * 128)).src == "é" * 128                   # 256 bytes
    rejected(tampered(src="x" * 257), reason="malformed", match="not a msgpack body")
    rejected(tampered(dst="é" * 129), reason="malformed", match="not a msgpack body")   # 258 bytes


def test_invalid_utf8_in_a_name_is_rejected():
    body = msgpack.packb(fields_of(), use_bin_type=True).replace(b"\xa1a", b"\xa1\xff", 1)
    rejected(seal(b"DF\x02\x02" + body, False), reason="malformed", match="not a msgpack body")


# each integer field over the edges: (field, lowest accepted, first refused above)
INT_RANGES = [("epoch", 0, 2**63), ("dst_epoch", 0, 2**63), ("seq", 0, 2**63), ("ack", -1, 2**63),
              ("ack_mask", 0, 2**64), ("n", 1, MAX_STATE_DIM + 1),
              ("seq_start", 0, 8)]   # (at most seq: make_msg's seq is 7)
EDGES = [-(2**63), -(2**31), -2, -1, 0, 1, 2**31, 2**32, 2**63 - 1, 2**63, 2**64 - 1]


@pytest.mark.parametrize("name,lo,hi", INT_RANGES, ids=[r[0] for r in INT_RANGES])
def test_integer_fields_over_their_whole_range(name, lo, hi):
    empty = make_msg(m=0)
    for value in EDGES + [lo - 1, lo, hi - 1, hi, 2, MAX_STATE_DIM]:
        if not -(2**63) <= value < 2**64:
            continue
        data = tampered(msg=empty, **{name: value})
        if lo <= value < hi:
            assert getattr(decode(data), name) == value
        else:
            rejected(data, reason="malformed", match=f"field '{name}' = {value} is outside \\[{lo}, {hi}\\)")


def test_integers_beyond_64_bits_cannot_be_encoded_in_msgpack():
    """msgpack has no integer type beyond uint64 / int64: a larger one cannot reach decode."""
    for value in (2**64, -(2**63) - 1):
        with pytest.raises(OverflowError):
            msgpack.packb(fields_of(seq=value))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e300, -9.3e9], ids=repr)
@pytest.mark.parametrize("name", ["start", "sent_at"])
def test_start_and_sent_at_must_be_finite_times(name, bad):
    rejected(tampered(**{name: bad}), reason="malformed", match=f"field '{name}' = .* is not a finite time")


def test_integer_start_and_float32_values_are_read_as_float64():
    fields = fields_of(start=0, sent_at=3)
    out = decode(frame_of(fields))
    assert out.start == 0.0 and isinstance(out.start, float) and out.sent_at == 3.0
    body = msgpack.packb(fields_of(), use_bin_type=True, use_single_float=True)
    assert decode(seal(b"DF\x02\x02" + body, False)).sent_at == 3.5


def test_times_field_sizes():
    rejected(tampered(times=b"\x00" * 7), reason="malformed", match="field 'times' has 7 bytes")
    rejected(tampered(times=b"\x00" * 14), reason="malformed", match="not a first time and whole gaps")
    rejected(tampered(WIDE | FULL, times=b"\x00" * 12), reason="malformed", match="not a first time and whole gaps")


def f8(*values) -> bytes:
    return struct.pack(f"<{len(values)}d", *values)


def keys_field(first: int, *gaps: int, wide: bool = False) -> bytes:
    return struct.pack("<q", first) + b"".join(struct.pack("<q" if wide else "<I", g) for g in gaps)


@pytest.mark.parametrize("times,wide", [(keys_field(500_000_000, 0, 10**9), False),
                                        (keys_field(500_000_000, 10**9, 0), False),
                                        (keys_field(500_000_000, -(10**9), 10**9, wide=True), True),
                                        (keys_field(500_000_000, 0, 1, wide=True), True)],
                         ids=["zero-gap", "zero-gap-last", "negative-wide-gap", "zero-wide-gap"])
def test_times_not_strictly_increasing(times, wide):
    rejected(tampered(FULL | (WIDE if wide else 0), times=times), reason="malformed",
             match="times are not strictly increasing")


def test_wide_time_gaps_that_overflow_int64_are_rejected():
    """Four gaps of 2^62 from 0 sum to 2^64: in int64 the keys would wrap to 2^62, -2^63,
    -2^62, 0 (not increasing, a repeated key, beyond the time limit)."""
    one = make_msg(n=1, m=5, start=-MAX_ABS_TIME, info=np.ones((5, 1, 1)), vec=np.ones((5, 1)),
                   times=np.arange(5.0))
    data = tampered(FULL | WIDE, msg=one, times=keys_field(0, *[2**62] * 4, wide=True))
    rejected(data, reason="malformed", match="times are not strictly increasing")
    # wide gaps up to the limits are accepted (an int64 gap is below 2^63: two of them span the range)
    big = int(MAX_ABS_TIME * 1e9)
    three = make_msg(n=1, m=3, start=-MAX_ABS_TIME, info=np.ones((3, 1, 1)), vec=np.ones((3, 1)),
                     times=np.array([-MAX_ABS_TIME, 0.0, MAX_ABS_TIME]))
    out = decode(tampered(FULL | WIDE, msg=three, times=keys_field(-big, big, big, wide=True)))
    assert out.times.tolist() == [-MAX_ABS_TIME, 0.0, MAX_ABS_TIME]
    rejected(tampered(FULL | WIDE, msg=three, times=keys_field(-big, big, big + 1, wide=True)), reason="malformed",
             match="exceeds")
    rejected(tampered(FULL | WIDE, msg=three, times=keys_field(-big, 2**63 - 1, 2**63 - 1, wide=True)),
             reason="malformed", match="not strictly increasing|exceeds")


def test_times_beyond_the_limit_are_rejected():
    big = int(MAX_ABS_TIME * 1e9)
    one = make_msg(n=1, m=1, start=-MAX_ABS_TIME, info=np.ones((1, 1, 1)), vec=np.ones((1, 1)), times=np.zeros(1))
    for first in (big + 1, -big - 1, 2**63 - 1, -(2**63)):
        rejected(tampered(msg=one, times=keys_field(first)), reason="malformed", match="a time exceeds")
    two = make_msg(n=1, m=2, start=-MAX_ABS_TIME, info=np.ones((2, 1, 1)), vec=np.ones((2, 1)), times=np.zeros(2))
    rejected(tampered(msg=two, times=keys_field(big - 10, 11)), reason="malformed", match="a time exceeds")
    assert decode(tampered(msg=two, times=keys_field(big - 10, 10))).times[-1] == big / 1e9


def test_time_before_start():
    # make_msg: times 0.5, 1.5, 2.5
    rejected(tampered(start=0.5000000011), reason="malformed", match="precedes the window start")
    rejected(tampered(start=100.0), reason="malformed", match="precedes the window start")
    assert decode(tampered(start=0.5)).start == 0.5        # the first time may equal start


def test_empty_messages_are_valid():
    for full in (True, False):
        out = decode(encode(make_msg(m=0, start=MAX_ABS_TIME, full=full)))
        assert len(out) == 0 and out.info.shape == (0, 2, 2) and out.vec.shape == (0, 2)


# cleared times (partial messages only)
def test_cleared_times_round_trip():
    msg = make_msg(full=False, cleared=np.array([0.25, 1.0, 9.0]))
    assert_same(decode(encode(msg)), msg)


@pytest.mark.parametrize("cleared,match", [
    (struct.pack("<q", 10**9)[:7], "not a whole number of int64"),
    (struct.pack("<qq", 2 * 10**9, 10**9), "not strictly increasing"),
    (struct.pack("<qq", 10**9, 10**9), "not strictly increasing"),
    (struct.pack("<q", int(MAX_ABS_TIME * 1e9) + 1), "not strictly increasing times"),
    (struct.pack("<q", -(2**63)), "not strictly increasing times|precedes the window start"),
    (struct.pack("<q", 1_500_000_000), "both cleared and carried"),
    (struct.pack("<q", 100_000_000), "precedes the window start"),
])
def test_cleared_rules(cleared, match):
    rejected(tampered(0, cleared=cleared), reason="malformed", match=match)


def test_a_full_message_clears_nothing():
    rejected(tampered(FULL, cleared=struct.pack("<q", 10**9)), reason="malformed",
             match="a full message clears no time")


def test_too_many_blocks_or_cleared_times():
    m = MAX_BLOCKS
    ones = dict(n=1, m=m, start=0.0, times=np.arange(1, m + 1) * 1e-6, info=np.ones((m, 1, 1)), vec=np.ones((m, 1)))
    assert len(decode(encode(make_msg(**ones)))) == m
    over = make_msg(**{**ones, "m": m + 1, "times": np.arange(1, m + 2) * 1e-6, "info": np.ones((m + 1, 1, 1)),
                       "vec": np.ones((m + 1, 1))})
    rejected(encode(over), reason="malformed", match=f"more than {MAX_BLOCKS} blocks")
    cleared = struct.pack(f"<{m + 1}q", *range(10**10, 10**10 + m + 1))
    rejected(tampered(0, cleared=cleared), reason="malformed", match=f"more than {MAX_BLOCKS} cleared times")


# mask and values sizes: make_msg() has m = 3 blocks of n = 2: 5 numbers, 1 mask byte each
@pytest.mark.parametrize("changes,match", [
    (dict(mask=b"\x1f\x1f"), "field 'mask' has 2 bytes, expected 3"),
    (dict(mask=b"\x1f" * 4), "field 'mask' has 4 bytes, expected 3"),
    (dict(mask=b""), "field 'mask' has 0 bytes, expected 3"),
    (dict(n=3), "field 'mask' has 3 bytes, expected 6"),           # 9 numbers: 2 bytes per block
    (dict(n=1), "field 'values' has 120 bytes, expected"),           # 2 numbers: 1 byte per block
    (dict(mask=b"\x1f\x1f\x0f"), "field 'values' has 120 bytes, expected 112"),
    (dict(mask=b"\x1f\x1f\xff"), "field 'values' has 120 bytes, expected 120|outside"),
    (dict(values=b"\x00" * 112), "field 'values' has 112 bytes, expected 120"),
    (dict(values=b"\x00" * 121), "field 'values' has 121 bytes, expected 120"),
    (dict(times=keys_field(500_000_000, 10**9)), "field 'mask' has 3 bytes, expected 2"),
])
def test_sizes_that_do_not_match_n_and_the_number_of_times(changes, match):
    data = tampered(**changes)
    if changes == dict(mask=b"\x1f\x1f\xff"):
        # bits beyond the 5 numbers of a block are ignored (padding): the message is the same
        assert_same(decode(data), make_msg())
        return
    rejected(data, reason="malformed", match=match)


def values_with(index: int, bad: float, msg: InfoMessage | None = None) -> bytes:
    msg = msg if msg is not None else make_msg()
    values = bytearray(fields_of(msg)[12])
    values[8 * index:8 * index + 8] = struct.pack("<d", bad)
    return tampered(msg=msg, values=bytes(values))


@pytest.mark.parametrize("bad", [math.nan, -math.nan, math.inf, -math.inf], ids=["nan", "-nan", "inf", "-inf"])
def test_non_finite_values_anywhere_are_rejected(bad):
    for index in range(15):      # 3 blocks of 5 numbers
        rejected(values_with(index, bad), reason="malformed", match="field 'values' contains NaN or inf")


def test_signalling_nan_payload_is_rejected():
    values = bytearray(fields_of()[12])
    values[0:8] = bytes.fromhex("010000000000f07f")      # sNaN, little-endian
    rejected(tampered(values=bytes(values)), reason="malformed", match="NaN or inf")


def test_information_and_vector_limits():
    top_info = np.nextafter(MAX_ABS_INFO, np.inf)
    top_vec = np.nextafter(MAX_ABS_VEC, np.inf)
    at_limit = make_msg(m=1, times=np.array([1.0]), info=np.diag([MAX_ABS_INFO, MAX_ABS_INFO])[None],
                        vec=np.array([[MAX_ABS_VEC, -MAX_ABS_VEC]]))
    assert_same(decode(encode(at_limit)), at_limit)
    rejected(encode(make_msg(m=1, times=np.array([1.0]), info=np.diag([top_info, 1.0])[None], vec=np.ones((1, 2)))),
             reason="malformed", match="information entry exceeds 1e\\+12")
    rejected(encode(make_msg(m=1, times=np.array([1.0]), info=np.eye(2)[None], vec=np.array([[0.0, -top_vec]]))),
             reason="malformed", match="information-vector entry exceeds 1e\\+18")
    # a huge finite number anywhere (1e308: twice it is inf) is refused
    for index in range(15):
        rejected(values_with(index, 1e308), reason="malformed", match="exceeds")


def test_largest_state_dimension_is_accepted():
    n = MAX_STATE_DIM
    msg = make_msg(n=n, m=2, times=np.array([1.0, 2.0]), info=np.stack([np.eye(n), np.ones((n, n))]),
                   vec=np.ones((2, n)))
    assert_same(decode(encode(msg)), msg)
    rejected(tampered(msg=make_msg(m=0), n=n + 1), reason="malformed", match="outside \\[1, 65\\)")


# ---------------------------------------------------------------- positive semi-definiteness
def with_block(k: int, block: np.ndarray, naive: bool = False) -> bytes:
    msg = make_msg(n=block.shape[0], m=3, full=not naive, naive=naive)
    info = msg.info.copy()
    info[k] = block
    return encode(InfoMessage(**{**msg.__dict__, "info": info}))


@pytest.mark.parametrize("k", [0, 1, 2])
@pytest.mark.parametrize("block", [
    np.array([[1.0, 2.0], [2.0, 1.0]]),                 # indefinite
    np.array([[-1.0, 0.0], [0.0, 0.0]]),                # negative
    np.array([[-1e-300, 0.0], [0.0, 0.0]]),             # negative, however tiny: no floor without scale
    np.array([[1e6, 0.0], [0.0, -1e-2]]),               # negative next to a large entry
], ids=["indefinite", "negative", "tiny-negative", "negative-next-to-large"])
def test_block_not_positive_semidefinite(k, block):
    assert brute_force_indefinite(block)
    err = rejected(with_block(k, block), reason="malformed", match="is not positive semi-definite")
    assert f"t={0.5 + k}" in str(err)        # the message names the offending state time


def test_naive_messages_carry_increments_that_need_not_be_positive():
    block = np.array([[1.0, 2.0], [2.0, 1.0]])
    out = decode(with_block(1, block, naive=True))
    assert out.naive and np.array_equal(out.info[1], block)


def test_psd_tolerance_is_relative_to_each_diagonal_entry():
    """Rounding of a difference of information matrices is relative to each entry's own
    diagonal: -1e-16 of it passes; a negative eigenvalue next to a huge diagonal entry does
    not hide (the scaled test); a rank-one block with a tiny diagonal entry passes."""
    ok = np.array([[1e6, 0.0], [0.0, -1e-16 * 1e6]])
    assert not brute_force_indefinite(ok)
    assert decode(with_block(1, ok)) is not None
    v = np.array([1e-6, 1.0])
    assert decode(with_block(1, np.outer(v, v))) is not None
    L = np.diag([4.0, 1e11, 0.0])
    L[0, 2] = L[2, 0] = 1e3
    assert np.linalg.eigvalsh(L)[0] < -100 and brute_force_indefinite(L)
    rejected(with_block(1, L), reason="malformed", match="not positive semi-definite")
    assert decode(with_block(1, np.zeros((2, 2)))) is not None


def _not_psd_reference(info: np.ndarray) -> int | None:
    """The scaled eigenvalue test of the docs on every block, no shortcut."""
    if not len(info):
        return None
    d = np.diagonal(info, axis1=1, axis2=2)
    floor = PSD_RTOL * np.abs(info).max(axis=(1, 2))
    s = 1.0 / np.sqrt(np.maximum(d, 0.0) + np.where(floor > 0, floor, 1.0)[:, None])
    bad = np.linalg.eigvalsh(info * s[:, :, None] * s[:, None, :])[:, 0] < -PSD_SCALED_ATOL
    return int(np.argmax(bad)) if bad.any() else None


def test_psd_shortcut_decides_like_the_full_test() -> None:
    """The diagonal-dominance shortcut of ``_not_psd`` never changes a decision; and the
    decision agrees with the brute-force test on the unscaled blocks."""
    rng = np.random.default_rng(7)
    decisions = set()
    for _ in range(3000):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 5))
        kind = int(rng.integers(4))
        if kind == 0:   # diagonal, some entries zero or slightly negative
            info = np.zeros((m, n, n))
            for b in range(m):
                info[b][np.diag_indices(n)] = rng.choice([0.0, 4.0, -1e-7, -1e-5, 1e-12], n)
        elif kind == 1:   # diagonally dominant up to a relative margin around zero
            A = rng.normal(size=(m, n, n))
            info = 0.5 * (A + A.transpose(0, 2, 1))
            off = np.abs(info).sum(axis=2) - np.abs(np.diagonal(info, axis1=1, axis2=2))
            margin = rng.choice([-1e-3, -1e-8, 0.0, 1e-12, 1e-3], (m, n))
            info[:, np.arange(n), np.arange(n)] = off * (1.0 + margin)
        elif kind == 2:   # rank-deficient with a negative eigenvalue near the tolerance
            v = rng.normal(size=(m, n, 1))
            info = v @ v.transpose(0, 2, 1) - 10.0 ** rng.uniform(-9, -4) * np.eye(n)
        else:   # random symmetric, scaled over many orders of magnitude
            A = rng.normal(size=(m, n, n))
            info = (A @ A.transpose(0, 2, 1) - rng.uniform(0, 2) * np.eye(n)) * 10.0 ** rng.uniform(-10, 10)
        info = 0.5 * (info + info.transpose(0, 2, 1))
        expected = _not_psd_reference(info)
        assert wire._not_psd(info) == expected
        # away from the boundary the brute force agrees (within 1 % of the tolerance it may not)
        for b in range(m):
            margin = _scaled_min_eig(info[b]) + PSD_SCALED_ATOL
            if abs(margin) > 0.01 * PSD_SCALED_ATOL:
                assert brute_force_indefinite(info[b]) == (margin < 0)
        decisions.add(expected is None)
    assert decisions == {True, False}


def test_decode_of_diagonal_blocks_decides_like_the_full_test() -> None:
    """decode accepts blocks whose mask carries only diagonal information entries without the
    dominance test when no diagonal value is negative: it must decide exactly like the scaled
    eigenvalue test on every block (negative, -0.0, subnormal and zero diagonals; repeated
    masks, whose layouts decode caches), and decode the same numbers as were sent."""
    rng = np.random.default_rng(11)
    decisions = set()
    choices = [0.0, -0.0, 4.0, 1e12, 5e-324, -5e-324, -1e-7, -1e-5, 1e-12, 3.5]
    for _ in range(2000):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 4))
        info = np.zeros((m, n, n))
        for b in range(m):
            info[b][np.diag_indices(n)] = rng.choice(choices, n)
        vec = rng.choice([0.0, 1.0, -2.0], (m, n))
        times = 1.0 + 0.1 * np.arange(m)
        msg = InfoMessage("a", "b", 1, 0, 1.0, 1.0, times, info, vec, full=False)
        expected = _not_psd_reference(info)
        try:
            got = decode(encode(msg))
        except MessageError as exc:
            assert expected is not None and "positive semi-definite" in str(exc)
            decisions.add(False)
            continue
        assert expected is None
        decisions.add(True)
        # (a zero, -0.0 included, is not carried and arrives as +0.0)
        assert got.info.tobytes() == (info + 0.0).tobytes() and got.vec.tobytes() == (vec + 0.0).tobytes()
    assert decisions == {True, False}


def _scaled_min_eig(L: np.ndarray) -> float:
    d = np.maximum(np.diag(L), 0.0)
    f = PSD_RTOL * np.abs(L).max() or 1.0
    s = 1.0 / np.sqrt(d + f)
    return float(np.linalg.eigvalsh(L * s[:, None] * s[None, :])[0])


# ---------------------------------------------------------------- sizes
def _bin(length: int) -> int:
    return length + (2 if length < 2**8 else 3 if length < 2**16 else 5)


def _str(s: str) -> int:
    b = len(s.encode())
    return b + (1 if b < 32 else 2 if b < 2**8 else 3)


def _int(x: int) -> int:
    """Bytes of a msgpack integer (the smallest encoding, as msgpack specifies)."""
    if 0 <= x < 128 or -32 <= x < 0:
        return 1
    if x >= 0:
        return 2 if x < 2**8 else 3 if x < 2**16 else 5 if x < 2**32 else 9
    return 2 if x >= -(2**7) else 3 if x >= -(2**15) else 5 if x >= -(2**31) else 9


def predicted_size(msg: InfoMessage, keyed: bool) -> int:
    """Bytes of a frame, from the layout: header, body fields, checksum, MAC."""
    m, n = msg.vec.shape
    width = n * (n + 1) // 2 + n
    nonzero = int(np.count_nonzero(msg.info[:, *np.triu_indices(n)])) + int(np.count_nonzero(msg.vec))
    keys = time_keys(msg.times)
    gap = 8 if m > 1 and np.diff(keys).max() >= 2**32 else 4
    body = (3 + _str(msg.src) + _str(msg.dst)      # array 16 header: 18 fields
            + sum(_int(x) for x in (msg.epoch, msg.dst_epoch, msg.seq, msg.ack, msg.ack_mask, n))
            + 9 + 9
            + _bin(8 + gap * (m - 1) if m else 0) + _bin(m * ((width + 7) // 8)) + _bin(8 * nonzero)
            + _bin(8 * len(msg.cleared))
            + _int(msg.tree_term) + _str(msg.tree_root) + _str(msg.parent) + _int(msg.seq_start))
    return 4 + body + 4 + (16 if keyed else 0)


SIZE_CASES = [(0, 1), (1, 1), (1, 4), (5, 4), (31, 1), (32, 1), (10, 6), (100, 4), (300, 8), (3000, 4), (3, 64)]


@pytest.mark.parametrize("keyed", [False, True])
@pytest.mark.parametrize("m,n", SIZE_CASES)
def test_size_matches_the_layout(m, n, keyed):
    rng = np.random.default_rng(m * 100 + n)
    for sparse in (False, True):
        msg = make_msg(n=n, m=m, epoch=2**62 + 5, dst_epoch=300, seq=70_000, seq_start=69_990, ack=-1, ack_mask=2**40,
                       src="node-17", dst="node-3", times=np.cumsum(rng.uniform(1e-3, 2.0, m)), start=0.0)
        if sparse:   # position fixes: only the first two diagonal entries and vector entries
            info = np.zeros((m, n, n))
            info[:, 0, 0] = info[:, min(1, n - 1), min(1, n - 1)] = 4.0
            vec = np.zeros((m, n))
            vec[:, :2] = 1.5
            msg = InfoMessage(**{**msg.__dict__, "info": info, "vec": vec, "full": False,
                                 "cleared": np.array([1e4, 2e4])})
        assert len(encode(msg, KEY if keyed else None)) == predicted_size(msg, keyed)


def test_a_position_fix_on_a_4d_state_costs_38_bytes():
    """One more 2-D position block (n = 4) adds a 4-byte time gap, 2 mask bytes (14 bits)
    and 4 float64 numbers: 38 bytes; a dense block adds 4 + 2 + 14 * 8 = 118 bytes."""
    def size(m, dense):
        info = np.tile(np.diag([4.0, 4.0, 0.0, 0.0]), (m, 1, 1)) if not dense else np.tile(
            np.eye(4) + 0.1, (m, 1, 1))
        vec = np.tile([1.0, 2.0, 0.0, 0.0] if not dense else [1.0, 2.0, 3.0, 4.0], (m, 1))
        return len(encode(make_msg(n=4, m=m, info=info, vec=vec, times=0.5 + 0.1 * np.arange(m))))
    assert size(11, False) - size(10, False) == 4 + 2 + 4 * 8 == 38
    assert size(11, True) - size(10, True) == 4 + 2 + 14 * 8 == 118


# ---------------------------------------------------------------- the worked example of the docs
DOC = Path(__file__).resolve().parents[1] / "docs" / "wire-format.md"


def test_worked_example_of_the_docs():
    """docs/wire-format.md shows a message, its bytes and a byte-by-byte reading: the code
    runs, the bytes are what encode writes and what the reference encoder writes, every
    line of the reading matches its offset, and the keyed variant is as described."""
    text = DOC.read_text(encoding="utf-8")
    example = text[text.index("## Worked example"):text.index("## Versioning")]
    blocks = re.findall(r"```(\w*)\n(.*?)```", example, re.S)
    code = [b for lang, b in blocks if lang == "python"]
    dumps = [b for lang, b in blocks if lang == ""]
    assert len(code) == 1 and len(dumps) == 2
    scope: dict = {}
    exec(code[0], scope)                       # noqa: S102 (the documented example, run as shown)
    msg = scope["msg"]
    data = bytes.fromhex(dumps[0].replace("\n", ""))
    assert encode(msg) == data == reference_frame(msg)
    assert f"Without a key, {len(data)} bytes" in example
    lines = [line for line in dumps[1].splitlines() if line.strip()]
    covered = 0
    for line in lines:
        m = re.match(r"^([0-9a-f]{4})\s+((?:[0-9a-f]{2} )*[0-9a-f]{2})\s{2,}", line)
        assert m, line
        offset, shown = int(m.group(1), 16), bytes.fromhex(m.group(2))
        assert data[offset:offset + len(shown)] == shown, line
        covered += len(shown)
    assert covered == len(data)                # the reading covers every byte once
    crc = re.search(r"crc32 0x([0-9a-f]{8}) of bytes 0000-([0-9a-f]{4})", example)
    assert int(crc.group(1), 16) == zlib.crc32(data[:int(crc.group(2), 16) + 1])
    # the keyed variant
    keyed_text = re.search(r'network key `b"(\w+)"`, network `"([\w-]+)"` and run `"([\w-]+)"`', example)
    network_key, network, run = keyed_text.group(1).encode(), keyed_text.group(2), keyed_text.group(3)
    keyed = encode(msg, FrameKey(network_key, network, run))
    assert f"{len(keyed)} bytes" in example and keyed[3] == 0x01
    assert keyed[:3] == data[:3] and keyed[4:len(data) - 4] == data[4:-4]
    assert keyed[-16:] == reference_mac(keyed[:-16], network_key, network, run)
    assert decode(keyed, FrameKey(network_key, network, run)).ack_mask == 3


def test_one_block_is_encoded_as_the_array_path_encodes_it():
    """A message of one block (the steady state) is encoded on Python floats: its mask, values
    and time are the bytes the array path gives for the same block, which a message of that
    block twice (two blocks: the array path) carries twice. Zeros, negative zeros, tiny and
    huge numbers, times on and between nanoseconds, every state dimension up to 6."""
    rng = np.random.default_rng(15)
    for trial in range(400):
        n = int(rng.integers(1, 7))
        A = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-8, 6)
        L = A @ A.T
        L[rng.random((n, n)) < 0.3] = 0.0
        L = np.triu(L) + np.triu(L, 1).T
        v = rng.normal(size=n) * 10.0 ** rng.integers(-8, 9)
        v[rng.random(n) < 0.3] = 0.0
        if trial % 5 == 0:
            L[:] = 0.0
        if trial % 7 == 0:
            v[0] = -0.0
        t = float(rng.uniform(-1e6, 1e6)) if trial % 2 else round(float(rng.uniform(0, 1e4)), 9)
        # (naive: the blocks need not be positive semi-definite to be decoded back)
        one = InfoMessage("a", "b", 1, 2, t - 1.0, 3.0, np.array([t]), L[None], v[None], full=False, naive=True)
        two = InfoMessage("a", "b", 1, 2, t - 1.0, 3.0, np.array([t, t + 1.0]), np.stack([L, L]), np.stack([v, v]),
                          full=False, naive=True)
        b1 = msgpack.unpackb(encode(one)[4:-4])
        b2 = msgpack.unpackb(encode(two)[4:-4])
        assert b1[10] == b2[10][:8] == time_keys(np.array([t])).astype("<i8").tobytes()
        assert b1[11] * 2 == b2[11] and b1[12] * 2 == b2[12]
        back = decode(encode(one))
        assert back.times.tobytes() == (time_keys(np.array([t])) / 1e9).tobytes()
        assert np.array_equal(back.info[0], L) and np.array_equal(back.vec[0], v)
