"""Replays, forgeries, restarts, bounded resources and rate-limited logs of FusionNode.receive.

* Replay and hygiene: a message of another run or another network fails authentication;
  one of an earlier incarnation, or one whose sequence number jumps too far, is rejected;
  all of them are counted by reason and change nothing. The limits are pinned too: the
  MAC key is shared network-wide, so a key holder can forge any sender; without a key,
  runs are told apart only by incarnations.
* Restarts: a sender's new incarnation (larger epoch) is recognized, its old messages
  still in flight are rejected, and the nodes end equal to filterpy's centralized filter.
* Bounded resources: information too far ahead (beyond ``max_ahead`` seconds or
  ``max_held`` held-back times) is not stored, is counted, is not acknowledged, and
  arrives later (nothing is lost for good); an oversized frame is refused before it is
  read.
* Rate-limited logging: 100,000 rejected messages make fewer than 100 log lines, whose
  counts by reason add up.
"""
from __future__ import annotations

import dataclasses
import logging
import re
import time
import zlib

import numpy as np
import pytest

from dfusion.errors import MessageError
from dfusion.fusion import FusionNode
from dfusion.fusion import node as node_module
from dfusion.fusion.channel import MAX_SEQ_JUMP
from dfusion.models import PositionSensor
from dfusion.wire import MAX_MESSAGE_BYTES, FrameKey, decode, encode

from tests.helpers.fusion_harness import KEY, build_chain, central_kalman, make_node, state_digest

SENSOR = PositionSensor(2, 0.5)
STD = 0.5


def rejected(node: FusionNode, data: bytes, reason: str) -> MessageError:
    """``data`` is rejected for ``reason``, counted once, and changes nothing else."""
    before = state_digest(node)
    count = node.stats.rejections.get(reason, 0)
    with pytest.raises(MessageError) as info:
        node.receive(data)
    assert info.value.reason == reason, (info.value.reason, str(info.value))
    assert node.stats.rejections[reason] == count + 1
    assert state_digest(node) == before
    return info.value


def assert_exact(nodes, meas, t: float, rtol: float = 1e-9) -> None:
    """Every node's newest state equals filterpy's Kalman filter given ``meas`` (to ``rtol``)."""
    mean, cov = central_kalman(meas, t)
    for node in nodes:
        m, P = node.estimate()
        np.testing.assert_allclose(P, cov, rtol=rtol, atol=rtol * np.abs(cov).max(), err_msg=node.name)
        np.testing.assert_allclose(m, mean, rtol=rtol, atol=rtol * np.abs(mean).max(), err_msg=node.name)


def assert_not_over_confident(node: FusionNode, meas, t: float) -> None:
    """P_node - P_central is positive semi-definite (to rounding): no information counted twice."""
    _, cov = central_kalman(meas, t)
    eig = np.linalg.eigvalsh(node.estimate()[1] - cov)
    assert eig[0] >= -1e-9 * np.abs(cov).max(), (node.name, eig[0])


def pair(**kw) -> tuple[FusionNode, FusionNode, list]:
    """Nodes a - b at t = 1.0 (10 steps), measurements recorded for the reference."""
    a = make_node("a", ["b"], epoch=11, window=400, **kw)
    b = make_node("b", ["a"], epoch=22, window=400, **kw)
    for k in range(1, 11):
        a.predict(round(0.1 * k, 9))
        b.predict(round(0.1 * k, 9))
    return a, b, []


def measure(node: FusionNode, t: float, z, meas: list) -> None:
    node.update(t, z, SENSOR)
    meas.append((t, np.asarray(z, float), STD))


# ---------------------------------------------------------------- replay and hygiene
@pytest.mark.parametrize("theirs", [dict(run="run-2"), dict(network="plant-4"), dict(run="run-2", network="plant-4")],
                         ids=["another-run", "another-network", "both"])
def test_a_message_of_another_run_or_network_fails_authentication(theirs):
    """The same network key, another run (a message captured earlier and replayed into a new
    run) or another network: the derived MAC key differs."""
    ours = dict(key=KEY, network="plant-3", run="run-1")
    a, b, c, _, _ = build_chain(**ours)
    other = build_chain(**(ours | theirs))[0]
    measure(other, 0.5, [1.0, 2.0], [])
    data = other.message_to("b")
    err = rejected(b, data, "unauthenticated")
    assert "wrong key, network or run" in str(err)
    # only the derived key told them apart: authenticated for this run, it is accepted
    params = ours | theirs
    msg = decode(data, FrameKey(KEY, params["network"], params["run"]))
    assert b.receive(encode(msg, FrameKey(KEY, "plant-3", "run-1"))) > 0


