"""The channel filter's per-message semantics, checked after *every* delivery.

The tree-wide exactness tests (``test_fusion_exactness.py``) compare nodes with the
centralized filter once the final lossless rounds are done, and those rounds would
repair a node that let an older, reordered message replace newer information. Here
a single link is checked message by message: node ``a`` measures (in random order,
so many measurements are late) and emits a message after each measurement; node
``b`` receives a random schedule of those messages with duplicates and reordering.
Each message of ``a`` carries all of ``a``'s information, so after every delivery
``b`` must equal filterpy's ``KalmanFilter`` given exactly the measurements of the
newest message ``b`` has accepted: an older message, or a duplicate, changes nothing.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PositionSensor

from tests.helpers.fusion_harness import P0, Q_PSD, central_kalman

DT = 0.1
STEPS = 20
STD = 0.5


def _pair(window: int = 60) -> tuple[FusionNode, FusionNode]:
    motion = ConstantVelocity(dim=2, q=Q_PSD)
    prior = (0.0, np.zeros(4), P0 * np.eye(4))
    a = FusionNode("a", ["b"], motion, window=window, prior=prior, epoch=1)
    b = FusionNode("b", ["a"], motion, window=window, prior=prior, epoch=2)
    for k in range(1, STEPS + 1):
        a.predict(round(k * DT, 9))
        b.predict(round(k * DT, 9))
    return a, b


def _close(b: FusionNode, measurements: list) -> None:
    mean, cov = b.estimate()
    ref_mean, ref_cov = central_kalman(measurements, STEPS * DT)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov, ref_cov, rtol=1e-9, atol=1e-11)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_meas=st.integers(1, 12), n_deliveries=st.integers(1, 30))
def test_every_delivery_equals_the_newest_accepted_message(seed: int, n_meas: int, n_deliveries: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = _pair()
    sensor = PositionSensor(dim=2, std=STD)
    # random order (late measurements) and repeated times (a block then changes between messages)
    times = rng.choice(np.arange(1, STEPS + 1), size=n_meas, replace=True)
    messages, contents, done = [], [], []
    for k in times:
        t = round(float(k) * DT, 9)
        z = rng.normal(size=2)
        a.update(t, z, sensor)
        done.append((t, z, STD))
        messages.append(a.message_to("b"))
        contents.append(list(done))
    newest = -1
    _close(b, [])
    for _ in range(n_deliveries):
        i = int(rng.integers(len(messages)))        # any message, any number of times
        b.receive(messages[i])
        newest = max(newest, i)
        _close(b, contents[newest])


def test_older_message_after_a_newer_one_changes_nothing() -> None:
    """The plainest case, bit for bit: m2 then m1 leaves b exactly as m2 alone."""
    a, b = _pair()
    sensor = PositionSensor(dim=2, std=STD)
    a.update(1.0, [0.3, -0.2], sensor)
    m1 = a.message_to("b")
    a.update(0.5, [0.1, 0.4], sensor)      # late: changes an older block too
    a.update(1.0, [0.2, -0.1], sensor)     # and the block m1 already carried
    m2 = a.message_to("b")
    assert b.receive(m2) > 0
    mean2, cov2 = b.estimate()
    assert b.receive(m1) == 0 and b.receive(m2) == 0     # stale, then duplicate
    mean, cov = b.estimate()
    np.testing.assert_array_equal(mean, mean2)
    np.testing.assert_array_equal(cov, cov2)
    assert b.stats.duplicates == 1
    _close(b, [(1.0, [0.3, -0.2], STD), (0.5, [0.1, 0.4], STD), (1.0, [0.2, -0.1], STD)])


def test_crossing_messages_count_each_measurement_once() -> None:
    """a and b measure, then their messages cross; both equal the union."""
    a, b = _pair()
    sensor = PositionSensor(dim=2, std=STD)
    ma = [(0.4, [0.1, 0.2], STD), (1.2, [0.5, 0.1], STD)]
    mb = [(0.4, [0.0, 0.3], STD), (2.0, [1.0, 0.2], STD)]
    for t, z, _ in ma:
        a.update(t, z, sensor)
    for t, z, _ in mb:
        b.update(t, z, sensor)
    to_b, to_a = a.message_to("b"), b.message_to("a")
    b.receive(to_b)
    a.receive(to_a)
    # a second exchange (each now holds the other's information) must change nothing
    b.receive(a.message_to("b"))
    a.receive(b.message_to("a"))
    for node in (a, b):
        _close(node, ma + mb)


@pytest.mark.parametrize("lost", [[0], [1], [0, 1]])
def test_a_lost_message_is_recovered_by_the_next(lost: list[int]) -> None:
    a, b = _pair()
    sensor = PositionSensor(dim=2, std=STD)
    done, msgs = [], []
    for k, t in enumerate((0.3, 0.9, 1.5)):
        z = [0.1 * k, -0.2 * k]
        a.update(t, z, sensor)
        done.append((t, z, STD))
        msgs.append(a.message_to("b"))
    for i, m in enumerate(msgs):
        if i not in lost:
            b.receive(m)
    _close(b, done)


def _lagging_link(window: int, steps: int, lag: int, lost: set[int], first: int = 1):
    """``a`` measures at ``(first + k) DT`` and sends after each measurement; ``b`` fuses each
    message ``lag`` messages after it was sent (a queue; the messages of ``lost`` are lost)
    and answers at once; ``a`` fuses the answers. Both have predicted to the last time.
    Returns ``a, b``, the measurements, the number of blocks of every message sent after the
    first answer, and ``a``'s channel after the last step (before draining the queue)."""
    from collections import deque

    from dfusion.wire import decode

    motion = ConstantVelocity(dim=2, q=Q_PSD)
    prior = (0.0, np.zeros(4), P0 * np.eye(4))
    a = FusionNode("a", ["b"], motion, window=window, prior=prior, epoch=1)
    b = FusionNode("b", ["a"], motion, window=window, prior=prior, epoch=2)
    sensor = PositionSensor(dim=2, std=STD)
    done, queue, blocks = [], deque(), []
    for k in range(steps):
        t = round((first + k) * DT, 9)
        for node in (a, b):
            node.predict(t)
        z = [0.1 * k, 0.05 * k * k]
        a.update(t, z, sensor)
        done.append((t, z, STD))
        answered = a.channels["b"].acked >= 0   # (before any acknowledgement: everything so far)
        data = a.message_to("b")
        if answered:
            blocks.append(decode(data).times.size)
        if k not in lost:
            queue.append(data)
        while len(queue) > lag:
            b.receive(queue.popleft())
            a.receive(b.message_to("a"))
    lagging = (a.channels["b"].lag(), a.channels["b"].stalled())
    while queue:
        b.receive(queue.popleft())
        a.receive(b.message_to("a"))
    b.receive(a.message_to("b"))   # the times the last acknowledgements showed lost
    a.receive(b.message_to("a"))
    return a, b, done, blocks, lagging


