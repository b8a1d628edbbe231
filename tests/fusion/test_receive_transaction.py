"""FusionNode.receive is transactional: a failure at any stage leaves the node exactly as it was.

A message is decoded, checked, planned and then applied to the filter, the channel
filter, the stores and the other channels' dirty sets, with the acknowledgement it
carries and the pruning that an inserted state may cause. Every function on that
path is made to fail here, before it runs and after it has made its changes; each
time the node must be unchanged (the same :func:`state_digest`, estimate and dense
information) and the failure must come out as a counted :class:`MessageError`.
Afterwards the same message, delivered without the failure, must give exactly what
it gives a node that never saw the failure (nothing half-done was left behind).
"""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from dfusion.errors import MessageError, NotPositiveDefiniteError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.fusion import ChannelFilter, FusionNode
from dfusion.fusion import node as node_module
from dfusion.models import PositionSensor
from dfusion import wire

from tests.helpers.fusion_harness import build_chain, make_node, state_digest

# b holds exactly WINDOW states after build_chain: a's message adds the state 0.33, so
# receiving it marginalizes b's oldest state and prunes its stores and channels
WINDOW = 11


def scenarios() -> dict[str, tuple[FusionNode, bytes]]:
    """Node ``b`` (pickled) and a message for it, one per kind of change."""
    a, b, c, fresh, _ = build_chain(window=WINDOW)
    out = {"fresh": (b, fresh)}
    # a duplicate of a message b already applied (counted in stats.duplicates)
    dup = pickle.loads(pickle.dumps(b))
    dup.receive(fresh)
    out["duplicate"] = (dup, fresh)
    # a new incarnation of a (the next message to it must be full)
    a2 = make_node("a", ["b"], epoch=a.epoch + 1, window=WINDOW)
    a2.predict(0.5)
    a2.update(0.5, [5.0, 0.1], PositionSensor(2, 0.5))
    out["restart"] = (b, a2.message_to("b"))
    # a message with a block far in the future (held back beyond max_ahead: not applied)
    far = pickle.loads(pickle.dumps(a))
    far.predict(30.0)
    far.update(30.0, [1.0, 2.0], PositionSensor(2, 0.5))
    out["too-far"] = (b, far.message_to("b"))
    return {k: (pickle.dumps(node), data) for k, (node, data) in out.items()}


SCENARIOS = scenarios()


def fresh(name: str) -> tuple[FusionNode, bytes]:
    blob, data = SCENARIOS[name]
    return pickle.loads(blob), data


class Injected(RuntimeError):
    """The failure injected into the apply path."""


def observable(node: FusionNode) -> tuple:
    """Digest, estimate and dense information (the latter two computed by the filter)."""
    mean, cov = node.estimate()
    omega, eta = node.filter.dense_information()
    return state_digest(node), mean, cov, omega, eta


def assert_same(x: tuple, y: tuple) -> None:
    assert x[0] == y[0], "the node's state changed"
    for u, v in zip(x[1:], y[1:]):
        assert np.array_equal(u, v)


class RaisingSet(set):
    """A dirty set whose ``update`` fails (the marking of the other links)."""

    def __init__(self, items, after: bool, exc: BaseException, calls: list) -> None:
        super().__init__(items)
        self.after, self.exc, self.calls = after, exc, calls

    def update(self, *others) -> None:
        self.calls.append("dirty.update")
        if self.after:
            super().update(*others)
        raise self.exc


# the functions on the receive path: (owner, attribute)
STAGES = {
    "decode": (node_module, "decode"),
    "psd-check": (wire, "_not_psd"),
    "check": (FusionNode, "_check"),
    "plan": (ChannelFilter, "plan"),
    "within-reach": (FusionNode, "_within_reach"),
    "without-far-blocks": (node_module, "_without"),
    "filter-add": (DelayedStateEIF, "add_information_batch"),
    "filter-estimate": (DelayedStateEIF, "estimate"),
    "channel-commit": (ChannelFilter, "commit"),
    "note-applied": (ChannelFilter, "note_applied"),
    "remote-restarted": (ChannelFilter, "remote_restarted"),
    "store-add-many": (node_module._Blocks, "add_many"),
    "store-add": (node_module._Blocks, "add"),
    "dirty-marking": None,   # a RaisingSet as the other channel's dirty set
    "acknowledged": (ChannelFilter, "acknowledged"),
    "prune": (FusionNode, "_prune"),
    "channel-prune": (ChannelFilter, "prune"),
    "store-prune": (node_module._Blocks, "prune"),
}


def inject(monkeypatch, node: FusionNode, stage: str, after: bool, exc: BaseException) -> list:
    """Make ``stage`` raise ``exc`` (after doing its work when ``after``); returns the list
    of calls that raised (empty: the stage was not reached)."""
    calls: list = []
    if stage == "dirty-marking":
        other = node.channels["c"]
        other.dirty = RaisingSet(other.dirty, after, exc, calls)
        return calls
    owner, name = STAGES[stage]
    original = getattr(owner, name)

    def failing(*args, **kwargs):
        calls.append(name)
        if after:
            original(*args, **kwargs)
        raise exc

    monkeypatch.setattr(owner, name, failing)
    return calls