def test_a_message_without_a_mac_or_with_another_key_is_rejected():
    a, b, c, fresh, _ = build_chain(KEY, network="n", run="r")
    msg = decode(fresh, FrameKey(KEY, "n", "r"))
    rejected(b, encode(msg), "unauthenticated")
    rejected(b, encode(msg, FrameKey(b"another-network-key-32-bytes-long", "n", "r")), "unauthenticated")
    b.receive(fresh)


def test_a_message_of_an_earlier_incarnation_is_rejected():
    a, b, c, fresh, _ = build_chain()
    b.receive(fresh)
    msg = decode(fresh)
    err = rejected(b, encode(dataclasses.replace(msg, epoch=msg.epoch - 1, seq=msg.seq + 1)), "previous-incarnation")
    assert "earlier incarnation" in str(err)


def test_a_sequence_jump_beyond_max_seq_jump_is_rejected_without_a_key():
    """Without a network key, a jump past MAX_SEQ_JUMP is rejected (a stranger cannot lock the
    sender out with one message numbered near 2^63)."""
    a, b, c, fresh, _ = build_chain()
    b.receive(fresh)
    msg = decode(fresh)
    last = msg.seq
    rejected(b, encode(dataclasses.replace(msg, seq=last + MAX_SEQ_JUMP + 1)), "sequence-jump")
    b.receive(encode(dataclasses.replace(msg, seq=last + MAX_SEQ_JUMP)))        # the largest jump allowed
    # in a new incarnation the count starts again from -1
    fresh_epoch = dataclasses.replace(msg, epoch=msg.epoch + 1)
    rejected(b, encode(dataclasses.replace(fresh_epoch, seq=MAX_SEQ_JUMP)), "sequence-jump")
    b.receive(encode(dataclasses.replace(fresh_epoch, seq=MAX_SEQ_JUMP - 1)))
    assert b.stats.rejections == {"sequence-jump": 2}


def test_with_a_key_a_link_that_lost_more_than_max_seq_jump_messages_comes_back():
    """With a network key the jump bound is not applied: a sender whose last 1,000,001 messages
    were all lost (28 h at 10 Hz) is heard again, and both nodes end on the centralized filter."""
    a, b, meas = pair(key=KEY)
    exchange(a, b, 0.5)
    measure(a, 0.6, [1.0, 2.0], meas)
    measure(b, 0.7, [-1.0, 0.5], meas)
    ch = a.channels["b"]
    ch.seq_out += MAX_SEQ_JUMP + 1                      # as if that many messages had been lost
    for t in (0.8, 0.9, 1.0, 1.1):
        exchange(a, b, t)
    assert b.stats.rejections == {}
    assert_exact([a, b], meas, 1.1)


def test_a_forged_sender_without_the_key_is_rejected():
    a, b, c, fresh, _ = build_chain(KEY, network="n", run="r")
    msg = decode(fresh, FrameKey(KEY, "n", "r"))
    forged = dataclasses.replace(msg, seq=msg.seq + 1, vec=msg.vec * 10)
    rejected(b, encode(forged, FrameKey(b"a-guess-at-the-network-key", "n", "r")), "unauthenticated")
    rejected(b, encode(forged), "unauthenticated")


