"""Fuzzing FusionNode.receive: only MessageError escapes, and a rejection changes nothing.

A chain ``a - b - c`` runs a few steps with measurements and exchanges; then the
middle node ``b`` is fed garbage, truncated, bit-flipped and re-encoded invalid
messages. After every rejection, ``b``'s estimate, its filter's dense
information, its channel filters, the stores its next messages are made from
and its statistics (all but ``messages_rejected`` / ``rejections``) must be
exactly as before. A bit flip may leave a valid message (a float mantissa, the
sign of an information vector entry...); those may be accepted, and then the
node must still have a finite mean and a symmetric positive definite covariance.

The tests at the end pin four defects that fuzzing found and that are fixed:
huge time stamps, an indefinite block hidden next to a huge entry, two times
with the same nanosecond key, and values near the float64 limit.
"""
from __future__ import annotations

import dataclasses
import hashlib
import hmac
import logging
import pickle

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.fusion import FusionNode
from dfusion.errors import MessageError
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.wire import decode, encode, InfoMessage, PSD_RTOL, PSD_SCALED_ATOL

KEY = b"fuzz-network-key"
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---------------------------------------------------------------- the network
def build_chain(key: bytes | None):
    """Nodes a - b - c after 5 steps; returns (a, b, c, fresh message a -> b).

    The message carries information ``b`` does not have yet (a measurement of
    ``a`` after the last exchange), so accepting it would change ``b``.
    """
    motion = ConstantVelocity(2, 0.3)
    prior = (0.0, np.zeros(4), np.eye(4) * 4.0)
    nodes = {
        name: FusionNode(name, nbrs, motion, window=50, prior=prior, network_key=key, epoch=epoch)
        for name, nbrs, epoch in (("a", ["b"], 11), ("b", ["a", "c"], 22), ("c", ["b"], 33))
    }
    a, b, c = nodes["a"], nodes["b"], nodes["c"]
    sensor = PositionSensor(2, 0.5)
    rng = np.random.default_rng(7)
    for k in range(1, 5):
        t = 0.1 * k
        for node in nodes.values():
            node.predict(t)
        a.update(t, rng.normal(size=2) + [k, 0.0], sensor)
        c.update(round(t - 0.05, 9), rng.normal(size=2) + [0.0, k], sensor)    # a late measurement
        if k % 2 == 0:
            for src, dst in (("a", "b"), ("b", "a"), ("b", "c"), ("c", "b")):
                nodes[dst].receive(nodes[src].message_to(dst))
    for node in nodes.values():
        node.predict(0.5)
    a.update(0.5, [5.0, 0.1], sensor)
    b.update(0.45, [4.5, 0.2], sensor)
    return a, b, c, a.message_to("b")


NETWORKS = {key: build_chain(key) for key in (None, KEY)}
# a pickled copy of b: unpickling is about twice as fast as copy.deepcopy
PICKLED_B = {key: pickle.dumps(net[1], pickle.HIGHEST_PROTOCOL) for key, net in NETWORKS.items()}


@pytest.fixture(autouse=True)
def quiet_rejections():
    """Every rejection logs a warning; thousands of them only slow the run down."""
    logger = logging.getLogger("dfusion.fusion.node")
    level = logger.level
    logger.setLevel(logging.ERROR)
    yield
    logger.setLevel(level)


def fresh_b(key: bytes | None) -> FusionNode:
    """A pristine copy of the middle node."""
    return pickle.loads(PICKLED_B[key])


def has_indefinite_block(data, key: bytes | None) -> bool:
    """True if some block of a decodable message is indefinite beyond rounding
    (an independent brute-force check of decode's positive semi-definiteness test)."""
    try:
        msg = decode(data, key)
    except MessageError:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        return any(_indefinite(L) for L in msg.info)


def _indefinite(L: np.ndarray) -> bool:
    """Indefinite beyond the rounding docs/wire-format.md allows.

    The documented rule accepts ``L`` when ``S L S >= -PSD_SCALED_ATOL I`` with
    ``S = diag(1 / sqrt(d+ + f))``, ``d+`` the non-negative part of the diagonal and
    ``f = PSD_RTOL max|L|``. By congruence (Sylvester's law of inertia) that is
    ``L + PSD_SCALED_ATOL (diag(d+) + f I)`` positive semi-definite, which is computed
    here on the unscaled matrix, without decode's diagonal scaling or its
    diagonal-dominance shortcut. The tolerance is per entry: a negative eigenvalue
    next to a huge entry is still found, while 1e-10-relative off-diagonal noise on a
    zero diagonal, or denormal entries, are rounding.
    """
    d = np.maximum(np.diag(L), 0.0)
    f = PSD_RTOL * np.abs(L).max(initial=0.0)
    shifted = L + PSD_SCALED_ATOL * (np.diag(d) + f * np.eye(L.shape[0]))
    # eigvalsh's own error is about eps * ||shifted||
    return bool(np.linalg.eigvalsh(shifted).min() < -1e-13 * max(1.0, np.abs(shifted).max()))


