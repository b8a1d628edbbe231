"""The fusion message format (dfusion.wire): round trip, every rejection, HMAC, size.

The layout under test is documented in docs/wire-format.md.
"""
from __future__ import annotations

import hashlib
import hmac
import math
import re
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import DfusionError, MessageError
from dfusion.wire import (
    decode,
    encode,
    InfoMessage,
    MAX_ABS_INFO,
    MAX_ABS_TIME,
    MAX_ABS_VEC,
    MAX_MESSAGE_BYTES,
    MAX_STATE_DIM,
    PSD_RTOL,
    VERSION,
)
from dfusion import wire

KEY = b"network-key-for-tests"
FIELDS = ("src", "dst", "epoch", "seq", "n", "start", "sent_at", "times", "info", "vec")


# ---------------------------------------------------------------- helpers
def sym_upper(S: np.ndarray) -> np.ndarray:
    """The symmetric matrices whose upper triangles are those of ``S`` (bit-exact symmetry)."""
    U = np.triu(S)
    return U + np.swapaxes(np.triu(S, 1), -1, -2)


def make_msg(n: int = 2, m: int = 3, seed: int = 0, **kw) -> InfoMessage:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n, n))
    fields = dict(
        src="a",
        dst="b",
        epoch=12345,
        seq=7,
        start=0.25,
        sent_at=3.5,
        times=0.5 + np.arange(m, dtype=float),
        info=sym_upper(A @ np.swapaxes(A, 1, 2)),
        vec=rng.normal(size=(m, n)),
    )
    fields.update(kw)
    return InfoMessage(**fields)


def body_of(msg: InfoMessage) -> dict:
    """The body map exactly as :func:`encode` builds it (to be tampered with)."""
    m, n = msg.vec.shape
    iu = np.triu_indices(n)
    return {
        "src": msg.src,
        "dst": msg.dst,
        "epoch": msg.epoch,
        "seq": msg.seq,
        "n": n,
        "start": float(msg.start),
        "sent_at": float(msg.sent_at),
        "times": np.asarray(msg.times, "<f8").tobytes(),
        "info": np.ascontiguousarray(msg.info[:, iu[0], iu[1]], "<f8").tobytes(),
        "vec": np.asarray(msg.vec, "<f8").tobytes(),
    }


def envelope(body, *, v=VERSION, key: bytes | None = None, mac=None, drop=(), extra=None) -> bytes:
    """Pack ``body`` (a dict, or raw bytes) into an envelope; ``key`` computes the MAC."""
    raw = body if isinstance(body, (bytes, bytearray)) else msgpack.packb(body, use_bin_type=True)
    if key is not None:
        mac = hmac.new(key, raw, hashlib.sha256).digest()
    env = {"v": v, "body": raw, "mac": mac}
    env.update(extra or {})
    for k in drop:
        del env[k]
    return msgpack.packb(env, use_bin_type=True)


def tampered(key: bytes | None = None, msg: InfoMessage | None = None, **changes) -> bytes:
    """A valid message with body fields replaced (``None`` value: field removed)."""
    body = body_of(msg or make_msg())
    for k, v in changes.items():
        if v is None:
            del body[k]
        else:
            body[k] = v
    return envelope(body, key=key)


def f8(*values) -> bytes:
    return np.array(values, "<f8").tobytes()


def rejected(data, key: bytes | None = None, match: str | None = None) -> MessageError:
    with pytest.raises(MessageError, match=match) as info:
        decode(data, key)
    assert isinstance(info.value, ValueError) and isinstance(info.value, DfusionError)
    assert str(info.value), "an empty error message is not a clear one"
    return info.value


def assert_same(a: InfoMessage, b: InfoMessage) -> None:
    """Bit-exact equality (so -0.0 != 0.0 and NaN payloads would count)."""
    assert (a.src, a.dst, a.epoch, a.seq) == (b.src, b.dst, b.epoch, b.seq)
    assert np.float64(a.start).tobytes() == np.float64(b.start).tobytes()
    assert np.float64(a.sent_at).tobytes() == np.float64(b.sent_at).tobytes()
    for name in ("times", "info", "vec"):
        x, y = np.asarray(getattr(a, name), "<f8"), np.asarray(getattr(b, name), "<f8")
        assert x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name


