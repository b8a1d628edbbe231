"""One undo for a received message on both paths (``FusionNode._mark_stores`` /
``_rollback_stores``): a failure at any stage of the general path (``_apply``) or of the
deferred bookkeeping of the critical path (``_settle_receive``), with the consistency guard
on, leaves **every attribute** of the node bit for bit as it was
(:func:`tests.helpers.fusion_harness.full_digest` walks ``vars(node)``: a store added to the
node later is compared too, or the digest fails on its type), and the same message delivered
again then gives exactly what it gives a node that never saw the failure. Also the message
that completes a quarantine (the withdrawal of everything that came over the link)."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from dfusion.errors import MessageError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.fusion import ChannelFilter, FusionNode, GuardConfig, NeighbourGuard
from dfusion.fusion import node as node_module
from dfusion.models import ConstantVelocity, PositionSensor
from tests.helpers.fusion_harness import P0, Q_PSD, CVTruth, full_digest

WINDOW = 10
SENSOR = PositionSensor(2, 0.5)


class Injected(RuntimeError):
    pass


def guarded_chain(hostile: bool = False, config: GuardConfig | None = None):
    """a - b - c with guards, window 10, after 25 lossless steps (steady state: every message
    partial and acknowledged); then a's next message for b. With ``hostile`` a's measurement
    of that step is 40 m off with a claimed noise of 0.05 m."""
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    cfg = config or GuardConfig()
    nbrs = {"a": ["b"], "b": ["a", "c"], "c": ["b"]}
    nodes = {n: FusionNode(n, nbrs[n], motion, window=WINDOW, prior=prior, epoch=i + 1, guard=cfg)
             for i, n in enumerate("abc")}
    rng = np.random.default_rng(11)
    truth = CVTruth(rng)
    for k in range(1, 27):
        t = round(0.1 * k, 9)
        x = truth.at(t)
        for node in nodes.values():
            node.predict(t)
        for node in nodes.values():
            z = x[:2] + 0.5 * rng.standard_normal(2)
            if hostile and k == 26 and node.name == "a":
                node.update(t, z + [40.0, 0.0], PositionSensor(2, 0.05))
            else:
                node.update(t, z, SENSOR)
        if k == 26:
            break
        msgs = [(j, nodes[n].message_to(j)) for n in "abc" for j in nbrs[n]]
        for j, data in msgs:
            nodes[j].receive(data)
    data = nodes["a"].message_to("b")
    b = nodes["b"]
    b.settle()
    return b, data


def inject(m, owner, name: str, exc: BaseException, calls: list) -> None:
    original = getattr(owner, name)

    def failing(*args, **kwargs):
        calls.append(name)
        original(*args, **kwargs)   # its changes are made, then it fails
        raise exc

    m.setattr(owner, name, failing)


def observable(node: FusionNode) -> tuple:
    return (full_digest(node), *[x.tobytes() for x in node.estimate()])


# the stages of a message's application after the filter took it, each failing after its work
BOOKKEEPING = [(ChannelFilter, "commit"), (node_module._Blocks, "add_many"), (FusionNode, "_mark_dirty"),
               (ChannelFilter, "acknowledged"), (FusionNode, "_prune")]
GENERAL = BOOKKEEPING + [(DelayedStateEIF, "add_information_moments"), (DelayedStateEIF, "estimate"),
                         (NeighbourGuard, "judge")]


def check_undone(b: FusionNode, data: bytes, before: tuple, reference: FusionNode, counted: bool) -> None:
    assert b.stats.messages_rejected == int(counted)
    assert b.stats.rejections == ({"internal": 1} if counted else {})
    assert observable(b) == before
    # nothing half-done is left: the message now does what it does to the node that never failed
    b.receive(data)
    reference.receive(data)
    b.settle()
    reference.settle()
    assert observable(b)[1:] == observable(reference)[1:]
    b.stats.messages_rejected, b.stats.rejections = 0, {}
    assert full_digest(b) == full_digest(reference)


def check_failing_receive_is_undone(monkeypatch, b, data, owner, stage, exc) -> None:
    """``b.receive(data)`` with ``exc`` raised at ``stage``: rejected (or the interrupt passed
    on), nothing left for settle(), every attribute as before."""
    reference = pickle.loads(pickle.dumps(b))
    before = observable(b)
    calls: list = []
    with monkeypatch.context() as m:
        inject(m, owner, stage, exc, calls)
        with pytest.raises(MessageError if isinstance(exc, Exception) else KeyboardInterrupt):
            b.receive(data)
    assert calls[:1] == [stage]
    assert b._pending is None
    check_undone(b, data, before, reference, isinstance(exc, Exception))


@pytest.mark.parametrize("owner, stage", GENERAL, ids=[s for _, s in GENERAL])
@pytest.mark.parametrize("exc", [Injected("injected"), KeyboardInterrupt()], ids=["error", "interrupt"])
def test_a_failure_on_the_general_path_restores_every_attribute(monkeypatch, owner, stage, exc):
    b, data = guarded_chain()
    b.critical_path_first = False
    check_failing_receive_is_undone(monkeypatch, b, data, owner, stage, exc)


# the deferred consistency test of a steady-state message (its verdict cannot change the belief)
DEFERRED_TEST = BOOKKEEPING + [(FusionNode, "_deferred_test"), (NeighbourGuard, "judge")]


@pytest.mark.parametrize("owner, stage", DEFERRED_TEST, ids=[s for _, s in DEFERRED_TEST])
@pytest.mark.parametrize("exc", [Injected("injected"), KeyboardInterrupt()], ids=["error", "interrupt"])
def test_a_failure_of_the_deferred_bookkeeping_restores_every_attribute(monkeypatch, owner, stage, exc):
    b, data = guarded_chain()
    reference = pickle.loads(pickle.dumps(b))
    before = observable(b)
    tests = b.guard.links["a"].tests
    assert b.receive(data) == 1
    assert b._pending is not None                # the critical path, with the guard on
    assert b._pending[-1] is not None            # the test left for settle(): no verdict could quarantine a
    assert b._guard.links["a"].tests == tests    # (not recorded yet; reading b.guard would settle)
    calls: list = []
    with monkeypatch.context() as m:
        inject(m, owner, stage, exc, calls)
        if isinstance(exc, Exception):
            b.settle()
        else:
            with pytest.raises(KeyboardInterrupt):
                b.settle()
    assert calls[:1] == [stage]
    check_undone(b, data, before, reference, isinstance(exc, Exception))


@pytest.mark.parametrize("owner, stage", [(NeighbourGuard, "would_quarantine"), (NeighbourGuard, "state"),
                                          (NeighbourGuard, "judge"), (FusionNode, "_add_tested")],
                         ids=["would_quarantine", "state", "judge", "add_tested"])
@pytest.mark.parametrize("exc", [Injected("injected"), KeyboardInterrupt()], ids=["error", "interrupt"])
def test_a_failure_of_the_guard_on_the_critical_path_restores_every_attribute(monkeypatch, owner, stage, exc):
    """When a failing verdict would complete a quarantine (here k = 1: any failure does) the test
    and the verdict run at once on the critical path: a failure there undoes the filter's part
    and the link's record before anything is left for settle()."""
    b, data = guarded_chain(config=GuardConfig(failures=1, window=10))
    assert b.guard.may_quarantine("a") and not b.is_quarantined("a")
    check_failing_receive_is_undone(monkeypatch, b, data, owner, stage, exc)