def reference(name: str) -> tuple:
    """What the scenario's message does to a node that never saw a failure."""
    node, data = fresh(name)
    node.receive(data)
    return observable(node)


REFERENCE = {name: reference(name) for name in SCENARIOS}


def test_the_scenarios_change_the_node_and_reach_every_stage():
    """The fixture is not vacuous: each clean delivery changes the node, the fresh message
    marginalizes b's oldest state (so prune has work to do), the restart is recognized,
    the far block is held back and the duplicate is counted."""
    for name in SCENARIOS:
        node, data = fresh(name)
        assert observable(node)[0] != REFERENCE[name][0], name
    node, data = fresh("fresh")
    before = node.filter.marginalized
    node.receive(data)
    assert node.filter.marginalized == before + 1
    assert node.channels["c"].dirty
    node, data = fresh("restart")
    node.receive(data)
    assert node.channels["a"].next_is_full()
    node, data = fresh("too-far")
    node.receive(data)
    assert node.stats.blocks_too_far_ahead == 1
    node, data = fresh("duplicate")
    dup = node.stats.duplicates
    node.receive(data)
    assert node.stats.duplicates == dup + 1


@pytest.mark.parametrize("after", [False, True], ids=["before", "after"])
@pytest.mark.parametrize("stage", list(STAGES))
def test_a_failure_at_any_stage_changes_nothing_and_is_counted(monkeypatch, stage, after):
    reached = []
    for name in SCENARIOS:
        node, data = fresh(name)
        before = observable(node)
        rejected = node.stats.messages_rejected
        with monkeypatch.context() as m:
            calls = inject(m, node, stage, after, Injected(f"injected at {stage}"))
            try:
                node.receive(data)
                error = None
            except MessageError as exc:
                error = exc
        if not calls:      # this message does not go through this stage
            assert error is None
            continue
        reached.append(name)
        assert error is not None, f"the failure at {stage} was swallowed ({name})"
        assert error.reason in ("internal", "numerical"), error.reason
        assert "injected" in str(error)
        assert node.stats.messages_rejected == rejected + 1
        assert node.stats.rejections.get(error.reason) == 1
        assert_same(observable(node), before)
        # nothing half-done is left: the same message now does what it does to a clean node
        node.receive(data)
        assert_same(observable(node), REFERENCE[name])
    assert reached, f"no scenario reaches {stage}"


@pytest.mark.parametrize("stage", ["filter-add", "filter-estimate"])
def test_a_numerical_failure_of_the_filter_is_a_numerical_rejection(monkeypatch, stage):
    node, data = fresh("fresh")
    before = observable(node)
    with monkeypatch.context() as m:
        inject(m, node, stage, True, NotPositiveDefiniteError("not positive definite"))
        with pytest.raises(MessageError) as info:
            node.receive(data)
    assert info.value.reason == "numerical"
    assert node.stats.rejections == {"numerical": 1}
    assert_same(observable(node), before)


@pytest.mark.parametrize("stage", ["filter-add", "channel-commit", "store-add-many", "acknowledged", "prune"])
def test_an_interrupt_is_undone_and_propagates_uncounted(monkeypatch, stage):
    """KeyboardInterrupt is not a rejected message: it propagates, after the undo."""
    node, data = fresh("fresh")
    before = observable(node)
    with monkeypatch.context() as m:
        inject(m, node, stage, True, KeyboardInterrupt())
        with pytest.raises(KeyboardInterrupt):
            node.receive(data)
    assert node.stats.messages_rejected == 0 and node.stats.rejections == {}
    assert_same(observable(node), before)


def test_a_message_that_would_make_the_filter_improper_is_rejected_as_numerical():
    """Naive fusion skips the positive semi-definiteness test (its blocks are increments):
    a negative increment larger than the prior makes the belief improper, and the filter's
    own check rejects it, leaving the node as it was."""
    def naive(name, nbrs, epoch):
        return make_node(name, nbrs, epoch=epoch, fusion="naive")
    a, b = naive("a", ["b"], 1), naive("b", ["a"], 2)
    for node in (a, b):
        node.predict(0.1)
    msg = wire.decode(a.message_to("b"))
    bad = wire.InfoMessage("a", "b", 1, 1, msg.start, 0.1, np.array([0.1]), -100 * np.eye(4)[None],
                           np.zeros((1, 4)), 2, -1, 0, np.zeros(0), False, True)
    before = observable(b)
    with pytest.raises(MessageError) as info:
        b.receive(wire.encode(bad))
    assert info.value.reason == "numerical"
    assert_same(observable(b), before)