@pytest.mark.parametrize("lost", [None, 6, 9])
def test_a_busy_recipient_is_sent_what_changed_and_a_lost_message_is_still_recovered(lost) -> None:
    """The resend backoff (docs/fusion.md): ``b`` answers every message of ``a``, but 4 messages
    late (a queue: the acknowledgements lag more than ACK_LAG behind, and keep advancing). ``a``
    then sends what changed only (one block: its new measurement), not everything since the
    newest acknowledged message, except the one time of a lost message, sent again once an
    acknowledgement shows it lost. After the queue is drained ``b`` equals filterpy's
    KalmanFilter on all of ``a``'s measurements. When ``b`` then falls silent (an outage) for
    more than ACK_LAG + 1 messages, ``a``'s messages carry everything since the newest
    acknowledged one again (the catch-up)."""
    from dfusion.fusion.channel import ACK_LAG
    from dfusion.wire import decode

    lag = ACK_LAG + 2
    a, b, done, blocks, (behind, stalled) = _lagging_link(60, STEPS, lag, {lost}, first=10)
    assert behind > ACK_LAG and not stalled   # behind, but not stalled
    # one block per message (two once: the lost message's time again), never a catch-up
    assert len(blocks) >= STEPS - lag - 1
    assert blocks.count(1) >= len(blocks) - (0 if lost is None else 1)
    assert max(blocks) == (1 if lost is None else 2)
    t_end = a.latest_time
    for node in (a, b):
        mean, cov = node.estimate()
        ref_mean, ref_cov = central_kalman(done, t_end)
        np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(cov, ref_cov, rtol=1e-9, atol=1e-11)
    # an outage: b answers nothing while a fuses late measurements (one per message); after
    # ACK_LAG + 1 messages every message catches up: everything since the newest acknowledged one
    sizes = []
    for j in range(ACK_LAG + 4):
        a.update(round((j + 10.5) * DT, 9), [0.0, 0.1 * j], PositionSensor(dim=2, std=STD))
        sizes.append(decode(a.message_to("b")).times.size)
    assert sizes == [1] * (ACK_LAG + 1) + list(range(ACK_LAG + 2, ACK_LAG + 5))


@pytest.mark.parametrize("lost", [{3}, {5}, {7}, {4, 5}, {6, 9, 12}])
def test_a_lost_message_near_the_window_edge_is_recovered_on_a_busy_link(lost) -> None:
    """A short window (8 states) and acknowledgements 4 messages late: a loss shows in an
    acknowledgement only when its time is about to leave the window, too late for a resend
    to arrive. The unacknowledged times among the oldest ``lag + 1`` window states are then
    carried in every message (ChannelFilter.pending_keys), so ``b`` still ends on ``a``'s
    estimate (everything ``a`` measured that is still in the window): against filterpy's
    KalmanFilter on the measurements of the states ``b`` still holds, plus the base
    ``a`` marginalized into (both have the same window)."""
    from dfusion.fusion.channel import ACK_LAG

    a, b, _, _, (behind, stalled) = _lagging_link(8, 16, ACK_LAG + 2, lost)
    assert behind > ACK_LAG and not stalled
    for x, y in zip(a.estimate(), b.estimate()):
        np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-9)
