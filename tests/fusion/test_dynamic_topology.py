"""Fusion over links that change (FusionNode(tree=...)): never over-confident at any step, and
exact once the last change has settled, against filterpy's Kalman filter on every measurement
of the nodes still present (linear models, a window longer than the run)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import MessageError, ValidationError
from dfusion.fusion import FusionNode
from dfusion.fusion.tree import SpanningTree, TreeEpoch, forest_settled, initial_parents
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.wire import decode, encode
from tests.helpers.dynamic_harness import (PRIOR, DynamicSchedule, assert_exact, build_node, rel, run_dynamic,
                                           settle)
from tests.helpers.fusion_harness import Q_PSD, central_kalman


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(2, 8),
    link_prob=st.floats(0.2, 0.9),
    change_prob=st.floats(0.1, 0.8),
    joiners=st.integers(0, 2),
    leavers=st.integers(0, 2),
    drop=st.floats(0.0, 0.4),
    duplicate=st.floats(0.0, 0.3),
    max_latency=st.floats(0.0, 0.5),
)
def test_property_never_over_confident_and_exact_after_the_last_change(seed, n, link_prob, change_prob, joiners,
                                                                      leavers, drop, duplicate, max_latency):
    joiners = min(joiners, n - 1)
    leavers = min(leavers, n - 1 - joiners)
    s = DynamicSchedule(seed=seed, n=n, steps=30, link_prob=link_prob, change_prob=change_prob, joiners=joiners,
                        leavers=leavers, drop=drop, duplicate=duplicate, max_latency=max_latency)
    run = run_dynamic(s)
    # every node at every step: P_node - P_central >= 0, checked with eigenvalues, tolerance relative
    assert run.worst_overconfidence >= -1e-9, run.worst_overconfidence
    # and per state time: the node's single-state information <= that of every measurement taken then
    assert run.worst_block >= -1e-10, run.worst_block
    assert_exact(run)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 7),
    change_prob=st.floats(0.1, 0.8),
    drop=st.floats(0.0, 0.4),
    duplicate=st.floats(0.0, 0.3),
    max_latency=st.floats(0.0, 0.5),
    send_every=st.integers(1, 5),
    min_interval=st.sampled_from([0.0, 0.1, 0.2, 0.35]),
)
def test_property_event_sends_never_over_confident_and_exact_after_the_last_change(
        seed, n, change_prob, drop, duplicate, max_latency, send_every, min_interval):
    """The same properties with event-triggered sends (dfusion.fusion.sending.SendSchedule): news
    at once, rate-limited per link, the heartbeat every ``send_every`` steps."""
    s = DynamicSchedule(seed=seed, n=n, steps=30, change_prob=change_prob, joiners=1, leavers=1, drop=drop,
                        duplicate=duplicate, max_latency=max_latency, send_every=send_every, sends="event",
                        min_interval=min_interval)
    run = run_dynamic(s)
    assert run.worst_overconfidence >= -1e-9, run.worst_overconfidence
    assert run.worst_block >= -1e-10, run.worst_block
    assert_exact(run)


@pytest.mark.parametrize("seed", range(4))
def test_many_changes_over_a_radio_graph_with_cycles(seed):
    """Eight nodes, dense radio graphs (cycles everywhere), a change at most steps, two joins and
    two leaves: the rule re-forms the tree again and again, nothing is ever double counted."""
    s = DynamicSchedule(seed=seed, n=8, steps=60, link_prob=0.6, change_prob=0.7, joiners=2, leavers=2,
                        drop=0.3, duplicate=0.2)
    run = run_dynamic(s)
    assert run.link_changes >= 30 and run.epochs >= 10
    assert run.worst_overconfidence >= -1e-9 and run.worst_block >= -1e-10
    assert_exact(run)


def chain(names, links, window=5000):
    start = initial_parents(names, links)
    return {n: build_node(n, set(links), start, i + 1, window) for i, n in enumerate(names)}


def rounds(nodes, k=1):
    for _ in range(k):
        out = [(j, d) for n in sorted(nodes) for j, d in nodes[n].outgoing()]
        for j, d in out:
            nodes[j].receive(d)


def measure(nodes, t, rng, sensor, record):
    for name, node in sorted(nodes.items()):
        z = rng.normal(size=2)
        node.update(t, z, sensor)
        record.append((t, z, sensor_std(sensor), name))


def sensor_std(sensor) -> float:
    return float(np.sqrt(sensor.R[0, 0]))


def assert_equal_to_kalman(nodes, record, t, keep=None):
    """Every node equals the Kalman filter on the measurements of ``keep`` (default: all) at ``t``."""
    mean, cov = central_kalman([(tt, z, s) for tt, z, s, n in record if keep is None or n in keep], t)
    for node in nodes.values():
        m, P = node.estimate()
        assert rel(m, mean) < 1e-9 and rel(P, cov) < 1e-9, (node.name, rel(m, mean), rel(P, cov))


def after_hold(nodes, links, t):
    """Past the time a node holds information a change took (FusionNode.hold), settled again."""
    t = round(t + max(x.hold for x in nodes.values()) + 0.1, 9)
    for x in nodes.values():
        x.predict(t)
    settle(nodes, links)
    return t


def run_steps(nodes, ks, seed, std=0.6, record=None, every=1):
    """Steps ``k`` of 0.1 s: predict, one measurement per node, a round every ``every`` steps."""
    rng = np.random.default_rng(seed)
    sensor = PositionSensor(2, std)
    record = [] if record is None else record
    for k in ks:
        t = round(0.1 * k, 9)
        for node in nodes.values():
            node.predict(t)
        measure(nodes, t, rng, sensor, record)
        if k % every == 0:
            rounds(nodes)
    return record


def test_a_configured_start_fuses_from_the_first_message_like_a_fixed_tree():
    """On a tree that never changes, nodes with the tree rule and a configured start send exactly
    the messages of fixed-tree nodes (plus the tree fields) and end with identical estimates."""
    links = [("a", "b"), ("b", "c"), ("b", "d")]
    motion = ConstantVelocity(2, Q_PSD)
    fixed = {n: FusionNode(n, sorted({x for l in links if n in l for x in l} - {n}), motion, window=50, prior=PRIOR,
                           epoch=i + 1) for i, n in enumerate("abcd")}
    ruled = chain(list("abcd"), links, window=50)
    sensor = PositionSensor(2, 0.7)
    for nodes in (fixed, ruled):
        rng = np.random.default_rng(5)
        for k in range(1, 40):
            t = round(0.1 * k, 9)
            for node in nodes.values():
                node.predict(t)
            measure(nodes, t, rng, sensor, [])
            if k % 3 == 0:
                rounds(nodes)
    for n in "abcd":
        assert ruled[n].stats.not_fused == 0 and ruled[n].stats.new_epochs == 0
        for x, y in zip(fixed[n].estimate(), ruled[n].estimate()):
            assert np.array_equal(x, y)
        assert fixed[n].stats.messages_sent == ruled[n].stats.messages_sent


def test_a_joining_node_gets_what_the_windows_hold_without_making_the_network_re_form():
    links = [("a", "b"), ("b", "c")]
    nodes = chain(["a", "b", "c"], links)
    record = run_steps(nodes, range(1, 21), seed=2)
    epochs = {n: x.tree.epoch for n, x in nodes.items()}
    # "a0" sorts before every name: with the same term it would win; it joins with term 0
    new = build_node("a0", set(), None, 99, 5000)
    new.predict(2.0)
    nodes["a0"] = new
    for x, y in (("a0", "c"),):
        nodes[x].link_up(y)
        nodes[y].link_up(x)
    links.append(("a0", "c"))
    settle(nodes, {tuple(sorted(l)) for l in links})
    assert all(nodes[n].tree.epoch == epochs[n] for n in "abc")     # the network kept its epoch
    assert all(nodes[n].stats.new_epochs == 0 for n in "abc")
    assert new.tree.parent == "c" and new.stats.new_epochs == 1
    assert_equal_to_kalman(nodes, record, 2.0)     # nothing was taken from anyone: nothing is held


def test_a_leaving_node_is_withdrawn_and_a_restarted_one_starts_again():
    links = {("a", "b"), ("b", "c"), ("c", "d")}
    nodes = chain(list("abcd"), links)
    record = run_steps(nodes, range(1, 11), seed=4)
    # d leaves for good: a link break at c, its only neighbour
    nodes["c"].link_down("d")
    links.discard(("c", "d"))
    cov_c = nodes["c"].estimate()[1]
    left = nodes.pop("d")
    assert left.tree.parent == "c"          # d was a leaf: c withdraws what it sent, no new epoch
    assert nodes["c"].stats.new_epochs == 0 and nodes["c"].stats.withdrawn_blocks > 0
    settle(nodes, links)
    # c's own estimate still holds what d measured (for FusionNode.hold seconds); a and b no longer
    np.testing.assert_allclose(nodes["c"].estimate()[1], cov_c, rtol=1e-12)
    assert_equal_to_kalman({"a": nodes["a"], "b": nodes["b"]}, record, 1.0, keep="abc")
    t = after_hold(nodes, links, 1.0)
    assert_equal_to_kalman(nodes, record, t, keep="abc")
    # b restarts: a new incarnation with nothing of the old one; its neighbours forget the old one
    restarted = build_node("b", {("a", "b"), ("b", "c")}, None, 1000, 5000)
    restarted.predict(t)
    nodes["b"] = restarted
    settle(nodes, links)
    assert nodes["a"].incarnations["b"] == 1000
    t = after_hold(nodes, links, t)
    assert_equal_to_kalman(nodes, record, t, keep="ac")     # what d and the old b measured is gone


def test_a_partition_heals_and_both_halves_keep_their_information():
    links = {("a", "b"), ("b", "c"), ("c", "d"), ("d", "e")}
    nodes = chain(list("abcde"), links)
    record = run_steps(nodes, range(1, 11), seed=9, std=0.8, every=2)
    for x, y in (("b", "c"), ("c", "b")):
        nodes[x].link_down(y)
    links.discard(("b", "c"))
    for k in range(11, 31):
        run_steps(nodes, [k], seed=k, std=0.8, record=record, every=2)
        t = round(0.1 * k, 9)
        # each half holds only its own half's measurements, never more
        for half in ("ab", "cde"):
            _, cov = central_kalman([(tt, z, s) for tt, z, s, n in record], t)
            for name in half:
                _, P = nodes[name].estimate()
                assert np.linalg.eigvalsh(P - cov)[0] >= -1e-9 * np.abs(cov).max()
    # a new link between the halves (not the one that broke)
    for x, y in (("a", "e"), ("e", "a")):
        nodes[x].link_up(y)
    links.add(("a", "e"))
    settle(nodes, links)
    assert_equal_to_kalman(nodes, record, 3.0)     # the healed tree delivers what each node held: nothing held
    assert all(not x._held for x in nodes.values())


@pytest.mark.parametrize("hold", [10.0, 0.0])
def test_a_node_in_a_new_epoch_keeps_what_it_had_until_the_new_tree_delivers(hold):
    """a - b - c - a, b without a sensor: when a - b breaks, b starts a new epoch and its
    channels start afresh. With ``hold`` its estimate keeps what it had (per state time, until the
    new tree delivers as much); with ``hold = 0`` it drops to the prior at once. Either way it is
    never more certain than the Kalman filter on every measurement, and both end exact."""
    links = {("a", "b"), ("b", "c"), ("a", "c")}
    nodes = chain(list("abc"), links)
    for x in nodes.values():
        x.hold = hold
    record = []
    rng = np.random.default_rng(1)
    sensor = PositionSensor(2, 0.5)
    for k in range(1, 21):
        t = round(0.1 * k, 9)
        for x in nodes.values():
            x.predict(t)
        for name in "ac":
            z = rng.normal(size=2)
            nodes[name].update(t, z, sensor)
            record.append((t, z, 0.5, name))
        rounds(nodes)
    assert nodes["b"].tree.parent == "a"
    before = np.trace(nodes["b"].estimate()[1])
    for x, y in (("a", "b"), ("b", "a")):
        nodes[x].link_down(y)
    links.discard(("a", "b"))
    assert nodes["b"].stats.new_epochs == 1
    after = np.trace(nodes["b"].estimate()[1])
    if hold:
        assert after == pytest.approx(before, rel=1e-9)
    else:
        assert after > 100 * before
    _, cov = central_kalman([(t, z, s) for t, z, s, _ in record], 2.0)
    for k in range(4):     # the new epoch floods, full messages replace what b held
        rounds(nodes)
        _, P = nodes["b"].estimate()
        assert np.linalg.eigvalsh(P - cov)[0] >= -1e-9 * np.abs(cov).max()
    assert not nodes["b"]._held
    assert_equal_to_kalman(nodes, record, 2.0)


def test_a_refused_message_changes_nothing_even_after_the_rule_took_it_in():
    """A fusion message from a new child that is then refused (its sequence number jumps too far):
    the child relation the rule took from it is undone with the rest (the node is exactly as before)."""
    e = TreeEpoch(1, "a")
    motion = ConstantVelocity(2, Q_PSD)
    a = FusionNode("a", ["b"], motion, window=50, prior=PRIOR, epoch=1,
                   tree=SpanningTree("a", ["b"], epoch=e, known={"b": (e, None)}))
    b = FusionNode("b", ["a"], motion, window=50, prior=PRIOR, epoch=2,
                   tree=SpanningTree("b", ["a"], epoch=e, parent="a", known={"a": (e, None)}))
    for node in (a, b):
        node.predict(0.1)
    b.update(0.1, [1.0, 2.0], PositionSensor(2, 0.5))
    good = decode(b.message_to("a"))
    assert not good.beacon and len(good) == 1
    bad = encode(dataclasses.replace(good, seq=2_000_000))
    before = (a.tree.snapshot(), dict(a.channels), a.estimate()[1].copy(), dict(a.incarnations))
    with pytest.raises(MessageError):
        a.receive(bad)
    assert a.tree.children() == set() and a.channels.keys() == before[1].keys()
    assert a.incarnations == before[3]
    assert np.array_equal(a.estimate()[1], before[2])
    assert a.stats.messages_rejected == 1 and a.stats.rejections == {"sequence-jump": 1}
    assert a.stats.tree_changes == 0
    assert a.receive(encode(good)) == 1 and a.tree.children() == {"b"}


def test_api_errors():
    motion = ConstantVelocity(2, Q_PSD)
    fixed = FusionNode("a", ["b"], motion, window=10, prior=PRIOR)
    with pytest.raises(ValidationError):
        fixed.link_up("c")
    with pytest.raises(ValidationError):
        FusionNode("a", ["b"], motion, window=10, prior=PRIOR, tree=SpanningTree("a", ["c"]))
    with pytest.raises(ValidationError):
        FusionNode("a", [], motion, window=10, prior=PRIOR, tree=SpanningTree("a"), fusion="naive")
    node = FusionNode("a", [], motion, window=10, prior=PRIOR, tree=SpanningTree("a"), peers=["b"])
    with pytest.raises(ValidationError):
        node.link_up("c")        # not a peer
    node.link_up("b")
    assert node.neighbors == ("b",) and node.tree_links == ()
    msg = decode(node.message_to("b"))
    assert msg.beacon and msg.tree_root == "a" and msg.parent == "" and msg.tree_term == 0
    with pytest.raises(ValidationError):
        node.message_to("c")
    # a fixed-tree node refuses the rule's messages and the other way round
    other = FusionNode("b", ["a"], motion, window=10, prior=PRIOR)
    with pytest.raises(MessageError):
        other.receive(node.message_to("b"))
    assert other.stats.rejections == {"malformed": 1}
    with pytest.raises(MessageError):
        node.receive(other.message_to("a"))
    assert node.stats.rejections == {"malformed": 1}
