"""A forged incarnation number (issue 23, item 4): without a key, one frame with a valid
checksum and a larger ``epoch`` must not lock the genuine neighbour out; one far beyond any
clock is refused; with a key the forgery is refused outright. Exactness is checked against
filterpy's Kalman filter (tests/helpers/fusion_harness.py)."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from dfusion.errors import MessageError
from dfusion.fusion.incarnation import MAX_EPOCH_AHEAD_NS, REVERT_STREAK, Incarnations
from dfusion.fusion.tree import initial_parents
from dfusion.models import PositionSensor
from dfusion.wire import FrameKey, decode, encode
from tests.helpers.dynamic_harness import build_node, rel, settle
from tests.helpers.fusion_harness import KEY, central_kalman, make_node, state_digest

SENSOR = PositionSensor(2, 0.5)
HOUR = 3600 * 10**9


class Pair:
    """Nodes a - b (a fixed tree unless ``tree``), one measurement each and an exchange every
    step of 0.1 s (the send period); ``key``: the network key."""

    def __init__(self, key: bytes | None = None, tree: bool = False) -> None:
        if tree:
            links = {("a", "b")}
            start = initial_parents(["a", "b"], sorted(links))
            self.a, self.b = (build_node(n, links, start, e, 400) for n, e in (("a", 11), ("b", 22)))
            self.links = links
        else:
            self.a = make_node("a", ["b"], epoch=11, window=400, key=key)
            self.b = make_node("b", ["a"], epoch=22, window=400, key=key)
        self.rng = np.random.default_rng(4)
        self.meas: list = []
        self.k = 0

    def step(self, deliver_to_b: bool = True) -> int | None:
        """One step; returns what b's receive of a's message returned (None: not delivered)."""
        self.k += 1
        t = round(0.1 * self.k, 9)
        for x in (self.a, self.b):
            x.predict(t)
            z = self.rng.normal(size=2)
            x.update(t, z, SENSOR)
            self.meas.append((t, z, 0.5))
        to_b = dict(self.a.outgoing())["b"]
        to_a = dict(self.b.outgoing())["a"]
        self.a.receive(to_a)
        return self.b.receive(to_b) if deliver_to_b else None

    def last_to_b(self) -> bytes:
        """What an eavesdropper copies: a's next message to b (made without changing a)."""
        return self.a.message_to("b")

    def assert_exact(self) -> None:
        mean, cov = central_kalman(self.meas, round(0.1 * self.k, 9))
        for x in (self.a, self.b):
            m, P = x.estimate()
            assert rel(m, mean) < 1e-9 and rel(P, cov) < 1e-9, (x.name, rel(m, mean), rel(P, cov))


def forge(frame: bytes, key=None, **changes) -> bytes:
    return encode(dataclasses.replace(decode(frame, key), **changes))


@pytest.mark.parametrize("content", ["copy", "empty-full"])
def test_without_a_key_the_genuine_neighbour_is_fused_again_at_its_next_message(content):
    """A stranger copies a frame of a, gives it an incarnation an hour ahead of the clock
    (plausible: accepted), once; as "empty-full" it also claims a holds nothing, which clears
    everything b had from a. a's next genuine message, one send period later, switches b back to
    a's incarnation and is fused; both ends resynchronize (full messages) and are exact again."""
    p = Pair()
    for _ in range(10):
        p.step()
    p.step(deliver_to_b=False)                      # (a's message of this step: its content reaches b later)
    frame = p.a.message_to("b")
    changes = dict(epoch=time.time_ns() + HOUR)
    if content == "empty-full":
        msg = decode(frame)
        changes.update(full=True, times=msg.times[:0], info=msg.info[:0], vec=msg.vec[:0], cleared=msg.cleared[:0])
    p.b.receive(forge(frame, **changes))
    assert p.b.channels["a"].epoch == changes["epoch"]          # taken for a restart of a
    fused = p.step()                                            # the forgery stopped: a's next message
    assert fused > 0                                            # fused at once
    assert p.b.channels["a"].epoch == p.a.epoch
    assert p.b.stats.incarnations_reverted == 1 and p.b.stats.rejections == {}
    for _ in range(3):
        p.step()
    p.assert_exact()
    assert p.a.stats.resyncs >= 1        # a saw b's new channel start and sent it a full message