# ---------------------------------------------------------------- round trip
finite = st.floats(-1e9, 1e9, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 8),
    m=st.integers(0, 50),
    rank=st.integers(1, 8),
    seed=st.integers(0, 2**32 - 1),
    log_scale=st.integers(-150, 9),   # entries (sums of up to 8 squares) stay within MAX_ABS_INFO
    t0=finite,
    start_back=st.floats(0.0, 1e6),
    sent_at=finite,
    epoch=st.integers(0, 2**64 - 1),
    seq=st.integers(0, 2**64 - 1),
    src=st.text(max_size=40),
    dst=st.text(max_size=40),
    keyed=st.booleans(),
)
def test_round_trip_is_bit_exact(n, m, rank, seed, log_scale, t0, start_back, sent_at, epoch, seq, src, dst, keyed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n, rank)) * 10.0 ** (log_scale / 2)   # rank < n: singular PSD blocks
    info = sym_upper(A @ np.swapaxes(A, 1, 2))
    times = t0 + np.cumsum(rng.uniform(1e-3, 10.0, size=m))
    assert m == 0 or np.all(np.diff(times) > 0)
    msg = InfoMessage(
        src=src, dst=dst, epoch=epoch, seq=seq,
        start=(times[0] if m else t0) - start_back,
        sent_at=sent_at,
        times=times,
        info=info.reshape(m, n, n),
        vec=rng.normal(size=(m, n)) * 10.0 ** log_scale,
    )
    key = KEY if keyed else None
    data = encode(msg, key)
    out = decode(data, key)
    assert_same(out, msg)
    assert out.n == n and len(out) == m
    assert out.info.shape == (m, n, n) and out.vec.shape == (m, n) and out.times.shape == (m,)
    # the decoded arrays are the receiver's own, writable copies
    assert out.info.flags.writeable and out.vec.flags.writeable and out.times.flags.writeable
    assert encode(out, key) == data


def test_round_trip_of_extreme_but_valid_values():
    tiny = np.finfo(float).smallest_subnormal
    msg = make_msg(
        n=2, m=3, start=-MAX_ABS_TIME, sent_at=-0.0,
        times=np.array([-MAX_ABS_TIME, -0.0, MAX_ABS_TIME]),
        info=np.array([[[MAX_ABS_INFO, 0.0], [0.0, MAX_ABS_INFO]], [[tiny, 0.0], [0.0, 0.0]], np.zeros((2, 2))]),
        vec=np.array([[-0.0, MAX_ABS_VEC], [tiny, -tiny], [0.0, 0.0]]),
        epoch=2**63 - 1, seq=0, src="ñødé/α", dst="",
    )
    assert_same(decode(encode(msg)), msg)


@pytest.mark.parametrize("field, value, words", [
    ("times", 1e300, "exceeds"),
    ("start", -1e12, "exceeds"),
    ("info", 1e13, "information entry exceeds"),
    ("vec", 1e19, "information-vector entry exceeds"),
])
def test_values_beyond_the_limits_are_rejected(field, value, words):
    msg = make_msg(n=2, m=2, times=np.array([1.0, 2.0]), start=0.0)
    kw = dict(msg.__dict__)
    if field == "times":
        kw["times"] = np.array([1.0, value])
    elif field == "start":
        kw["start"] = value
    elif field == "info":
        kw["info"] = np.array([np.eye(2), np.eye(2) * value])
    else:
        kw["vec"] = np.array([[0.0, 0.0], [value, 0.0]])
    rejected(encode(InfoMessage(**kw)), match=words)


def test_times_closer_than_the_resolution_are_rejected():
    msg = make_msg(n=2, m=2, times=np.array([1.0, 1.0 + 0.4e-9]), start=0.0)
    rejected(encode(msg), match="closer than")


def test_bytearray_and_memoryview_are_accepted():
    data = encode(make_msg())
    assert_same(decode(bytearray(data)), make_msg())
    assert_same(decode(memoryview(data)), make_msg())


