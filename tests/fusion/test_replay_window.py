"""The channel's replay window (``ChannelFilter.was_applied`` / ``note_applied``) against a
brute-force reference: the set of every sequence number applied so far, and the rule of
RFC 4303 section 3.4.3 (a number is refused when it was applied, or when it is more than
``REPLAY_WINDOW`` below the highest one applied).

Sequence numbers come from peers: a jump of any size up to the wire's limit (2^63 - 1) must
cost constant time and memory (a 64-bit mask, never a shift by the jump)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dfusion.fusion.channel import REPLAY_WINDOW, ChannelFilter

TOP = 2**63 - 1


def reference_refuses(applied: set[int], seq: int) -> bool:
    if not applied:
        return False
    top = max(applied)
    return seq in applied or top - seq > REPLAY_WINDOW


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.integers(0, 200), st.integers(0, TOP), st.integers(-70, 70)), min_size=1, max_size=60))
def test_the_window_refuses_exactly_what_the_reference_refuses(steps):
    ch = ChannelFilter("a", "b", 2)
    applied: set[int] = set()
    seq = 0
    for step in steps:
        # a step is an absolute number (0-200, or anywhere up to 2^63 - 1) or a move from the last one
        seq = min(max(seq + step, 0), TOP) if -70 <= step <= 70 else step
        assert ch.was_applied(seq) == reference_refuses(applied, seq), (seq, sorted(applied)[-5:])
        if not reference_refuses(applied, seq):
            ch.note_applied(seq)
            applied.add(seq)


@pytest.mark.parametrize("jump", [REPLAY_WINDOW - 1, REPLAY_WINDOW, REPLAY_WINDOW + 1, 2**33, 2**62, TOP - 5])
def test_a_jump_of_any_size_is_one_step(jump):
    """A peer's message 2^62 ahead is applied like any other (before: the mask was shifted by the
    jump, a Python integer of 2^62 bits: MemoryError, and 10 s and 3.4 GB at 2^33)."""
    ch = ChannelFilter("a", "b", 2)
    for s in (3, 4, 6):
        ch.note_applied(s)
    ch.note_applied(6 + jump)
    applied = {3, 4, 6, 6 + jump}
    for s in [3, 4, 5, 6, 7, 6 + jump - 1, 6 + jump, 6 + jump + 1, 6 + jump - REPLAY_WINDOW,
              6 + jump - REPLAY_WINDOW - 1]:
        assert ch.was_applied(s) == reference_refuses(applied, s), s


def test_the_window_holds_64_numbers_below_the_highest():
    ch = ChannelFilter("a", "b", 2)
    rng = np.random.default_rng(5)
    order = rng.permutation(np.arange(1000, 1000 + REPLAY_WINDOW + 1))
    for s in order:
        assert not ch.was_applied(int(s))
        ch.note_applied(int(s))
    assert all(ch.was_applied(s) for s in range(0, 1000 + REPLAY_WINDOW + 1))
    assert not ch.was_applied(1000 + REPLAY_WINDOW + 1)