def test_a_forger_claiming_a_late_clock_is_undone_after_a_few_genuine_messages():
    """The forged frame also claims a ``sent_at`` far in the future: a's messages are not
    "made after" it, so b takes a back on the REVERT_STREAK-th of them in a row."""
    p = Pair()
    for _ in range(10):
        p.step()
    p.b.receive(forge(p.last_to_b(), epoch=time.time_ns() + HOUR, sent_at=9e9))
    results = []
    for _ in range(REVERT_STREAK):
        try:
            results.append(p.step())
        except MessageError as err:
            results.append(err.reason)
    assert results[:-1] == ["previous-incarnation"] * (REVERT_STREAK - 1) and results[-1] > 0
    assert p.b.stats.incarnations_reverted == 1
    for _ in range(3):
        p.step()
    p.assert_exact()


def test_an_incarnation_far_beyond_the_clock_is_refused_and_changes_nothing():
    p = Pair()
    for _ in range(5):
        p.step()
    frame = p.last_to_b()
    before = state_digest(p.b)
    for epoch in (time.time_ns() + MAX_EPOCH_AHEAD_NS + HOUR, 2**62, 2**63 - 1):
        with pytest.raises(MessageError) as info:
            p.b.receive(forge(frame, epoch=epoch))
        assert info.value.reason == "implausible-incarnation"
    assert state_digest(p.b) == before and p.b.stats.rejections == {"implausible-incarnation": 3}
    p.step()
    p.assert_exact()


def test_with_a_key_the_forgery_is_refused_outright():
    p = Pair(key=KEY)
    for _ in range(5):
        p.step()
    frame = p.last_to_b()
    before = state_digest(p.b)
    msg = decode(frame, FrameKey(KEY))
    for key in (None, FrameKey(b"a-guess-at-the-network-key")):
        with pytest.raises(MessageError) as info:
            p.b.receive(encode(dataclasses.replace(msg, epoch=time.time_ns() + HOUR), key))
        assert info.value.reason == "unauthenticated"
    assert state_digest(p.b) == before
    for _ in range(3):
        p.step()
    p.assert_exact()


def test_a_genuine_restart_is_not_undone_by_its_previous_incarnation_still_under_way():
    """a restarts; a message its previous incarnation made before (delayed on the way) arrives
    after the new incarnation's first: it continues the old stream but was made earlier, so it is
    refused (a restart is not taken back)."""
    p = Pair()
    for _ in range(6):
        p.step()
    late = p.last_to_b()
    a2 = make_node("a", ["b"], epoch=p.a.epoch + 1, window=400)
    a2.predict(round(0.1 * p.k, 9))
    p.a = a2
    p.step()
    with pytest.raises(MessageError) as info:
        p.b.receive(late)
    assert info.value.reason == "previous-incarnation"
    assert p.b.channels["a"].epoch == a2.epoch and p.b.stats.incarnations_reverted == 0


def test_the_judge_on_its_own():
    clock = [10**18]
    judge = Incarnations(keyed=False, clock=lambda: clock[0])
    assert judge.judge("a", 5, 0, 0.0, None, -1) == ("first", -1)
    assert judge.judge("a", 5, 7, 1.0, 5, 6) == ("same", 6)
    assert judge.judge("a", 10**18 + MAX_EPOCH_AHEAD_NS + 1, 0, 1.0, 5, 7)[0] == "implausible-incarnation"
    assert judge.judge("a", 9, 0, 1.0, 5, 7) == ("new", -1)        # a restart (or a forgery)
    assert judge.judge("a", 5, 7, 2.0, 9, 0)[0] == "previous-incarnation"     # a replay: not newer than 7
    assert judge.judge("a", 4, 8, 2.0, 9, 0)[0] == "previous-incarnation"     # older than the replaced one
    assert judge.judge("a", 5, 8, 0.5, 9, 0)[0] == "previous-incarnation"     # made before 9's first message
    assert judge.judge("a", 5, 9, 2.0, 9, 0) == ("revert", 8)                 # made after it: back to 5
    assert judge.replaced["a"].epoch == 9
    keyed = Incarnations(keyed=True, clock=lambda: clock[0])
    keyed.judge("a", 9, 0, 1.0, 5, 7)
    assert keyed.judge("a", 5, 8, 2.0, 9, 0)[0] == "previous-incarnation"     # with a key: never back