def test_packed_upper_triangle_is_row_major():
    """n = 3: info holds L00 L01 L02 L11 L12 L22 (docs/wire-format.md)."""
    L = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]]) + 10 * np.eye(3)
    msg = make_msg(n=3, m=1, info=L[None], vec=np.array([[7.0, 8.0, 9.0]]), times=np.array([1.0]))
    body = msgpack.unpackb(msgpack.unpackb(encode(msg))["body"])
    assert np.frombuffer(body["info"], "<f8").tolist() == [11.0, 2.0, 3.0, 14.0, 5.0, 16.0]
    assert np.frombuffer(body["vec"], "<f8").tolist() == [7.0, 8.0, 9.0]
    assert body["n"] == 3 and list(body) == list(FIELDS)


def test_any_field_order_and_unknown_fields_are_accepted():
    body = body_of(make_msg())
    shuffled = {k: body[k] for k in reversed(FIELDS)}
    shuffled["future_field"] = [1, 2, 3]
    data = envelope(shuffled, extra={"also_new": {"x": 1}})
    assert_same(decode(data), make_msg())


def test_other_msgpack_encodings_of_the_same_values_are_accepted():
    """Integers for start/sent_at, float32 floats: decoded to the same float64."""
    body = body_of(make_msg())
    body["start"] = 0          # msgpack int
    raw = msgpack.packb(body, use_bin_type=True, use_single_float=True)   # sent_at as float32
    out = decode(envelope(raw))
    assert out.start == 0.0 and isinstance(out.start, float)
    assert out.sent_at == 3.5


# ---------------------------------------------------------------- rejections: envelope
@pytest.mark.parametrize("data", ["text", None, 42, [b"x"], {"v": 1}], ids=repr)
def test_not_bytes(data):
    rejected(data, match="must be bytes")


@pytest.mark.parametrize(
    "data",
    [b"", b"\xc1", b"\x83\xa1v", b"\xdb\xff\xff\xff\xff", msgpack.packb({"v": 1}) + b"\x00", b"\x81\x01\x02"],
    ids=["empty", "reserved-byte", "truncated", "str-longer-than-data", "trailing-bytes", "int-map-key"],
)
def test_not_msgpack(data):
    rejected(data, match="not a msgpack message")


def test_every_truncation_of_a_valid_message_is_rejected():
    data = encode(make_msg(), KEY)
    for cut in range(len(data)):
        rejected(data[:cut], match="not a msgpack message")
        rejected(data[:cut], KEY, match="not a msgpack message")


@pytest.mark.parametrize("obj", [[1, 2], 1, "x", None, b"bytes", 1.5, True], ids=repr)
def test_envelope_not_a_map(obj):
    rejected(msgpack.packb(obj, use_bin_type=True), match="not a map")


@pytest.mark.parametrize("obj", [[1, 2], 1, "x", None], ids=repr)
def test_body_not_a_map(obj):
    rejected(envelope(msgpack.packb(obj, use_bin_type=True)), match="not a map")


def test_body_not_msgpack():
    rejected(envelope(b"\xc1garbage"), match="not a msgpack message")
    body = msgpack.packb(body_of(make_msg()), use_bin_type=True)
    rejected(envelope(body + b"\x00"), match="not a msgpack message")   # trailing bytes in the body


@pytest.mark.parametrize("v", [0, 2, -1, 2**64 - 1])
def test_unknown_version(v):
    rejected(envelope(body_of(make_msg()), v=v), match=f"unknown message version {v}")


@pytest.mark.parametrize("v", [True, False, 1.0, "1", None, b"\x01"], ids=repr)
def test_version_of_wrong_type(v):
    rejected(envelope(body_of(make_msg()), v=v), match="field 'v' has type")


@pytest.mark.parametrize("name", ["v", "body"])
def test_envelope_field_missing(name):
    rejected(envelope(body_of(make_msg()), drop=(name,)), match=f"no field '{name}'")


@pytest.mark.parametrize("body", ["a string", 1, None, [1]], ids=repr)
def test_body_of_wrong_type(body):
    data = msgpack.packb({"v": 1, "body": body, "mac": None}, use_bin_type=True)
    rejected(data, match="field 'body' has type")


def test_message_larger_than_the_limit():
    rejected(b"\x00" * (MAX_MESSAGE_BYTES + 1), match="exceeds the limit")


