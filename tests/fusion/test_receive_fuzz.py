"""Fuzzing FusionNode.receive: only MessageError escapes, and a rejected message changes nothing.

A chain ``a - b - c`` (:func:`tests.helpers.fusion_harness.build_chain`) runs a few
steps with measurements and exchanges; the middle node ``b`` is then fed mutations of
valid version-2 frames. After every rejection ``b``'s whole state (its filter, every
channel filter with its counters, acknowledgements and records, the stores its
messages are made from, its statistics but the rejection counters) must be bit for bit
what it was: compared by :func:`state_digest`. A mutation may leave a valid message
(a new ``sent_at``, another acknowledgement, a new incarnation of the sender...); it
may then be accepted, and the node must still have a finite estimate and a symmetric
positive definite covariance (the node is then reset to its pristine copy).

The bulk test (:func:`test_bulk_fuzz`) is a deterministic loop over mutation
generators, not hypothesis: ``BULK`` mutated messages without a key and as many with
one (with a key, re-encoded bodies are sealed with the right key, as a key holder
or an undetected corruption would, so the validation behind the MAC is exercised
too), with memory measured by tracemalloc. The tests after it pin particular cases.
"""
from __future__ import annotations

import dataclasses
import gc
import logging
import pickle
import random
import struct
import tracemalloc
import zlib
from collections import Counter

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import MessageError
from dfusion.fusion import FusionNode
from dfusion.fusion.node import RejectionLog
from dfusion.fusion.channel import MAX_SEQ_JUMP
from dfusion.models import PositionSensor
from dfusion.wire import PSD_RTOL, PSD_SCALED_ATOL, FrameKey, InfoMessage, clear_caches, decode, encode

from tests.helpers.fusion_harness import KEY, build_chain, state_digest

NETWORK, RUN = "fuzz-net", "run-1"
FRAME_KEY = FrameKey(KEY, NETWORK, RUN)
KEYS = {None: None, KEY: FRAME_KEY}
#: mutated messages per key setting: in the bulk test (with a state digest after each one),
#: and in the memory test (3,000 untraced, 1,500 traced for the warm-up, then MEMORY_RUN):
#: 2 x 59,500 = 119,000 in all, 100,000 of them with the digest check
BULK = 50_000
MEMORY_RUN = 5_000
log = logging.getLogger(__name__)
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---------------------------------------------------------------- the network
def build(key: bytes | None):
    a, b, c, fresh, _ = build_chain(key, network=NETWORK, run=RUN)
    # a full message too (the first after a lost full one): every time of a's window
    full_sender = pickle.loads(pickle.dumps(a))
    full_sender.channels["b"].need_full = True
    full = full_sender.message_to("b")
    # and one from c with a new measurement that clears the time of an earlier one
    # (re-encoded from c's own message: c's information at 0.35 is now zero)
    c.update(0.5, [0.2, 5.1], PositionSensor(2, 0.5))
    msg = decode(c.message_to("b"), KEYS[key])
    assert not msg.full and len(msg) == 1
    cleared = dataclasses.replace(msg, cleared=np.array([0.35]))
    return a, b, c, [fresh, full, encode(cleared, KEYS[key])]


NETWORKS = {key: build(key) for key in (None, KEY)}
PICKLED_B = {key: pickle.dumps(net[1], pickle.HIGHEST_PROTOCOL) for key, net in NETWORKS.items()}
PRISTINE = {key: state_digest(net[1]) for key, net in NETWORKS.items()}


def fresh_b(key: bytes | None) -> FusionNode:
    """A pristine copy of the middle node (unpickling is about twice as fast as deepcopy)."""
    return pickle.loads(PICKLED_B[key])


def valid_messages(key: bytes | None) -> list[bytes]:
    return NETWORKS[key][3]


@pytest.fixture(autouse=True)
def quiet_rejections():
    """Rejections are logged (rate-limited); the fuzz does not need to see them."""
    logger = logging.getLogger("dfusion.fusion.node")
    level = logger.level
    logger.setLevel(logging.ERROR)
    yield
    logger.setLevel(level)