def test_links_that_change_recover_from_a_forged_incarnation_too():
    """With the tree rule: a forged fusion frame of a (b's parent) with a plausible incarnation
    makes b forget a (a new tree epoch); a's next message takes the incarnation back, the one
    after it is fused in the re-formed tree, and after the links settle (and what b held is
    released) both are exact."""
    p = Pair(tree=True)
    for _ in range(8):
        p.step()
    p.b.receive(forge(p.last_to_b(), epoch=time.time_ns() + HOUR))
    assert p.b.incarnations["a"] != p.a.epoch
    p.step()
    assert p.b.incarnations["a"] == p.a.epoch and p.b.stats.incarnations_reverted == 1
    assert p.step() > 0        # fused again in the re-formed tree (b had started a new tree epoch)
    nodes = {"a": p.a, "b": p.b}
    settle(nodes, p.links)
    t = round(0.1 * p.k + p.b.hold + 0.1, 9)
    for x in nodes.values():
        x.predict(t)
    settle(nodes, p.links)
    mean, cov = central_kalman(p.meas, t)
    for x in nodes.values():
        m, P = x.estimate()
        assert rel(m, mean) < 1e-9 and rel(P, cov) < 1e-9, x.name


def test_a_switch_back_whose_message_is_refused_later_changes_nothing(monkeypatch):
    """A message of a's genuine incarnation that the judge takes as a switch back (``revert``) but
    that is then refused (here a failure injected after the checks, in the receive's planning)
    leaves b exactly as it was: the judge's record of the replaced incarnation and the counter are
    put back, so a's next genuine message still switches the link back and is fused (before, the
    record pointed at the forged incarnation from then on, and a stayed locked out)."""
    from dfusion.fusion.node import FusionNode

    p = Pair()
    for _ in range(10):
        p.step()
    p.step(deliver_to_b=False)
    frame = p.a.message_to("b")
    p.b.receive(forge(frame, epoch=time.time_ns() + HOUR))          # the forgery, once
    record = p.b._incarnation_judge.replaced["a"]
    before = state_digest(p.b)
    genuine = forge(p.a.message_to("b"), sent_at=decode(frame).sent_at + 1.0)

    def fail(self, deltas):
        raise RuntimeError("injected")

    with monkeypatch.context() as m:
        m.setattr(FusionNode, "_within_reach", fail)
        with pytest.raises(MessageError) as err:
            p.b.receive(genuine)
    assert err.value.reason == "internal"
    assert p.b._incarnation_judge.replaced["a"] == record and p.b.stats.incarnations_reverted == 0
    assert state_digest(p.b) == before
    fused = p.step()                                                 # a's next genuine message
    assert fused > 0 and p.b.channels["a"].epoch == p.a.epoch and p.b.stats.incarnations_reverted == 1
    for _ in range(3):
        p.step()
    p.assert_exact()


def test_a_forged_jump_of_the_replaced_incarnation_does_not_move_its_record():
    """Without a key, a forged frame of the replaced incarnation with a sequence number far
    ahead (and an early ``sent_at``, so it does not switch back) is refused and leaves the record
    as it was: the genuine sender's next messages still switch the link back (before, the record
    jumped to the forged number and every genuine message was "previous-incarnation")."""
    from dfusion.fusion.channel import MAX_SEQ_JUMP

    judge = Incarnations(keyed=False, clock=lambda: 10**18)
    judge.judge("a", 5, 0, 0.0, None, -1)
    assert judge.judge("a", 9, 0, 1.0, 5, 7) == ("new", -1)                     # the forged incarnation
    record = judge.replaced["a"]
    assert judge.judge("a", 5, 7 + MAX_SEQ_JUMP + 1, 0.5, 9, 0)[0] == "previous-incarnation"
    assert judge.replaced["a"] == record
    assert judge.judge("a", 5, 8, 2.0, 9, 0) == ("revert", 7)                   # the genuine a, made after