# ---------------------------------------------------------------- rejections: body
@pytest.mark.parametrize("name", FIELDS)
def test_body_field_missing(name):
    rejected(tampered(**{name: None}), match=f"no field '{name}'")
    rejected(tampered(KEY, **{name: None}), KEY, match=f"no field '{name}'")


WRONG_TYPES = [
    ("src", 1), ("src", b"a"), ("src", ["a"]),
    ("dst", 2.0), ("dst", b"b"), ("dst", True),
    ("epoch", 1.0), ("epoch", True), ("epoch", False), ("epoch", "1"), ("epoch", b"\x01"),
    ("seq", 7.0), ("seq", True), ("seq", "7"), ("seq", [7]),
    ("n", 2.0), ("n", True), ("n", "2"), ("n", {"n": 2}),
    ("start", "0.25"), ("start", True), ("start", [0.25]), ("start", b"\x00" * 8),
    ("sent_at", "3.5"), ("sent_at", False), ("sent_at", {}),
    ("times", "x"), ("times", [0.5, 1.5, 2.5]), ("times", 0.5),
    ("info", "x"), ("info", [1.0] * 9), ("info", 1),
    ("vec", "x"), ("vec", [1.0] * 6), ("vec", True),
]


@pytest.mark.parametrize("name,value", WRONG_TYPES, ids=[f"{n}={v!r}" for n, v in WRONG_TYPES])
def test_body_field_of_wrong_type(name, value):
    rejected(tampered(**{name: value}), match=f"field '{name}' has type {type(value).__name__}")


def test_none_is_a_wrong_type_not_a_missing_field():
    data = envelope({**body_of(make_msg()), "seq": None})
    rejected(data, match="field 'seq' has type NoneType")


@pytest.mark.parametrize("n", [0, -1, MAX_STATE_DIM + 1, 2**40, -(2**63)])
def test_state_dimension_out_of_range(n):
    rejected(tampered(n=n), match=f"state dimension {n} out of range")


def test_largest_state_dimension_is_accepted():
    n = MAX_STATE_DIM
    msg = make_msg(n=n, m=1, info=np.eye(n)[None], vec=np.ones((1, n)), times=np.array([1.0]))
    assert decode(encode(msg)).n == n
    assert decode(tampered(msg=make_msg(m=0, n=2), n=n, info=b"", vec=b"", times=b"")).n == n


@pytest.mark.parametrize("field,value", [("seq", -1), ("epoch", -1), ("seq", -(2**63)), ("epoch", -(2**63))])
def test_negative_seq_or_epoch(field, value):
    rejected(tampered(**{field: value}), match="negative sequence number or epoch")


def test_largest_seq_and_epoch_are_accepted():
    out = decode(tampered(seq=2**64 - 1, epoch=2**64 - 1))
    assert out.seq == out.epoch == 2**64 - 1


def test_times_not_whole_float64():
    rejected(tampered(times=b"\x00" * 23), match="'times' is not a whole number of float64")
    rejected(tampered(times=b"\x00"), match="'times' is not a whole number of float64")


# a message of m=3 blocks of n=2: times 24 bytes, info 3*3*8 = 72, vec 3*2*8 = 48
@pytest.mark.parametrize(
    "changes,match",
    [
        (dict(info=b"\x00" * 64), "field 'info' has 64 bytes, expected 72"),
        (dict(info=b"\x00" * 80), "field 'info' has 80 bytes, expected 72"),
        (dict(info=b""), "field 'info' has 0 bytes, expected 72"),
        (dict(vec=b"\x00" * 40), "field 'vec' has 40 bytes, expected 48"),
        (dict(vec=b"\x00" * 72), "field 'vec' has 72 bytes, expected 48"),
        (dict(n=3), "field 'info' has 72 bytes, expected 144"),               # 3 blocks of 6
        (dict(n=1), "field 'info' has 72 bytes, expected 24"),
        (dict(times=f8(0.5, 1.5)), "field 'info' has 72 bytes, expected 48"),  # fewer times than blocks
        (dict(times=f8(0.5, 1.5, 2.5, 3.5)), "field 'info' has 72 bytes, expected 96"),
        (dict(times=b""), "field 'info' has 72 bytes, expected 0"),
    ],
    ids=lambda x: x if isinstance(x, str) else ",".join(x),
)
def test_sizes_that_do_not_match_n_and_the_number_of_times(changes, match):
    rejected(tampered(**changes), match=match)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("name", ["start", "sent_at"])
