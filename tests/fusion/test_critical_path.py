"""The critical path first (issue 15): steady-state messages are fused into the filter at once
and their bookkeeping is settled later (:meth:`FusionNode.settle`); a message's record and
the sender's forward pass too. None of it may change any result.

* over random schedules (losses, duplicates, reordering, crossed messages, one-way outages,
  restarts; :func:`tests.helpers.fusion_harness.run_network`), every node's whole state
  (:func:`state_digest`), its estimate and every message it sends are bit for bit those of
  the same run with every message on the general path (``FusionNode.critical_path_first``
  and ``ChannelFilter.append_plans`` off), step by step;
* a failure of the deferred bookkeeping undoes the whole message when it is settled, the
  filter's part too, and is counted as an internal rejection; an interrupt propagates after
  the undo.
"""
from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.fusion import ChannelFilter, FusionNode
from dfusion.models import ConstantVelocity, PositionSensor
from tests.helpers.fusion_harness import (
    PRIOR,
    Schedule,
    Trace,
    random_tree,
    run_network,
    state_digest,
)


def recorded_run(monkeypatch, graph, s: Schedule, general: bool) -> tuple[list, list]:
    """Run the schedule; returns ``(per-step states, messages sent, rejections)``, on the general path
    with ``general``."""
    steps: list = []
    sent: list = []
    original = FusionNode.message_to

    def message_to(self, neighbor, sent_at=None):
        data = original(self, neighbor, sent_at)
        sent.append((self.name, neighbor, data))
        return data

    def on_step(nodes, measurements, t):
        steps.append({n: (state_digest(node), *[x.tobytes() for x in node.estimate()]) for n, node in nodes.items()})

    with monkeypatch.context() as m:
        m.setattr(FusionNode, "message_to", message_to)
        m.setattr(FusionNode, "critical_path_first", not general)
        m.setattr(ChannelFilter, "append_plans", not general)
        s.on_step = on_step
        trace = Trace()   # (messages of a replaced incarnation are rejected)
        nodes, _, _ = run_network(graph, s, trace=trace)
        on_step(nodes, None, None)   # after the final lossless rounds
    return steps, sent, trace.rejections


@st.composite
def schedules(draw) -> tuple:
    n = draw(st.integers(2, 5))
    seed = draw(st.integers(0, 2**31 - 1))
    steps = 20
    graph = random_tree(n, seed)
    names = sorted(graph.nodes)
    restarts = tuple(sorted(draw(st.lists(st.tuples(st.integers(2, steps), st.sampled_from(names)), max_size=1))))
    return graph, dict(
        seed=seed, steps=steps, drop=draw(st.floats(0.0, 0.4)), max_consecutive_drops=draw(st.integers(1, 3)),
        duplicate=draw(st.floats(0.0, 0.3)), max_latency=draw(st.sampled_from([0.0, 0.1, 0.3])),
        send_every=draw(st.integers(1, 2)), irregular=draw(st.booleans()),
        outage=draw(st.sampled_from([0.0, 0.1])), outage_steps=draw(st.integers(2, 5)), restarts=restarts,
        window=draw(st.sampled_from([5, 12, 50])))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(case=schedules())
def test_the_critical_path_first_changes_no_result(monkeypatch, case):
    graph, kw = case
    fast = recorded_run(monkeypatch, graph, Schedule(**kw), general=False)
    slow = recorded_run(monkeypatch, graph, Schedule(**kw), general=True)
    assert fast[1] == slow[1]   # every message, byte for byte
    assert fast[0] == slow[0]   # every node's state and estimate after every step
    assert fast[2] == slow[2]


def test_the_steady_state_takes_the_critical_path():
    """Not vacuous: in the steady state of a link the receiver leaves work to settle(), the
    channel appends in place, and the sender leaves its record of the message."""
    a, b = steady_pair()
    t = 3.0
    a.predict(t)
    a.update(t, [0.5, -0.2], PositionSensor(2, 0.5))
    data = a.message_to("b")
    assert a._sent_pending and a._warm
    ch = b.channels["a"]
    buf = ch._buf
    b.predict(t)
    assert b.receive(data) == 1
    assert b._pending is not None
    b.settle()
    assert b._pending is None and ch._buf is buf and ch.keys.base is buf[0]


def steady_pair(window: int = 10) -> tuple[FusionNode, FusionNode]:
    motion = ConstantVelocity(2, 0.1)
    a = FusionNode("a", ["b"], motion, window=window, prior=PRIOR, epoch=1)
    b = FusionNode("b", ["a"], motion, window=window, prior=PRIOR, epoch=2)
    sensor = PositionSensor(2, 0.5)
    for k in range(1, 26):
        t = round(0.1 * k, 9)
        a.predict(t)
        b.predict(t)
        a.update(t, [np.sin(t), np.cos(t)], sensor)
        b.receive(a.message_to("b"))
        a.receive(b.message_to("a"))
    return a, b


class Injected(RuntimeError):
    pass


@pytest.mark.parametrize("owner, stage", [(ChannelFilter, "commit"), (ChannelFilter, "acknowledged"),
                                          (FusionNode, "_mark_dirty")])
@pytest.mark.parametrize("exc", [Injected("injected"), KeyboardInterrupt()], ids=["error", "interrupt"])
def test_a_failure_of_the_deferred_bookkeeping_undoes_the_message(monkeypatch, owner, stage, exc):
    a, b = steady_pair()
    t = 2.6
    a.predict(t)
    a.update(t, [0.5, -0.2], PositionSensor(2, 0.5))
    data = a.message_to("b")
    b.predict(t)
    b.settle()
    reference = pickle.loads(pickle.dumps(b))
    before = (state_digest(b), *[x.tobytes() for x in b.estimate()])
    assert b.receive(data) == 1
    assert b.estimate()[0].tobytes() != before[1]   # the filter has the message at once
    calls = []
    original = getattr(owner, stage)

    def failing(self, *args, **kwargs):
        calls.append(stage)
        original(self, *args, **kwargs)
        raise exc

    with monkeypatch.context() as m:
        m.setattr(owner, stage, failing)
        if isinstance(exc, Exception):
            b.settle()
        else:
            with pytest.raises(KeyboardInterrupt):
                b.settle()
    assert calls == [stage]
    counted = isinstance(exc, Exception)   # an interrupt is undone too, but it is no rejected message
    assert b.stats.rejections == ({"internal": 1} if counted else {}) and b.stats.messages_rejected == int(counted)
    b.stats.rejections, b.stats.messages_rejected = {}, 0
    assert (state_digest(b), *[x.tobytes() for x in b.estimate()]) == before
    # nothing half-done is left: the message now does what it does to the node that never failed
    b.receive(data)
    reference.receive(data)
    assert (state_digest(b), *[x.tobytes() for x in b.estimate()]) == \
        (state_digest(reference), *[x.tobytes() for x in reference.estimate()])