@pytest.mark.parametrize("owner, stage", [(FusionNode, "_withdraw"), (node_module._Blocks, "subtract"),
                                          (FusionNode, "_mark_dirty")], ids=["withdraw", "subtract", "mark_dirty"])
def test_a_failure_while_quarantining_restores_every_attribute(monkeypatch, owner, stage):
    """k = m = 1: a's hostile steady-state message quarantines it; it falls back from the critical
    path to the general one, whose failure (during the withdrawal) undoes everything."""
    b, data = guarded_chain(hostile=True, config=GuardConfig(failures=1, window=1))
    reference = pickle.loads(pickle.dumps(b))
    before = observable(b)
    calls: list = []
    with monkeypatch.context() as m:
        inject(m, owner, stage, Injected("injected"), calls)
        with pytest.raises(MessageError):
            b.receive(data)
    assert calls[:1] == [stage]
    check_undone(b, data, before, reference, True)
    assert b.guard.quarantined == {"a"}


def test_every_attribute_is_compared():
    """The digest is not blind: a message that b fuses changes it, and so does a change of any
    single store."""
    b, data = guarded_chain()
    before = full_digest(b)
    for change in (lambda n: n._held.add(n.latest_time, np.eye(4), np.ones(4)),
                   lambda n: n._tree_held.update({1: (0.0, np.eye(4), np.ones(4), 1.0)}),
                   lambda n: setattr(n, "_pruned_at", n._pruned_at - 1.0),
                   lambda n: n.guard.links["c"].recent.append(True),
                   lambda n: n.channels["c"].dirty.add(123),
                   lambda n: n._heard.update({"c": -1.0})):
        other = pickle.loads(pickle.dumps(b))
        change(other)
        assert full_digest(other) != before
    b.receive(data)
    b.settle()
    assert full_digest(b) != before