def test_non_finite_scalar(name, bad):
    rejected(tampered(**{name: bad}), match="non-finite start or sent_at")


def _poisoned(name: str, index: int, bad: float) -> bytes:
    body = body_of(make_msg())
    a = np.frombuffer(body[name], "<f8").copy()
    a[index] = bad
    body[name] = a.tobytes()
    return envelope(body)


@pytest.mark.parametrize("bad", [math.nan, -math.nan, math.inf, -math.inf], ids=["nan", "-nan", "inf", "-inf"])
@pytest.mark.parametrize("name,count", [("times", 3), ("info", 9), ("vec", 6)])
def test_non_finite_array_entry(name, count, bad):
    for index in range(count):
        rejected(_poisoned(name, index, bad), match=f"field '{name}' contains NaN or inf")


def test_signalling_nan_payload_is_rejected():
    body = body_of(make_msg())
    raw = bytearray(body["vec"])
    raw[0:8] = bytes.fromhex("0100000000 00f07f".replace(" ", ""))   # sNaN, little-endian
    body["vec"] = bytes(raw)
    rejected(envelope(body), match="field 'vec' contains NaN or inf")


@pytest.mark.parametrize(
    "times",
    [(0.5, 0.5, 2.5), (0.5, 1.5, 1.5), (2.5, 1.5, 0.5), (0.5, 2.5, 1.5), (0.5, 0.4, 2.5)],
    ids=str,
)
def test_times_not_strictly_increasing(times):
    rejected(tampered(times=f8(*times)), match="not strictly increasing")


def test_negative_zero_equals_zero_so_it_is_not_increasing():
    msg = make_msg(start=-1.0)
    rejected(tampered(msg=msg, times=f8(-0.0, 0.0, 1.0)), match="not strictly increasing")


def test_time_before_start():
    rejected(tampered(start=0.5000000001), match="precedes the window start")
    rejected(tampered(start=100.0), match="precedes the window start")
    assert decode(tampered(start=0.5)).start == 0.5        # the first time may equal start


def test_empty_message_with_any_start_is_valid():
    msg = make_msg(m=0, start=MAX_ABS_TIME)
    out = decode(encode(msg))
    assert len(out) == 0 and out.info.shape == (0, 2, 2) and out.vec.shape == (0, 2)


def _with_block(k: int, block: np.ndarray) -> bytes:
    msg = make_msg(n=block.shape[0], m=3)
    info = msg.info.copy()
    info[k] = block
    return encode(InfoMessage(**{**msg.__dict__, "info": info}))


@pytest.mark.parametrize("k", [0, 1, 2])
@pytest.mark.parametrize(
    "block",
    [
        np.array([[1.0, 2.0], [2.0, 1.0]]),                 # indefinite
        np.array([[-1.0, 0.0], [0.0, 0.0]]),                # negative definite part
        np.array([[-1e-300, 0.0], [0.0, 0.0]]),             # negative, however tiny
        np.array([[1e6, 0.0], [0.0, -1e-2]]),               # -1e-8 relative: beyond PSD_RTOL
    ],
    ids=["indefinite", "negative", "tiny-negative", "small-relative-negative"],
)
def test_block_not_positive_semidefinite(k, block):
    err = rejected(_with_block(k, block), match="is not positive semi-definite")
    assert f"t={0.5 + k}" in str(err)        # the message names the offending state time


def test_psd_check_tolerates_rounding():
    # rounding of a difference of information matrices: ~1e-16 of the largest entry
    ok = np.array([[1e6, 0.0], [0.0, -1e-16 * 1e6]])
    assert decode(_with_block(1, ok)) is not None
    bad = np.array([[1e6, 0.0], [0.0, -PSD_RTOL * 1e6]])
    rejected(_with_block(1, bad), match="not positive semi-definite")
    zero = np.zeros((2, 2))
    assert decode(_with_block(1, zero)) is not None