def valid_message(key: bytes | None) -> bytes:
    return NETWORKS[key][3]


# ---------------------------------------------------------------- snapshots
def snapshot(node: FusionNode) -> dict:
    """Everything observable about ``node``, except the rejection counters."""
    mean, cov = node.estimate()
    Omega, eta = node.filter.dense_information()
    stats = dataclasses.asdict(node.stats)
    del stats["messages_rejected"], stats["rejections"]
    channels = {}
    for name, ch in node.channels.items():
        channels[name] = (
            {k: (e.t, e.seq, e.info.copy(), e.vec.copy()) for k, e in ch.received.items()},
            ch.epoch, ch.last_seq, ch.seq_out, ch.messages_in, ch.messages_out, ch.duplicates,
        )
    # what message_to() sends from: the node's own and total information per state time
    # (private stores; comparing them is far cheaper than probing message_to on a copy)
    stores = {
        name: {k: (e.t, e.info.copy(), e.vec.copy()) for k, e in getattr(node, name).items()}
        for name in ("_own", "_total")
    }
    return {
        "estimate": (mean.copy(), cov.copy()),
        "dense": (Omega.copy(), eta.copy()),
        "times": node.filter.times,
        "marginalized": node.filter.marginalized,
        "stats": stats,
        "channels": channels,
        "stores": stores,
    }


def assert_same(x, y, path="node") -> None:
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        assert np.array_equal(x, y), path
    elif isinstance(x, dict):
        assert isinstance(y, dict) and x.keys() == y.keys(), path
        for k in x:
            assert_same(x[k], y[k], f"{path}[{k!r}]")
    elif isinstance(x, (tuple, list)):
        assert type(x) is type(y) and len(x) == len(y), path
        for i, (a, b) in enumerate(zip(x, y)):
            assert_same(a, b, f"{path}[{i}]")
    else:
        assert x == y, (path, x, y)


PRISTINE = {key: snapshot(net[1]) for key, net in NETWORKS.items()}


class Target:
    """The middle node under fuzzing, with its last snapshot."""

    def __init__(self, key: bytes | None) -> None:
        self.key = key
        self.reset()
        self.accepted = 0
        self.rejected = 0

    def reset(self) -> None:
        self.node = fresh_b(self.key)
        self.snap = PRISTINE[self.key]

    def feed(self, data, *, must_reject: bool = False) -> bool:
        """Deliver ``data``; return True if accepted. Anything but MessageError fails the test."""
        node = self.node
        before_rejected = node.stats.messages_rejected
        before_reasons = sum(node.stats.rejections.values())
        try:
            node.receive(data)
        except MessageError:
            self.rejected += 1
            assert node.stats.messages_rejected == before_rejected + 1
            assert sum(node.stats.rejections.values()) == before_reasons + 1
            assert_same(snapshot(node), self.snap)
            return False
        self.accepted += 1
        assert not must_reject, "an invalid message was accepted"
        # it must have been a valid message, and the node must still be sound
        decode(data, self.key)
        assert not has_indefinite_block(data, self.key)
        mean, cov = node.estimate()
        assert np.all(np.isfinite(mean))
        assert_spd(cov)
        self.reset()          # the next input goes to a pristine node again
        return True


def assert_spd(cov: np.ndarray) -> None:
    """Symmetric positive definite up to rounding.

    A valid message may carry huge information (a flipped exponent bit turns 4.0
    into 7e19): the covariance then has variances of 1e-20 next to 1e-1, and its
    smallest eigenvalue is not resolved better than ``eps`` times the largest.
    """
    assert np.all(np.isfinite(cov))
    assert np.array_equal(cov, cov.T)
    assert np.all(np.diag(cov) > 0)
    eig = np.linalg.eigvalsh(cov)
    assert eig.min() > -16 * np.finfo(float).eps * eig.max(), eig


def test_the_valid_message_is_accepted_and_changes_the_node():
    """Sanity check of the fixture: rejections below are compared against a real change."""
    for key in (None, KEY):
        t = Target(key)
        before = t.snap
        node = t.node
        assert node.receive(valid_message(key)) > 0
        after = snapshot(node)
        assert not np.array_equal(before["estimate"][1], after["estimate"][1])