# ---------------------------------------------------------------- soundness of accepted messages
def indefinite(info: np.ndarray) -> np.ndarray:
    """Per block of ``info`` (m, n, n): indefinite beyond the rounding docs/wire-format.md
    allows, by the congruence ``L + PSD_SCALED_ATOL (diag(d+) + f I)`` (no scaling, no
    shortcut; see tests/test_wire.py)."""
    if not len(info):
        return np.zeros(0, dtype=bool)
    n = info.shape[1]
    d = np.maximum(np.diagonal(info, axis1=1, axis2=2), 0.0)
    f = PSD_RTOL * np.abs(info).max(axis=(1, 2))
    f = np.where(f > 0, f, 1.0)
    shifted = info + PSD_SCALED_ATOL * (d[:, :, None] * np.eye(n) + f[:, None, None] * np.eye(n))
    return np.linalg.eigvalsh(shifted)[:, 0] < -1e-13 * np.abs(shifted).max(axis=(1, 2))


def assert_sound(node: FusionNode) -> None:
    """A finite mean and a symmetric positive definite covariance (up to rounding: a valid
    message may carry information of 1e12 next to 1e-1, and the smallest eigenvalue is
    not resolved better than eps times the largest)."""
    mean, cov = node.estimate()
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))
    assert np.array_equal(cov, cov.T)
    assert np.all(np.diag(cov) > 0)
    eig = np.linalg.eigvalsh(cov)
    assert eig.min() > -16 * np.finfo(float).eps * eig.max(), eig


class Target:
    """The middle node under fuzzing: feed it, check it, reset it after an accepted message."""

    def __init__(self, key: bytes | None, pristine: bytes | None = None) -> None:
        self.key = key
        self.pristine = PICKLED_B[key] if pristine is None else pristine
        self.digest = PRISTINE[key] if pristine is None else state_digest(pickle.loads(pristine))
        self.reasons: Counter = Counter()
        self.accepted = 0
        self.reset()

    def reset(self) -> None:
        self.node = pickle.loads(self.pristine)

    def feed(self, data, *, must_reject: bool = False, what: str = "") -> bool:
        """Deliver ``data``; True if accepted. Anything but MessageError fails the test."""
        node = self.node
        rejected = node.stats.messages_rejected
        reasons = dict(node.stats.rejections)
        try:
            node.receive(data)
        except MessageError as exc:
            self.reasons[exc.reason] += 1
            assert node.stats.messages_rejected == rejected + 1, what
            reasons[exc.reason] = reasons.get(exc.reason, 0) + 1
            assert node.stats.rejections == reasons, what
            assert state_digest(node) == self.digest, f"a rejected message changed the node: {what}"
            return False
        except Exception as exc:   # noqa: BLE001 (reported with the mutation that caused it)
            raise AssertionError(f"{type(exc).__name__} escaped receive ({what}): {exc}") from exc
        assert not must_reject, f"an invalid message was accepted: {what}"
        self.accepted += 1
        msg = decode(data, KEYS[self.key])        # it was a valid message
        if not msg.naive:
            assert not indefinite(msg.info).any(), what
        assert_sound(node)
        self.reset()
        return True


def test_the_valid_messages_are_accepted_and_change_the_node():
    """Sanity check of the fixture: rejections are compared against a real change."""
    for key in (None, KEY):
        for data in valid_messages(key):
            t = Target(key)
            assert t.node.receive(data) > 0
            assert state_digest(t.node) != PRISTINE[key]


# ---------------------------------------------------------------- the mutation generators
FLAGS = {"KEYED": 1, "FULL": 2, "NAIVE": 4, "WIDE": 8}
INT_FIELDS = {"epoch": 2, "dst_epoch": 3, "seq": 4, "ack": 5, "ack_mask": 6, "n": 7}
FLOAT_FIELDS = {"start": 8, "sent_at": 9}
BIN_FIELDS = {"times": 10, "mask": 11, "values": 12, "cleared": 13}
EDGE_INTS = [0, -1, 1, 2, 3, 4, 5, 31, 32, 63, 64, 65, 127, 128, 255, 256, 2**16 - 1, 2**16, 2**31 - 1, 2**31,
             2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1, -(2**31), -(2**31) - 1, -(2**63), -32, -33,
             MAX_SEQ_JUMP - 1, MAX_SEQ_JUMP, MAX_SEQ_JUMP + 1, 2 * MAX_SEQ_JUMP, 11, 12, 22, 33, 10, 21, 23]