def test_psd_check_accepts_rank_one_blocks_with_a_tiny_diagonal_entry():
    v = np.array([1e-6, 1.0])
    assert decode(_with_block(1, np.outer(v, v))) is not None
    # and refuses an indefinite part hidden next to a huge entry (brute force: eigenvalues)
    L = np.diag([4.0, 1e11, 0.0])
    L[0, 2] = L[2, 0] = 1e3
    assert np.linalg.eigvalsh(L)[0] < -100
    rejected(_with_block(1, L), match="not positive semi-definite")


# ---------------------------------------------------------------- HMAC
def test_authenticated_message_is_accepted_with_the_right_key():
    msg = make_msg()
    assert_same(decode(encode(msg, KEY), KEY), msg)
    mac = msgpack.unpackb(encode(msg, KEY))["mac"]
    assert isinstance(mac, bytes) and len(mac) == 32


def test_unauthenticated_message_is_rejected_when_a_key_is_set():
    rejected(encode(make_msg()), KEY, match="not authenticated")                          # mac: nil
    rejected(envelope(body_of(make_msg()), drop=("mac",)), KEY, match="not authenticated")  # no mac field
    rejected(envelope(body_of(make_msg()), mac="a string"), KEY, match="not authenticated")


def test_wrong_mac_is_rejected():
    msg = make_msg()
    rejected(encode(msg, b"another key"), KEY, match="authentication failed")
    good = msgpack.unpackb(encode(msg, KEY))["mac"]
    body = body_of(msg)
    rejected(envelope(body, mac=good[:-1]), KEY, match="authentication failed")             # truncated
    rejected(envelope(body, mac=good + b"\x00"), KEY, match="authentication failed")        # extended
    rejected(envelope(body, mac=b""), KEY, match="authentication failed")
    flipped = bytes([good[0] ^ 1]) + good[1:]
    rejected(envelope(body, mac=flipped), KEY, match="authentication failed")
    # the MAC of the original body does not authenticate a modified body
    body2 = {**body, "seq": body["seq"] + 1}
    rejected(envelope(body2, mac=good), KEY, match="authentication failed")


def test_mac_is_checked_before_the_body_is_parsed():
    """A forged body is reported as a MAC failure, never by what is wrong inside it."""
    rejected(envelope(b"\xc1 not msgpack", mac=b"\x00" * 32), KEY, match="authentication failed")
    rejected(envelope(b"\xc1 not msgpack"), KEY, match="not authenticated")


def test_mac_is_hmac_sha256_of_the_body_bytes():
    data = encode(make_msg(), KEY)
    env = msgpack.unpackb(data)
    assert env["mac"] == hmac.new(KEY, env["body"], hashlib.sha256).digest()
    assert set(env) == {"v", "body", "mac"} and env["v"] == VERSION


def test_without_a_key_an_authenticated_message_is_accepted():
    """Design choice (docs/wire-format.md, "Authentication"): a receiver without a key
    does not authenticate, so it ignores the ``mac`` field whatever it holds."""
    msg = make_msg()
    assert_same(decode(encode(msg, KEY)), msg)
    assert_same(decode(envelope(body_of(msg), mac=b"\x00" * 32)), msg)
    assert_same(decode(envelope(body_of(msg), mac="not even bytes")), msg)
    assert_same(decode(envelope(body_of(msg), drop=("mac",))), msg)


def test_empty_key_means_no_authentication():
    """Current behaviour (documented): ``b""`` is treated like no key at all, on both
    sides. See the report: FusionNode(network_key=b"") silently disables the MAC."""
    msg = make_msg()
    assert msgpack.unpackb(encode(msg, b""))["mac"] is None
    assert_same(decode(encode(msg), b""), msg)


# ---------------------------------------------------------------- size
def _bin(length: int) -> int:
    return length + (2 if length < 2**8 else 3 if length < 2**16 else 5)


def _str(s: str) -> int:
    b = len(s.encode())
    return b + (1 if b < 32 else 2 if b < 2**8 else 3 if b < 2**16 else 5)


def _uint(x: int) -> int:
    return 1 if x < 128 else 2 if x < 2**8 else 3 if x < 2**16 else 5 if x < 2**32 else 9