# ---------------------------------------------------------------- garbage
@FUZZ
@given(data=st.binary(max_size=600))
def test_random_bytes(data):
    Target(None).feed(data)


@FUZZ
@given(data=st.binary(max_size=600))
def test_random_bytes_with_a_key(data):
    Target(KEY).feed(data, must_reject=True)


@FUZZ
@given(pos=st.integers(0, 10_000), junk=st.binary(min_size=1, max_size=64), replace=st.booleans())
def test_random_bytes_spliced_into_a_valid_message(pos, junk, replace):
    data = valid_message(None)
    pos %= len(data)
    end = pos + len(junk) if replace else pos
    Target(None).feed(data[:pos] + junk + data[end:])


def test_every_truncation():
    data = valid_message(None)
    target = Target(None)
    for cut in range(len(data)):
        target.feed(data[:cut], must_reject=True)
    assert target.rejected == len(data)


def test_truncations_with_a_key():
    """A sample: every cut in the headers and the MAC, every 8th in the payload."""
    data = valid_message(KEY)
    cuts = sorted(set(range(100)) | set(range(len(data) - 40, len(data))) | set(range(0, len(data), 8)))
    target = Target(KEY)
    for cut in cuts:
        target.feed(data[:cut], must_reject=True)
    assert target.rejected == len(cuts)


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
def test_wrong_python_types(key):
    target = Target(key)
    for data in (None, "text", 42, [valid_message(key)], {"v": 1}):
        target.feed(data, must_reject=True)