def test_limit_a_key_holder_can_forge_any_sender():
    """The MAC key is shared by the whole network: it proves a message comes from *some*
    key holder, not from the node named in ``src``. Node c (a key holder) forges a message
    "from a" with a's next sequence number: b accepts it; and a forged larger epoch (a
    plausible one: an hour ahead of the clock; one far beyond any clock is refused) makes b
    take it for a restart of a and reject a's genuine messages as an earlier incarnation
    from then on (with a key incarnations are taken as authentic: no switching back,
    dfusion.fusion.incarnation). Per-node keys (or signatures) would be needed to prevent this."""
    a, b, c, fresh, _ = build_chain(KEY, network="n", run="r")
    key_of_c = FrameKey(KEY, "n", "r")          # c derives the same key
    msg = decode(fresh, key_of_c)
    assert b.receive(encode(dataclasses.replace(msg, vec=msg.vec + 1.0), key_of_c)) > 0
    assert b.stats.messages_rejected == 0
    rejected(b, encode(dataclasses.replace(msg, epoch=2**63 - 1, seq=0), key_of_c), "implausible-incarnation")
    lockout = dataclasses.replace(msg, epoch=time.time_ns() + 3600 * 10**9, seq=0)
    b.receive(encode(lockout, key_of_c))
    for _ in range(4):
        rejected(b, a.message_to("b"), "previous-incarnation")


def test_limit_without_a_key_runs_are_told_apart_only_by_incarnations():
    """Without a key nothing ties a message to a run. A message of an earlier run carries
    an earlier incarnation of its sender (epochs grow: the default is the time in ns):
    once b has heard from the current incarnation it is rejected; before that it is taken
    for the sender's current incarnation until the current one is heard."""
    _, _, _, old_message, _ = build_chain()                # a's incarnation 11, an earlier run
    current = encode(dataclasses.replace(decode(old_message), epoch=11_000, seq=0))
    b = make_node("b", ["a", "c"], epoch=22)
    b.predict(0.5)
    assert b.receive(old_message) > 0                      # nothing heard from a yet: accepted
    b.receive(current)                                     # the current incarnation replaces it
    rejected(b, old_message, "previous-incarnation")       # from now on the old run is rejected


# ---------------------------------------------------------------- restarts
def test_a_restarted_sender_is_recognized_and_its_old_messages_rejected():
    a, b, meas = pair()
    own_a = []
    for k, t in enumerate([0.2, 0.5, 0.7, 0.9]):
        measure(a, t, [t, 1.0 + k], meas)
        own_a.append((t, [t, 1.0 + k]))
        measure(b, t - 0.05, [t, -1.0], meas)
        b.receive(a.message_to("b"))
        a.receive(b.message_to("a"))
    in_flight = a.message_to("b")            # sent just before a restarts, delivered late
    # a restarts: a fresh incarnation with a larger epoch replays its own measurements
    a2 = make_node("a", ["b"], epoch=a.epoch + 1, window=400)
    a2.predict(1.0)
    for t, z in own_a:
        a2.update(t, z, SENSOR)
    b.receive(a2.message_to("b"))
    ch = b.channels["a"]
    assert ch.epoch == a2.epoch and ch.next_is_full()
    err = rejected(b, in_flight, "previous-incarnation")
    assert f"({a.epoch} < {a2.epoch})" in str(err)
    first = b.message_to("a")
    assert decode(first).full and decode(first).dst_epoch == a2.epoch
    a2.receive(first)
    for _ in range(3):
        a2.receive(b.message_to("a"))
        b.receive(a2.message_to("b"))
    assert_exact([a2, b], meas, 1.0)


def test_limit_a_restart_with_a_smaller_epoch_is_rejected():
    """An incarnation must have a larger epoch than the one before (the default is the time
    in ns): a node whose clock went back is taken for its own earlier incarnation and
    rejected until its clock passes the old epoch."""
    a, b, meas = pair()
    b.receive(a.message_to("b"))
    a2 = make_node("a", ["b"], epoch=a.epoch - 1, window=400)
    a2.predict(1.0)
    rejected(b, a2.message_to("b"), "previous-incarnation")


# ---------------------------------------------------------------- bounded resources
def exchange(a: FusionNode, b: FusionNode, t: float) -> None:
    for node in (a, b):
        node.predict(t)
    b.receive(a.message_to("b"))
    a.receive(b.message_to("a"))