def predicted_size(m: int, n: int, src: str, dst: str, epoch: int, seq: int, keyed: bool) -> int:
    """Bytes of a message, from the layout in docs/wire-format.md."""
    k = n * (n + 1) // 2
    keys = sum(1 + len(f) for f in FIELDS)                # fixstr field names
    body = (
        1 + keys                                          # fixmap of 10
        + _str(src) + _str(dst) + _uint(epoch) + _uint(seq) + _uint(n)
        + 9 + 9                                           # start, sent_at: float64
        + _bin(8 * m) + _bin(8 * m * k) + _bin(8 * m * n)
    )
    env = 1 + (2 + 1) + (5 + _bin(body)) + (4 + (2 + 32 if keyed else 1))
    return env


SIZE_CASES = [(0, 1), (1, 1), (1, 4), (5, 4), (31, 1), (32, 1), (10, 6), (100, 4), (300, 8), (3000, 4), (3, 64)]


@pytest.mark.parametrize("keyed", [False, True])
@pytest.mark.parametrize("m,n", SIZE_CASES)
def test_size_matches_the_layout(m, n, keyed):
    epoch = 2**62 + 5
    msg = make_msg(n=n, m=m, epoch=epoch, seq=300, src="node-17", dst="node-3")
    data = encode(msg, KEY if keyed else None)
    assert len(data) == predicted_size(m, n, "node-17", "node-3", epoch, 300, keyed)
    # payload: 8 bytes per time, per packed information entry and per vector entry
    payload = 8 * m * (1 + n + n * (n + 1) // 2)
    overhead = len(data) - payload
    assert 0 < overhead <= overhead_bound("node-17", "node-3")
    assert overhead_bound("node-17", "node-3") == 154 + _str("node-17") + _str("node-3")


def overhead_bound(src: str, dst: str) -> int:
    """Most msgpack overhead of any message between ``src`` and ``dst``."""
    body = 1 + sum(1 + len(f) for f in FIELDS) + _str(src) + _str(dst) + 9 + 9 + 1 + 9 + 9 + 3 * 5
    env = 1 + (2 + 1) + (5 + 5) + (4 + 2 + 32)
    return body + env


def test_one_block_of_dimension_four_costs_120_bytes():
    sizes = [len(encode(make_msg(n=4, m=m, seq=1, epoch=1))) for m in (10, 11)]
    assert sizes[1] - sizes[0] == 8 * (1 + 4 + 10) == 120


def test_worked_example_of_the_docs():
    """docs/wire-format.md shows these bytes; keep the two in step."""
    text = (Path(__file__).parent.parent / "docs" / "wire-format.md").read_text()
    shown = re.findall(r"```\n([0-9a-f\n]+)```", text)
    msg = InfoMessage(src="a", dst="b", epoch=7, seq=3, start=0.5, sent_at=1.0,
                      times=np.array([1.0]), info=np.array([[[4.0, 0.5], [0.5, 2.0]]]),
                      vec=np.array([[1.0, -2.0]]))
    assert bytes.fromhex(shown[0].replace("\n", "")) == encode(msg)
    assert "ea 29 1a bf 50 cd 70 64 67 75 57 77 31 f6 50 4c" in text
    assert encode(msg, b"secret")[0x92:0xa2].hex(" ") == "ea 29 1a bf 50 cd 70 64 67 75 57 77 31 f6 50 4c"


def _not_psd_reference(info: np.ndarray) -> int | None:
    """The scaled eigenvalue test of ``wire._not_psd`` on every block, no shortcut."""
    if not len(info):
        return None
    d = np.diagonal(info, axis1=1, axis2=2)
    floor = wire.PSD_RTOL * np.abs(info).max(axis=(1, 2))
    s = 1.0 / np.sqrt(np.maximum(d, 0.0) + np.where(floor > 0, floor, 1.0)[:, None])
    bad = np.linalg.eigvalsh(info * s[:, :, None] * s[:, None, :])[:, 0] < -wire.PSD_SCALED_ATOL
    return int(np.argmax(bad)) if bad.any() else None


def test_psd_shortcut_decides_like_the_full_test() -> None:
    """The diagonal-dominance shortcut of ``_not_psd`` never changes a decision."""
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
        decisions.add(expected is None)
    assert decisions == {True, False}
