"""The tree rule and the consistency guard together (FusionNode(tree=..., guard=...)): what a
quarantine withdrew is not withdrawn again when the tree drops the link (a link break, a new
epoch), and a quarantine while a change of the tree holds information lets the held times go
first. The reference is filterpy's Kalman filter on the measurements of the honest nodes."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.fusion import FusionNode, GuardConfig
from dfusion.fusion.tree import SpanningTree, initial_parents
from dfusion.models import ConstantVelocity, PositionSensor
from tests.helpers.dynamic_harness import PRIOR, settle
from tests.helpers.fusion_harness import Q_PSD, central_kalman

STD = 0.6
BIAS = 40.0     # the liar's offset (m): every one of its messages fails the test


def rel(a, b) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


def network(names, links, hold=10.0):
    start = initial_parents(names, links)
    nodes = {}
    for i, n in enumerate(names):
        nbrs = sorted({x for l in links if n in l for x in l} - {n})
        tree = SpanningTree(n, nbrs, epoch=start[n][0], parent=start[n][1], known={j: start[j] for j in nbrs})
        nodes[n] = FusionNode(n, nbrs, ConstantVelocity(2, Q_PSD), window=5000, prior=PRIOR, tree=tree,
                              epoch=i + 1, hold=hold, guard=GuardConfig(failures=1, window=1))
    return nodes


def step(nodes, k, rng, record, liars=(), silent=()):
    """One 0.1 s step: predict, a measurement per node (liars add BIAS), one lossless round."""
    t = round(0.1 * k, 9)
    sensor = PositionSensor(2, STD)
    for node in nodes.values():
        node.predict(t)
    for name, node in sorted(nodes.items()):
        if name in silent:
            continue
        z = rng.normal(scale=STD, size=2) + (BIAS if name in liars else 0.0)
        node.update(t, z, sensor)
        record.append((t, z, STD, name))
    out = [(j, d) for n in sorted(nodes) for j, d in nodes[n].outgoing()]
    for j, d in out:
        nodes[j].receive(d)
    return t


def assert_kalman(nodes, record, t, keep):
    mean, cov = central_kalman([(tt, z, s) for tt, z, s, n in record if n in keep], t)
    for name in keep:
        m, P = nodes[name].estimate()
        assert rel(m, mean) < 1e-9 and rel(P, cov) < 1e-9, (name, rel(m, mean), rel(P, cov))


def lied_to(seed):
    """a - b - c, c joins the lies after 15 honest-only steps: b quarantines c."""
    links = {("a", "b"), ("b", "c")}
    nodes = network(["a", "b", "c"], links)
    rng = np.random.default_rng(seed)
    record: list = []
    t = 0.0
    for k in range(1, 16):
        t = step(nodes, k, rng, record, silent=("c",))
    for k in range(16, 26):
        t = step(nodes, k, rng, record, liars=("c",))
    assert nodes["b"].is_quarantined("c") and not nodes["b"].is_quarantined("a")
    return nodes, links, record, t, rng


@pytest.mark.parametrize("seed", range(3))
def test_a_quarantined_link_that_breaks_is_not_withdrawn_twice(seed):
    nodes, links, record, t, _ = lied_to(seed)
    withdrawn = nodes["b"].stats.withdrawn_blocks
    assert nodes["c"].tree.parent == "b"
    for x, y in (("b", "c"), ("c", "b")):
        nodes[x].link_down(y)
    links.discard(("b", "c"))
    nodes.pop("c")
    assert nodes["b"].stats.new_epochs == 0                             # c was b's child: no new epoch
    assert nodes["b"].stats.withdrawn_blocks == withdrawn               # nothing of c was left to withdraw
    settle(nodes, links)
    assert_kalman(nodes, record, t, keep="ab")


@pytest.mark.parametrize("seed", range(3))
def test_a_new_epoch_with_a_quarantined_channel_keeps_exactly_the_honest_information(seed):
    nodes, links, record, t, rng = lied_to(seed)
    # b loses its parent a: b starts a new epoch (every channel withdrawn, the quarantined one too)
    for x, y in (("a", "b"), ("b", "a")):
        nodes[x].link_down(y)
    assert nodes["b"].stats.new_epochs >= 1 and nodes["b"].is_quarantined("c")   # the record outlives the change
    for k in range(26, 31):
        t = step(nodes, k, rng, record, liars=("c",))
    for x, y in (("a", "b"), ("b", "a")):
        nodes[x].link_up(y)
    t = round(t + max(x.hold for x in nodes.values()) + 0.1, 9)
    for x in nodes.values():
        x.predict(t)
    settle(nodes, links)
    assert nodes["b"].is_quarantined("c")
    assert_kalman(nodes, record, t, keep="ab")


@pytest.mark.parametrize("seed", range(3))
def test_a_quarantine_while_a_change_holds_information_lets_the_held_times_go_first(seed):
    """b holds what d sent (d's link broke); then c lies and is quarantined: b is never
    over-confident, and once d's hold would have expired b equals the Kalman filter on a and b."""
    links = {("a", "b"), ("b", "c"), ("b", "d")}
    nodes = network(["a", "b", "c", "d"], links, hold=30.0)
    rng = np.random.default_rng(seed)
    record: list = []
    t = 0.0
    for k in range(1, 11):
        t = step(nodes, k, rng, record, silent=("c",))
    for x, y in (("b", "d"), ("d", "b")):
        nodes[x].link_down(y)
    links.discard(("b", "d"))
    nodes.pop("d")
    assert nodes["b"]._tree_held     # b's estimate keeps what d sent for hold seconds
    for k in range(11, 21):
        t = step(nodes, k, rng, record, liars=("c",))
        _, cov = central_kalman([(tt, z, s) for tt, z, s, n in record], t)
        P = nodes["b"].estimate()[1]
        worst = np.linalg.eigvalsh(P - cov)[0] / np.abs(cov).max()
        assert worst >= -1e-9, worst
    assert nodes["b"].is_quarantined("c") and not nodes["b"]._tree_held
    settle(nodes, links)
    assert_kalman(nodes, record, t, keep="ab")