def test_blocks_far_in_the_future_are_applied_later():
    """a runs 20 s ahead of b: its block at t = 21 is beyond b's max_ahead (10 s). b applies
    the rest of the message, counts the block, does not acknowledge the message, and gets
    the block again once it is within reach: at the end b equals the centralized filter."""
    a, b, meas = pair()
    measure(a, 0.5, [1.0, 2.0], meas)
    a.predict(21.0)
    measure(a, 21.0, [30.0, 5.0], meas)
    data = a.message_to("b")
    seq = decode(data).seq
    assert b.receive(data) == 1                               # only the block at 0.5
    assert b.stats.blocks_too_far_ahead == 1
    assert b.channels["a"].information(21_000_000_000) is None
    reply = decode(b.message_to("a"))
    assert reply.ack < seq                                    # not acknowledged
    a.receive(encode(reply))
    t = 1.0
    while t < 21.0:
        t = round(t + 1.0, 9)
        b.predict(t)
        b.receive(a.message_to("b"))
        a.receive(b.message_to("a"))
    assert b.stats.blocks_too_far_ahead >= 1
    exchange(a, b, 21.0)
    assert_exact([a, b], meas, 21.0)


def test_more_held_back_times_than_max_held_are_applied_later():
    """b (max_held = 2) is at t = 1.0; a sends four times ahead of it: two are held back, two
    are refused and counted; once b moves on, every one of them is fused."""
    a, b, meas = pair(max_held=2)
    a.predict(1.4)
    for t in (1.1, 1.2, 1.3, 1.4):
        measure(a, t, [t, -t], meas)
    data = a.message_to("b")
    b.receive(data)
    assert b.stats.blocks_too_far_ahead == 2
    assert decode(b.message_to("a")).ack < decode(data).seq
    for t in (1.2, 1.3, 1.4, 1.5, 1.6):
        exchange(a, b, t)
        assert_not_over_confident(b, meas, t)
    assert_exact([a, b], meas, 1.6)


def test_full_message_updating_held_times_at_max_held_is_not_double_counted():
    """b holds max_held = 2 times back (1.1, 1.2) when a full message brings new values for
    both. Before the fix the refused update became a zero entry of the channel while the
    store kept the old value, and the resent value was then added on top of it
    (min eig(P_b - P_central) = -0.096)."""
    a, b, meas = pair(max_held=2)
    a.predict(1.2)
    measure(a, 1.1, [1.0, 1.0], meas)
    measure(a, 1.2, [2.0, 2.0], meas)
    a.message_to("b")                                  # the first (full) message is lost
    b.receive(a.message_to("b"))                       # partial: both times held back
    a.receive(b.message_to("a"))                       # the acknowledgement shows the loss
    assert a.channels["b"].next_is_full()
    measure(a, 1.1, [1.5, 1.0], meas)
    measure(a, 1.2, [2.5, 2.0], meas)
    b.receive(a.message_to("b"))                       # full, with new values for the held times
    for t in (1.3, 1.4, 1.5, 1.6):
        exchange(a, b, t)
        assert_not_over_confident(b, meas, t)
    assert_exact([a, b], meas, 1.6)


def test_cleared_times_ahead_are_bounded_like_blocks():
    """Cleared times (and zero blocks) change no information, so only the channel's own bound
    stops them: one valid message clearing 100,000 times in the future, sent five times,
    leaves b's channel with at most ``max_held`` entries ahead of its newest state (before
    the bound: 500,000 entries, 93 MB); the message's other blocks are fused, it is not
    acknowledged, and the network still ends on the centralized filter."""
    a, b, meas = pair(max_held=8)
    exchange(a, b, 1.0)
    measure(a, 1.0, [1.0, 2.0], meas)
    msg = decode(a.message_to("b"))
    assert not msg.full
    cleared = 1.0 + 0.05 * np.arange(1, 100_001)          # 1.05 .. 5001 s: some within 10 s, most beyond
    for i in range(5):
        forged = dataclasses.replace(msg, seq=msg.seq + i, cleared=cleared)
        b.receive(encode(forged))
        ch = b.channels["a"]
        ahead = np.count_nonzero(ch.keys > 1_000_000_000)
        assert ahead <= b.max_held, ahead
        assert decode(b.message_to("a")).ack < forged.seq        # not acknowledged: a sends again
    assert b.channels["a"].keys.size <= b.max_held + len(b.filter.times) + 1
    for t in (1.1, 1.2, 1.3):
        exchange(a, b, t)
        assert_not_over_confident(b, meas, t)
    assert_exact([a, b], meas, 1.3)