# ---------------------------------------------------------------- bit flips
def flip(data: bytes, bits) -> bytes:
    out = bytearray(data)
    for b in bits:
        out[b // 8] ^= 1 << (b % 8)
    return bytes(out)


def payload_spans(data: bytes) -> dict[str, tuple[int, int]]:
    """Offset and length, in ``data``, of the float64 payloads of times/info/vec."""
    body = msgpack.unpackb(data)["body"]
    fields = msgpack.unpackb(body)
    at = data.find(body)
    spans = {name: (at + body.find(fields[name]), len(fields[name])) for name in ("times", "info", "vec")}
    assert spans["times"][0] + spans["times"][1] < spans["info"][0] < spans["vec"][0]
    return spans


def bits_to_flip(data: bytes) -> list[int]:
    """Every bit outside the float payloads (map headers, field names, integers, strings,
    start/sent_at, the MAC), and every bit of a few payload floats: the last time, a
    vector entry, and diagonal and off-diagonal entries of the first and last
    information blocks (n = 4: 10 packed entries per block, row-major upper triangle,
    so entries 0 = L00, 1 = L01, 4 = L11, 8 = L23)."""
    spans = payload_spans(data)
    payload = set()
    for offset, length in spans.values():
        payload.update(range(offset, offset + length))
    bits = [b for b in range(8 * len(data)) if b // 8 not in payload]
    tl = spans["times"][0] + spans["times"][1] - 8
    i0, il = spans["info"][0], spans["info"][0] + spans["info"][1] - 80
    vl = spans["vec"][0] + spans["vec"][1] - 32
    for start in (tl, vl + 8, i0, il + 8, il + 32, il + 64):
        bits.extend(range(8 * start, 8 * start + 64))
    return bits


def keyed_bits_to_flip(data: bytes) -> list[int]:
    """With a MAC every flip inside the body fails the same check: every bit outside
    the body (envelope headers, version, MAC) and every bit of every 16th body byte."""
    body = msgpack.unpackb(data)["body"]
    at = data.find(body)
    inside = range(at, at + len(body))
    return [b for b in range(8 * len(data)) if b // 8 not in inside or (b // 8 - at) % 16 == 0]


def test_single_bit_flips_without_a_key():
    data = valid_message(None)
    target = Target(None)
    bits = bits_to_flip(data)
    assert len(bits) > 900
    for bit in bits:
        target.feed(flip(data, [bit]))
    # flips in float payloads often leave a valid message; most others do not
    assert target.accepted > 0 and target.rejected > 0
    assert target.accepted + target.rejected == len(bits)


def test_single_bit_flips_with_a_key_are_all_rejected():
    data = valid_message(KEY)
    target = Target(KEY)
    bits = keyed_bits_to_flip(data)
    assert len(bits) > 600
    for bit in bits:
        target.feed(flip(data, [bit]), must_reject=True)


@FUZZ
@given(st.data())
def test_multiple_bit_flips(data):
    msg = valid_message(None)
    bits = data.draw(st.lists(st.integers(0, 8 * len(msg) - 1), min_size=2, max_size=24, unique=True))
    Target(None).feed(flip(msg, bits))


@FUZZ
@given(st.data())
def test_multiple_bit_flips_with_a_key(data):
    msg = valid_message(KEY)
    bits = data.draw(st.lists(st.integers(0, 8 * len(msg) - 1), min_size=1, max_size=24, unique=True))
    Target(KEY).feed(flip(msg, bits), must_reject=True)


# ---------------------------------------------------------------- invalid re-encodings
SAME = object()


def reencode(key: bytes | None, *, sign_key=SAME, **changes) -> bytes:
    """The valid message ``a -> b`` with fields replaced (values, or functions of the
    old value), encoded without validation and signed with ``sign_key``."""
    msg = decode(valid_message(key), key)
    fields = {f.name: getattr(msg, f.name) for f in dataclasses.fields(InfoMessage)}
    for name, value in changes.items():
        if callable(value):
            value = value(np.array(fields[name], copy=True))
        fields[name] = value
    return encode(InfoMessage(**fields), key if sign_key is SAME else sign_key)


def rebody(key: bytes | None, **changes) -> bytes:
    """The valid message ``a -> b`` with raw body fields replaced, signed with ``key``."""
    body = msgpack.unpackb(msgpack.unpackb(valid_message(key))["body"])
    body.update(changes)
    raw = msgpack.packb(body, use_bin_type=True)
    mac = hmac.new(key, raw, hashlib.sha256).digest() if key else None
    return msgpack.packb({"v": 1, "body": raw, "mac": mac}, use_bin_type=True)


def setitem(index, value):
    def change(a):
        a[index] = value
        return a
    return change


def non_psd(info):
    info[1] = np.diag([1.0, 1.0, 1.0, -1.0])
    return info


def swap_times(times):
    times[[1, 2]] = times[[2, 1]]
    return times


def repeat_time(times):
    times[2] = times[1]
    return times


INVALID = {
    "nan-info": dict(info=setitem((0, 1, 1), np.nan)),
    "inf-info": dict(info=setitem((-1, 0, 3), np.inf)),
    "-inf-info": dict(info=setitem((2, 3, 3), -np.inf)),
    "nan-vec": dict(vec=setitem((0, 0), np.nan)),
    "inf-vec": dict(vec=setitem((-1, 3), np.inf)),
    "nan-times": dict(times=setitem(0, np.nan)),
    "inf-times": dict(times=setitem(-1, np.inf)),
    "nan-start": dict(start=np.nan),
    "inf-sent_at": dict(sent_at=np.inf),
    "non-psd-block": dict(info=non_psd),
    "times-swapped": dict(times=swap_times),
    "times-repeated": dict(times=repeat_time),
    "time-before-start": dict(start=lambda s: float(s) + 0.35),
    "negative-seq": dict(seq=-1),
    "negative-epoch": dict(epoch=-5),
    "wrong-n-3": dict(info=lambda a: a[:, :3, :3], vec=lambda v: v[:, :3]),       # valid body, n = 3
    "wrong-n-6": dict(info=lambda a: np.pad(a, ((0, 0), (0, 2), (0, 2))), vec=lambda v: np.pad(v, ((0, 0), (0, 2)))),
    "from-non-neighbour": dict(src="x"),
    "from-itself": dict(src="b"),
    "from-empty-name": dict(src=""),
    "to-another-node": dict(dst="c"),
    "to-the-sender": dict(dst="a"),
    "to-nobody": dict(dst=""),
}


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_message_is_rejected(case, key):
    Target(key).feed(reencode(key, **INVALID[case]), must_reject=True)


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 0, -4, 65, True])
def test_n_that_does_not_match_the_sizes_is_rejected(n, key):
    Target(key).feed(rebody(key, n=n), must_reject=True)


@pytest.mark.parametrize(
    "changes",
    [
        dict(info=b"\x00" * 8), dict(vec=b""), dict(times=b"\x00" * 12),
        dict(seq=True), dict(epoch=1.5), dict(src=b"a"), dict(start="0"),
    ],
    ids=lambda c: ",".join(f"{k}={v!r}" for k, v in c.items()),
)
def test_malformed_body_fields_are_rejected(changes):
    for key in (None, KEY):
        Target(key).feed(rebody(key, **changes), must_reject=True)


def test_rebody_without_changes_is_the_valid_message():
    assert rebody(None) == valid_message(None) and rebody(KEY) == valid_message(KEY)


@pytest.mark.parametrize(
    "sign_key,case",
    [(None, "unauthenticated"), (b"wrong key", "wrong-key"), (KEY[:-1], "truncated-key")],
)
def test_bad_hmac_is_rejected_by_a_keyed_node(sign_key, case):
    target = Target(KEY)
    target.feed(reencode(KEY, sign_key=sign_key), must_reject=True)
    assert target.node.stats.rejections == {"malformed": 1}


def test_rejection_reasons_are_counted():
    target = Target(None)
    for case, reason in [
        ("nan-info", "malformed"),
        ("from-non-neighbour", "not-a-neighbour"),
        ("to-another-node", "misaddressed"),
        ("wrong-n-3", "dimension"),
    ]:
        target.feed(reencode(None, **INVALID[case]), must_reject=True)
    assert target.node.stats.rejections == {"malformed": 1, "not-a-neighbour": 1, "misaddressed": 1, "dimension": 1}
    assert target.node.stats.messages_rejected == 4


def test_interleaved_rejections_do_not_disturb_a_valid_exchange():
    """Garbage between two valid messages: the result equals the clean run."""
    clean = fresh_b(None)
    clean.receive(valid_message(None))
    node = fresh_b(None)
    for case in sorted(INVALID):
        with pytest.raises(MessageError):
            node.receive(reencode(None, **INVALID[case]))
    node.receive(valid_message(None))
    for case in sorted(INVALID):
        with pytest.raises(MessageError):
            node.receive(reencode(None, **INVALID[case]))
    a, b = snapshot(clean), snapshot(node)
    assert_same(b, a)
    assert node.stats.messages_rejected == 2 * len(INVALID)


# ---------------------------------------------------------------- defects found by fuzzing (fixed)
def test_huge_state_time_is_rejected():
    huge = dict(times=lambda t: np.append(t[:-1], 1e300))
    node = fresh_b(None)
    with pytest.raises(MessageError):
        node.receive(reencode(None, **huge))


def test_indefinite_block_hidden_by_a_large_entry_is_rejected():
    block = np.diag([4.0, 1e11, 0.0, 0.0])
    block[0, 2] = block[2, 0] = 5.0     # eigenvalue -4: inside the old tolerance 1e-9 * 1e11 = 100
    assert _indefinite(block) and np.linalg.eigvalsh(block)[0] < -1.0

    def hide(info):
        info[-1] = block
        return info
    node = fresh_b(None)
    before = snapshot(node)
    with pytest.raises(MessageError, match="positive semi-definite"):
        node.receive(reencode(None, info=hide))
    assert node.stats.messages_rejected == 1
    assert_same(snapshot(node), before)   # the snapshot leaves the rejection counters out


def test_times_with_the_same_key_leave_no_phantom_information():
    reference = fresh_b(None)
    reference.receive(valid_message(None))
    node = fresh_b(None)
    node.receive(valid_message(None))
    msg = decode(valid_message(None))
    t = msg.times[-1]
    # replace the last block by two blocks 0.5 ns apart: both round to the same key
    times = np.append(msg.times[:-1], [t - 0.3e-9, t + 0.2e-9])
    info = np.concatenate([msg.info[:-1], 10 * np.eye(4)[None], 10 * np.eye(4)[None]])
    vec = np.concatenate([msg.vec[:-1], np.zeros((2, 4))])
    crafted = encode(dataclasses.replace(msg, seq=msg.seq + 1, times=times, info=info, vec=vec))
    try:
        node.receive(crafted)
    except MessageError:
        pass          # rejecting such a message is a fix too
    # the sender's next message (same information as the first) must restore the state
    node.receive(encode(dataclasses.replace(msg, seq=msg.seq + 2)))
    np.testing.assert_allclose(node.estimate()[1], reference.estimate()[1], rtol=1e-9, atol=1e-12)


def test_huge_finite_values_do_not_poison_the_estimate():
    cases = [
        dict(info=setitem((-1, 0, 0), 1e308)),              # symmetrize: 0.5 * (1e308 + 1e308) = inf
        dict(vec=setitem((slice(-2, None), 0), 1e308)),     # two entries of 1e308
        dict(vec=setitem((-1, slice(0, 2)), 1e308)),
    ]
    sound = []
    for huge in cases:
        node = fresh_b(None)
        try:
            with np.errstate(all="ignore"):
                node.receive(reencode(None, **huge))
        except MessageError:
            sound.append(True)
            continue
        with np.errstate(all="ignore"):
            mean, cov = node.estimate()
        try:
            assert np.all(np.isfinite(mean))
            assert_spd(cov)
            sound.append(True)
        except AssertionError:
            sound.append(False)
    assert all(sound), sound