# floats no field accepts (for values: NaN, inf, or beyond the information limits) and
# floats that may be valid somewhere (a time, a sent_at, an entry that keeps a block PSD)
BAD_FLOATS = [float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1.7976931348623157e308, 9.3e9, -9.3e9,
              1e13, 1e19, -1e19]
EDGE_FLOATS = BAD_FLOATS + [9.2e9, -9.2e9, 1e12, 1e18, -0.0, 0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.0,
                            -1.0, -4.0, 0.5, 1e-300, 3.0, 30.0, 1e6]
WRONG_TYPES = [None, True, False, 1.5, -2.5, "x", "", "b", b"", b"\x00" * 8, [1], [], {"k": 1}, {},
               msgpack.ExtType(1, b"\x00"), msgpack.Timestamp(1, 0), 7, -1, 2**64 - 1]
NAMES = ["a", "b", "c", "x", "", "a" * 256, "a" * 257, "é" * 129, "a\x00", "A"]


class Mutator:
    """Deterministic mutations of the valid frames of one key setting."""

    def __init__(self, key: bytes | None, seed: int, frames: list[bytes] | None = None) -> None:
        self.rng = random.Random(seed)
        self.key = KEYS[key]
        self.frames = valid_messages(key) if frames is None else frames
        self.fields = [msgpack.unpackb(f[4:len(f) - 4 - (16 if self.key else 0)]) for f in self.frames]
        # a valid message of another state dimension (n = 3), sealed for this key setting
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(2, 3, 3))
        other = InfoMessage("a", "b", 11, 3, 0.0, 0.5, np.array([0.45, 0.5]), A @ A.transpose(0, 2, 1),
                            rng.normal(size=(2, 3)), dst_epoch=22, ack=1, full=False)
        self.other_dimension = encode(other, self.key)
        # weights: byte-level mutations are cheap to reject; re-encoded ones reach the node's
        # checks, and those that stay valid (about 1 in 12) are accepted and cost a reset
        self.generators = [
            (self.byte_flips, 3), (self.bit_flips, 3), (self.splice, 2), (self.truncate_or_extend, 2),
            (self.int_field, 2), (self.float_field, 1), (self.values_entries, 1), (self.wrong_type, 3),
            (self.bin_field, 2), (self.flags_or_version, 1), (self.names, 1), (self.times_shift, 0.5),
            (self.fields_count, 1), (self.unsealed, 1), (self.dimension, 0.3),
        ]
        self.weights = [w for _, w in self.generators]

    def __call__(self) -> tuple[str, bytes]:
        gen = self.rng.choices(self.generators, self.weights)[0][0]
        return gen.__name__, gen()

    def pick(self) -> tuple[bytes, list, int]:
        i = self.rng.randrange(len(self.frames))
        return self.frames[i], list(self.fields[i]), self.frames[i][3]

    def seal(self, fields: list, flags: int, version: int = 2) -> bytes:
        """A frame around ``fields`` with a correct checksum and, with a key, a correct MAC."""
        body = msgpack.packb(fields, use_bin_type=True)
        head = b"DF" + bytes((version, flags)) + body
        frame = head + struct.pack("<I", zlib.crc32(head))
        return frame + self.key.mac(frame) if self.key is not None and flags & 1 else frame

    # byte-level: caught by the checksum (or the MAC)
    def byte_flips(self) -> bytes:
        frame = bytearray(self.pick()[0])
        for _ in range(self.rng.randint(1, 4)):
            frame[self.rng.randrange(len(frame))] ^= self.rng.randint(1, 255)
        return bytes(frame)

    def bit_flips(self) -> bytes:
        frame = bytearray(self.pick()[0])
        for _ in range(self.rng.randint(1, 8)):
            bit = self.rng.randrange(8 * len(frame))
            frame[bit // 8] ^= 1 << (bit % 8)
        return bytes(frame)

    def splice(self) -> bytes:
        while True:
            frame = self.pick()[0]
            r = self.rng.random()
            pos = self.rng.randrange(len(frame) + 1)
            if r < 0.3:     # head of one frame, tail of another
                other = self.pick()[0]
                out = frame[:pos] + other[min(pos, len(other)):]
            else:
                junk = self.rng.randbytes(self.rng.randint(1, 64))
                if r < 0.6:
                    out = frame[:pos] + junk + frame[pos:]
                elif r < 0.8:
                    out = frame[:pos] + junk + frame[pos + len(junk):]
                else:
                    out = frame[:pos] + frame[pos + self.rng.randint(1, 32):]
            if out not in self.frames:
                return out

    def truncate_or_extend(self) -> bytes:
        frame = self.pick()[0]
        if self.rng.random() < 0.7:
            return frame[:self.rng.randrange(len(frame))]
        return frame + self.rng.randbytes(self.rng.randint(1, 40))

    # re-encoded bodies, sealed correctly: the body's own validation, then the node's checks
    def int_field(self) -> bytes:
        _, fields, flags = self.pick()
        # most edge values are out of range for n, epoch (previous incarnation) and seq
        # (a jump); acknowledgements are rarely invalid, so they are drawn less often
        name = self.rng.choices(list(INT_FIELDS), [2, 1, 2, 0.5, 0.5, 4])[0]
        i = INT_FIELDS[name]
        v = self.rng.choice(EDGE_INTS) if self.rng.random() < 0.8 else fields[i] + self.rng.choice([-2, -1, 1, 2])
        if not -(2**63) <= v < 2**64:
            v = self.rng.choice([2**64 - 1, -(2**63)])   # msgpack holds nothing beyond 64 bits
        fields[i] = v
        return self.seal(fields, flags)

    def float_field(self) -> bytes:
        _, fields, flags = self.pick()
        fields[self.rng.choice(list(FLOAT_FIELDS.values()))] = self.rng.choice(
            BAD_FLOATS if self.rng.random() < 0.6 else EDGE_FLOATS)
        return self.seal(fields, flags)

    def values_entries(self) -> bytes:
        _, fields, flags = self.pick()
        values = bytearray(fields[12])
        for _ in range(self.rng.randint(1, 3)):
            if len(values) >= 8:
                j = 8 * self.rng.randrange(len(values) // 8)
                x = self.rng.choice(BAD_FLOATS if self.rng.random() < 0.6 else EDGE_FLOATS) if self.rng.random() < 0.8 else (
                    struct.unpack("<d", values[j:j + 8])[0] * self.rng.choice([-1.0, 10.0, 1e6, -1e-3, 0.0]))
                values[j:j + 8] = struct.pack("<d", x)
        fields[12] = bytes(values)
        return self.seal(fields, flags)

    def wrong_type(self) -> bytes:
        _, fields, flags = self.pick()
        fields[self.rng.randrange(14)] = self.rng.choice(WRONG_TYPES)
        return self.seal(fields, flags)

    def bin_field(self) -> bytes:
        _, fields, flags = self.pick()
        i = self.rng.choice(list(BIN_FIELDS.values()))
        raw = bytearray(fields[i])
        r = self.rng.random()
        if r < 0.25 or not raw:
            raw = bytearray(self.rng.randbytes(self.rng.choice([0, 1, 4, 7, 8, 12, 16, 24, 40])))
        elif r < 0.5:
            del raw[self.rng.randrange(len(raw)):]
        elif r < 0.75:
            raw += self.rng.randbytes(self.rng.choice([1, 4, 8]))
        else:
            j = self.rng.randrange(len(raw))
            raw[j] ^= 1 << self.rng.randrange(8)
        fields[i] = bytes(raw)
        return self.seal(fields, flags)

    def flags_or_version(self) -> bytes:
        _, fields, flags = self.pick()
        if self.rng.random() < 0.7:
            flags ^= self.rng.choice([2, 4, 8, 16, 128, 6, 10])
            return self.seal(fields, flags)
        return self.seal(fields, flags, version=self.rng.choice([0, 1, 3, 255]))

    def names(self) -> bytes:
        _, fields, flags = self.pick()
        fields[self.rng.choice([0, 1])] = self.rng.choice(NAMES)
        return self.seal(fields, flags)

    def times_shift(self) -> bytes:
        """Times moved far ahead (held back or too far), before the window or start, or made
        wide: valid encodings with hostile values."""
        _, fields, flags = self.pick()
        times = fields[10]
        if len(times) < 8:
            return self.seal(fields, flags)
        first = struct.unpack_from("<q", times)[0]
        shift = self.rng.choice([10**9, 5 * 10**9, 10**10, 10**11, 10**13, -10**9, -10**12, 2**40, -(2**40),
                                 9_200_000_000 * 10**9 - first, -5 * 10**8])
        fields[10] = struct.pack("<q", first + shift) + times[8:]
        if self.rng.random() < 0.5:
            fields[8] = min(fields[8], (first + shift) / 1e9)     # keep start before the first time
        return self.seal(fields, flags)

    def dimension(self) -> bytes:
        return self.other_dimension

    def fields_count(self) -> bytes:
        _, fields, flags = self.pick()
        if self.rng.random() < 0.5:
            del fields[self.rng.randrange(14):]
        else:
            fields += [self.rng.choice(WRONG_TYPES)] * self.rng.randint(1, 20)
        return self.seal(fields, flags)

    def unsealed(self) -> bytes:
        """A re-encoded body with a stale checksum (corruption), or for a key, without its MAC."""
        _, fields, flags = self.pick()
        fields[self.rng.randrange(2, 10)] = self.rng.choice(EDGE_INTS[:12])
        frame = self.seal(fields, flags)
        if self.key is not None and self.rng.random() < 0.5:
            return self.seal(fields, flags & ~1)       # no MAC to a keyed node
        if self.key is None:
            return frame[:-5] + bytes([frame[-5] ^ 0x55]) + frame[-4:]
        return frame[:-1] + bytes([frame[-1] ^ 0x01])


def run_bulk(key: bytes | None, count: int, seed: int) -> tuple[Target, Counter]:
    target = Target(key)
    mutate = Mutator(key, seed)
    kinds: Counter = Counter()
    for i in range(count):
        kind, data = mutate()
        kinds[kind] += 1
        target.feed(data, what=f"{kind} #{i} (key={key is not None})")
    return target, kinds


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
def test_bulk_fuzz(key):
    """``BULK`` mutated messages: zero exceptions but MessageError, zero state changes from
    a rejected message, every generator used, every kind of rejection seen."""
    target, kinds = run_bulk(key, BULK, seed=1 if key is None else 2)
    reasons, accepted = target.reasons, target.accepted
    assert sum(reasons.values()) + accepted == BULK
    assert len(kinds) == 15, kinds
    assert reasons["malformed"] > 0.2 * BULK and reasons["corrupt"] > 0.2 * BULK, reasons
    assert 0 < accepted < 0.2 * BULK, (reasons, accepted)
    # "internal" is the catch-all for an exception the checks did not foresee: none may happen
    assert reasons["internal"] == 0, reasons
    for reason in ("version", "misaddressed", "not-a-neighbour", "dimension", "previous-incarnation"):
        assert reasons[reason] > 0, (reason, reasons)
    if key is not None:
        assert reasons["unauthenticated"] > 0.02 * BULK, reasons
        assert reasons["sequence-jump"] == 0, reasons   # with a key the jump bound is not applied
    else:
        assert reasons["sequence-jump"] > 0, reasons
    log.info("bulk fuzz (key: %s): %d messages, %d accepted, rejected by reason %s, by generator %s",
             key is not None, BULK, accepted, dict(reasons), dict(kinds))


def feed_fast(target: Target, mutate: Mutator, count: int) -> None:
    """The fuzz without the state digest (for the memory test): only MessageError may escape."""
    for _ in range(count):
        kind, data = mutate()
        try:
            target.node.receive(data)
        except MessageError:
            continue
        target.reset()


#: allocations made inside numpy's own modules: numpy keeps freed buffers (shapes and
#: strides of arrays, ufunc loop data) in bounded caches that fill slowly under the
#: fuzz's random sizes; their blocks stay allocated and are attributed to whatever numpy
#: call first made them (10 to 20 kB here, growth that levels off)
NUMPY_CACHES = tracemalloc.Filter(False, "*/numpy/*")


def traced_fuzz_memory(count: int, untraced: int = 3_000, warm: int = 1_500) -> tuple[int, int, int]:
    """Run the fuzz under tracemalloc, traced from before the network is built (so the
    baseline is the node under test with its fixtures): 2 x ``untraced`` messages before
    tracing starts, 2 x ``warm`` of warm-up, then 2 x ``count``. Returns (baseline, final,
    total growth with numpy's caches)."""
    for key in (None, KEY):      # untraced: most caches filled before, invisible to tracemalloc
        feed_fast(Target(key), Mutator(key, seed=7), untraced)
    gc.collect()
    tracemalloc.start()
    try:
        nets = {key: build(key) for key in (None, KEY)}
        targets = {key: Target(key, pickle.dumps(net[1])) for key, net in nets.items()}
        mutators = {key: Mutator(key, seed=5 if key is None else 6, frames=net[3]) for key, net in nets.items()}

        def measure(n: int) -> tuple[int, int]:
            for key in targets:
                feed_fast(targets[key], mutators[key], n)
                targets[key].reset()
            clear_caches()   # the decoder's layout cache: bounded (LAYOUT_CACHE_ENTRIES), like numpy's
            gc.collect()
            own = tracemalloc.take_snapshot().filter_traces([NUMPY_CACHES])
            return sum(t.size for t in own.traces), tracemalloc.get_traced_memory()[0]

        baseline, total0 = measure(warm)
        final, total1 = measure(count)
    finally:
        tracemalloc.stop()
    return baseline, final, total1 - total0


def test_fuzz_memory_is_flat():
    """The same fuzz, 2 x MEMORY_RUN more messages, under tracemalloc (which slows it down
    about five times, hence no digests): the memory held at the end is within 5 % of what
    was held after the warm-up, leaving out numpy's bounded caches (see NUMPY_CACHES) and the
    decoder's bounded layout cache (emptied before each snapshot: clear_caches); with
    them the growth is logged). A leak of 2 bytes per message would show."""
    baseline, final, total_growth = traced_fuzz_memory(MEMORY_RUN)
    log.info("fuzz memory: %d bytes after the warm-up, %d after 2 x %d more messages (with numpy's caches: "
             "%+d bytes)", baseline, final, MEMORY_RUN, total_growth)
    assert final <= 1.05 * baseline, (final, baseline)


def test_the_memory_measurement_sees_a_small_leak(monkeypatch):
    """Positive control: a leak of one 100-byte string per rejected message (a rejection
    log that keeps every detail) shows after 2 x 300 messages, far beyond the 5 %."""
    kept = []
    add = RejectionLog.add
    monkeypatch.setattr(RejectionLog, "add", lambda self, reason, detail: (kept.append(detail.ljust(100)),
                                                                           add(self, reason, detail)))
    baseline, final, _ = traced_fuzz_memory(300, untraced=0, warm=100)
    assert final > 1.1 * baseline, (final, baseline)


# ---------------------------------------------------------------- hypothesis: garbage and flips
@FUZZ
@given(data=st.binary(max_size=600))
def test_random_bytes(data):
    Target(None).feed(data, must_reject=True)


@FUZZ
@given(data=st.binary(max_size=600))
def test_random_bytes_with_a_key(data):
    Target(KEY).feed(data, must_reject=True)


@FUZZ
@given(st.data())
def test_multiple_bit_flips(data):
    key = data.draw(st.sampled_from([None, KEY]))
    msg = data.draw(st.sampled_from(valid_messages(key)))
    bits = data.draw(st.lists(st.integers(0, 8 * len(msg) - 1), min_size=1, max_size=24, unique=True))
    out = bytearray(msg)
    for b in bits:
        out[b // 8] ^= 1 << (b % 8)
    Target(key).feed(bytes(out), must_reject=True)


def test_every_truncation():
    for key in (None, KEY):
        target = Target(key)
        for data in valid_messages(key):
            for cut in range(len(data)):
                target.feed(data[:cut], must_reject=True, what=f"cut {cut}")


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
def test_wrong_python_types(key):
    target = Target(key)
    for data in (None, "text", 42, [valid_messages(key)[0]], {"v": 2}, 1.5, object()):
        target.feed(data, must_reject=True)
    assert target.reasons == {"malformed": 7}


# ---------------------------------------------------------------- node-level rejections
def reencode(key: bytes | None, index: int = 0, **changes) -> bytes:
    """A valid message for b with fields replaced (values, or functions of the old value)."""
    msg = decode(valid_messages(key)[index], KEYS[key])
    fields = {f.name: getattr(msg, f.name) for f in dataclasses.fields(InfoMessage)}
    for name, value in changes.items():
        fields[name] = value(np.array(fields[name], copy=True)) if callable(value) else value
    return encode(InfoMessage(**fields), KEYS[key])


def setitem(index, value):
    def change(a):
        a[index] = value
        return a
    return change


INVALID = {
    # (changes, reason)
    "from-non-neighbour": (dict(src="x"), "not-a-neighbour"),
    "from-itself": (dict(src="b"), "not-a-neighbour"),
    "to-another-node": (dict(dst="c"), "misaddressed"),
    "to-the-sender": (dict(dst="a"), "misaddressed"),
    "wrong-n-3": (dict(info=lambda a: a[:, :3, :3], vec=lambda v: v[:, :3]), "dimension"),
    "wrong-n-6": (dict(info=lambda a: np.pad(a, ((0, 0), (0, 2), (0, 2))), vec=lambda v: np.pad(v, ((0, 0), (0, 2)))),
                  "dimension"),
    "naive-to-channel-node": (dict(naive=True, full=False), "malformed"),
    "previous-incarnation": (dict(epoch=10), "previous-incarnation"),
    "sequence-jump": (dict(seq=lambda s: s + MAX_SEQ_JUMP + 10), "sequence-jump"),
    "non-psd-block": (dict(info=setitem(0, np.diag([1.0, 1.0, 1.0, -1.0]))), "malformed"),
    "nan-vec": (dict(vec=setitem((0, 0), np.nan)), "malformed"),
    "time-before-start": (dict(start=lambda s: float(s) + 0.45), "malformed"),
}


@pytest.mark.parametrize("key", [None, KEY], ids=["no-key", "key"])
@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_message_is_rejected_with_its_reason(case, key):
    changes, reason = INVALID[case]
    if case == "sequence-jump" and key is not None:
        target = Target(key)
        assert target.feed(reencode(key, **changes), what=case)     # accepted: a long outage must heal
        assert target.node.stats.rejections == {}
        return
    target = Target(key)
    target.feed(reencode(key, **changes), must_reject=True, what=case)
    assert target.node.stats.rejections == {reason: 1}


def test_interleaved_rejections_do_not_disturb_a_valid_exchange():
    """Garbage between valid messages: the result equals the clean run."""
    clean = fresh_b(None)
    for data in valid_messages(None):
        clean.receive(data)
    node = fresh_b(None)
    for data in valid_messages(None):
        for case in sorted(INVALID):
            with pytest.raises(MessageError):
                node.receive(reencode(None, **INVALID[case][0]))
        node.receive(data)
    assert state_digest(node) == state_digest(clean)
    assert node.stats.messages_rejected == 3 * len(INVALID)


# ---------------------------------------------------------------- defects of version 1 found by fuzzing
def test_huge_state_time_is_rejected():
    with np.errstate(over="ignore", invalid="ignore"):     # the encoder turns 1e300 s into some int64
        data = reencode(None, times=lambda t: np.append(t[:-1], 1e300))
    Target(None).feed(data, must_reject=True)


def test_indefinite_block_hidden_by_a_large_entry_is_rejected():
    block = np.diag([4.0, 1e11, 0.0, 0.0])
    block[0, 2] = block[2, 0] = 5.0     # eigenvalue -4, invisible next to 1e11 without scaling
    assert indefinite(block[None])[0] and np.linalg.eigvalsh(block)[0] < -1.0
    target = Target(None)
    target.feed(reencode(None, info=setitem(-1, block)), must_reject=True)
    assert target.node.stats.rejections == {"malformed": 1}


def test_times_with_the_same_key_are_rejected():
    """Two blocks 0.5 ns apart have the same nanosecond key: the encoder writes a zero gap,
    which decode refuses (version 1 accepted them and left phantom information)."""
    msg = decode(valid_messages(None)[0])
    t = msg.times[-1]
    crafted = dataclasses.replace(msg, seq=msg.seq + 1, times=np.append(msg.times[:-1], [t - 0.3e-9, t + 0.2e-9]),
                                  info=np.concatenate([msg.info[:-1], 10 * np.eye(4)[None], 10 * np.eye(4)[None]]),
                                  vec=np.concatenate([msg.vec[:-1], np.zeros((2, 4))]))
    Target(None).feed(encode(crafted), must_reject=True)


def test_huge_finite_values_do_not_poison_the_estimate():
    for change in (dict(info=setitem((-1, 0, 0), 1e308)), dict(vec=setitem((slice(-2, None), 0), 1e308)),
                   dict(vec=setitem((-1, slice(0, 2)), 1e308)), dict(info=setitem((-1, 0, 0), 1e12))):
        Target(None).feed(reencode(None, **change))