def test_an_oversized_frame_is_rejected_before_it_is_parsed():
    a, b, c, fresh, _ = build_chain()
    big = fresh[:4] + b"\x00" * MAX_MESSAGE_BYTES
    err = rejected(b, big, "oversized")
    assert f"exceeds the limit of {MAX_MESSAGE_BYTES}" in str(err)
    # fast: far less than one pass over the frame (a CRC over 4 MiB)
    times = []
    for _ in range(21):
        t0 = time.perf_counter()
        with pytest.raises(MessageError):
            b.receive(big)
        times.append(time.perf_counter() - t0)
    one_pass = []
    for _ in range(3):
        t0 = time.perf_counter()
        zlib.crc32(big)
        one_pass.append(time.perf_counter() - t0)
    assert np.median(times) < min(one_pass) / 5, (np.median(times), min(one_pass))
    # the limit is the node's own
    small = make_node("b", ["a", "c"], epoch=22, max_message_bytes=len(fresh) - 1)
    small.predict(0.5)
    rejected(small, fresh, "oversized")


# ---------------------------------------------------------------- rate-limited logging
SUMMARY = re.compile(r"^b: ([\d,]+) messages rejected since the last report: (.*) \(last: ")
FIRST = re.compile(r"^b: rejected a message \(([a-z-]+)\): ")


def garbage(b: FusionNode, fresh: bytes) -> list[tuple[bytes, str]]:
    """Rejected messages of several kinds with their reasons: 17 in 20 are refused by the
    cheap frame checks, 3 in 20 are decoded first (to keep the test fast)."""
    msg = decode(fresh)
    cheap = [
        (fresh[:-1] + bytes([fresh[-1] ^ 1]), "corrupt"),
        (b"DF\x01\x02" + fresh[4:], "version"),
        (b"\x83\xa1v\x01", "version"),
        (b"not a frame at all", "malformed"),
    ]
    decoded = [
        (encode(dataclasses.replace(msg, dst="c")), "misaddressed"),
        (encode(dataclasses.replace(msg, src="x")), "not-a-neighbour"),
        (encode(dataclasses.replace(msg, epoch=1)), "previous-incarnation"),
    ]
    return (cheap * 5)[:17] + decoded


def parse(records) -> tuple[int, dict]:
    """Lines and the counts by reason they report."""
    counts: dict = {}
    lines = 0
    for r in records:
        text = r.getMessage()
        lines += 1
        if m := FIRST.match(text):
            counts[m.group(1)] = counts.get(m.group(1), 0) + 1
        elif m := SUMMARY.match(text):
            parts = dict(p.rsplit(" ", 1) for p in m.group(2).split(", "))
            for reason, n in parts.items():
                counts[reason] = counts.get(reason, 0) + int(n.replace(",", ""))
            assert sum(int(n.replace(",", "")) for n in parts.values()) == int(m.group(1).replace(",", ""))
        else:
            raise AssertionError(f"unexpected log line: {text}")
    return lines, counts


@pytest.mark.parametrize("clock", ["real", "100 s"])
def test_100000_rejections_make_fewer_than_100_log_lines(caplog, monkeypatch, clock):
    """100,000 rejected messages: at most one line per log interval (10 s) plus the first
    one, and the counts by reason in the lines add up to the node's counters. With the
    real clock the run takes a few seconds; with a clock that advances 1 ms per rejection
    it spans 100 s (ten intervals)."""
    a, b, c, fresh, _ = build_chain()
    if clock != "real":
        now = [0.0]

        def monotonic():
            now[0] += 0.001
            return now[0]
        monkeypatch.setattr(node_module.time, "monotonic", monotonic)
    kinds = garbage(b, fresh)
    digest = state_digest(b)
    caplog.set_level(logging.WARNING, logger="dfusion.fusion.node")
    for i in range(100_000):
        data, reason = kinds[i % len(kinds)]
        try:
            b.receive(data)
        except MessageError as exc:
            assert exc.reason == reason
        else:
            raise AssertionError("a garbage message was accepted")
    b.flush_log()
    assert state_digest(b) == digest
    records = [r for r in caplog.records if r.name == "dfusion.fusion.node"]
    lines, counts = parse(records)
    assert lines < 100
    if clock != "real":
        assert 10 <= lines <= 13, lines
    assert counts == b.stats.rejections
    assert sum(counts.values()) == b.stats.messages_rejected == 100_000
    assert set(counts) == {reason for _, reason in kinds}
