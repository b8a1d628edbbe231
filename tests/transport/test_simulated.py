"""Tests of the simulated lossy network (dfusion.transport.simulated) and the transport types."""
from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dfusion.errors import ValidationError
from dfusion.transport import LinkSpec, SimulatedNetwork
from dfusion.transport import Delivery, Transport, TransportStats


def _send_many(net: SimulatedNetwork, src: str, dst: str, n: int, dt: float = 0.01, t0: float = 0.0) -> None:
    """Send ``n`` messages whose payload is their index, ``dt`` apart."""
    for k in range(n):
        net.send(src, dst, k.to_bytes(4, "big"), t0 + k * dt)


def _index(d: Delivery) -> int:
    return int.from_bytes(d.data, "big")


def _lossy_spec() -> LinkSpec:
    return LinkSpec(latency=0.05, jitter=0.02, drop=0.2, duplicate=0.1, reorder=0.2, reorder_delay=0.1)


# ---------------------------------------------------------------- determinism


def test_same_seed_gives_same_deliveries() -> None:
    runs = []
    for _ in range(2):
        net = SimulatedNetwork([("a", "b", _lossy_spec()), ("b", "c", _lossy_spec())], seed=7)
        _send_many(net, "a", "b", 200)
        _send_many(net, "c", "b", 200)
        _send_many(net, "b", "a", 50)
        runs.append((net.receive("b", 1.0), net.flush(), net.stats))
    assert runs[0] == runs[1]
    assert len(runs[0][0]) > 0 and len(runs[0][1]) > 0


def test_different_seed_gives_different_deliveries() -> None:
    out = []
    for seed in (1, 2):
        net = SimulatedNetwork([("a", "b", _lossy_spec())], seed=seed)
        _send_many(net, "a", "b", 200)
        out.append(net.flush())
    assert out[0] != out[1]


# ---------------------------------------------------------------- drop, delay, duplicates


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drop_rate_matches_spec_within_binomial_bound(seed: int) -> None:
    n, p = 20_000, 0.2
    net = SimulatedNetwork({("a", "b"): LinkSpec(drop=p)}, seed=seed)
    _send_many(net, "a", "b", n)
    delivered = len(net.flush())
    sigma = math.sqrt(n * p * (1 - p))
    assert abs((n - delivered) - n * p) <= 5 * sigma
    assert net.stats.total.dropped == n - delivered


def test_delay_lies_within_latency_plus_jitter_and_covers_it() -> None:
    latency, jitter = 0.3, 0.1
    net = SimulatedNetwork({("a", "b"): LinkSpec(latency=latency, jitter=jitter)}, seed=3)
    _send_many(net, "a", "b", 5000)
    delays = [d.t_arrival - d.t_sent for d in net.flush()]
    assert len(delays) == 5000
    assert min(delays) >= latency - 1e-12
    assert max(delays) <= latency + jitter + 1e-12
    assert min(delays) < latency + 0.01 * jitter
    assert max(delays) > latency + 0.99 * jitter


def test_reorder_delay_is_bounded() -> None:
    spec = LinkSpec(latency=0.1, jitter=0.05, reorder=0.5, reorder_delay=0.4)
    net = SimulatedNetwork({("a", "b"): spec}, seed=4)
    _send_many(net, "a", "b", 2000)
    delays = [d.t_arrival - d.t_sent for d in net.flush()]
    assert min(delays) >= 0.1 - 1e-12
    assert max(delays) <= 0.1 + 0.05 + 0.4 + 1e-12
    assert max(delays) > 0.1 + 0.05 + 0.3  # some copies did get the extra delay


def test_duplicates_are_identical_copies() -> None:
    net = SimulatedNetwork({("a", "b"): LinkSpec(latency=0.1, jitter=0.05, duplicate=1.0)}, seed=5)
    _send_many(net, "a", "b", 100)
    deliveries = net.flush()
    assert len(deliveries) == 200
    by_index: dict[int, list[Delivery]] = {}
    for d in deliveries:
        by_index.setdefault(_index(d), []).append(d)
    assert sorted(by_index) == list(range(100))
    for copies in by_index.values():
        assert len(copies) == 2
        first, second = copies
        assert (first.data, first.src, first.dst, first.t_sent) == (second.data, second.src, second.dst, second.t_sent)
    assert net.stats.total.duplicated == 100


def test_duplicate_rate_matches_spec() -> None:
    n, p = 10_000, 0.3
    net = SimulatedNetwork({("a", "b"): LinkSpec(duplicate=p)}, seed=6)
    _send_many(net, "a", "b", n)
    extra = len(net.flush()) - n
    assert abs(extra - n * p) <= 5 * math.sqrt(n * p * (1 - p))


# ---------------------------------------------------------------- outages


def test_outage_loses_messages_sent_or_arriving_in_it_and_no_others() -> None:
    # Binary-exact times: sends every 1/64 s, latency 1/8 s, outage [1, 2).
    spec = LinkSpec(latency=0.125, outages=[(1.0, 2.0)])
    net = SimulatedNetwork([("a", "b", spec)], seed=0)
    sent = [k / 64 for k in range(200)]
    for k, t in enumerate(sent):
        net.send("a", "b", k.to_bytes(4, "big"), t)
    got = [d.t_sent for d in net.flush()]
    # Lost iff sent in [1, 2) or arriving (t + 0.125) in [1, 2), i.e. 0.875 <= t < 2.
    assert got == [t for t in sent if not 0.875 <= t < 2.0]
    assert net.stats.total.dropped == sum(1 for t in sent if 0.875 <= t < 2.0)


def test_outage_only_removes_affected_messages_with_jitter() -> None:
    base = LinkSpec(latency=0.1, jitter=0.3, drop=0.1, reorder=0.1, reorder_delay=0.5)
    with_outage = dataclasses.replace(base, outages=[(1.0, 1.5), (3.0, 3.2)])
    results = []
    for spec in (base, with_outage):
        net = SimulatedNetwork([("a", "b", spec)], seed=11)
        _send_many(net, "a", "b", 500)
        results.append(net.flush())
    free, cut = results

    def affected(d: Delivery) -> bool:
        return with_outage.is_down(d.t_sent) or with_outage.is_down(d.t_arrival)

    assert cut == [d for d in free if not affected(d)]
    assert any(affected(d) for d in free)


def test_outage_applies_to_both_directions_and_is_not_buffered() -> None:
    spec = LinkSpec(latency=0.01, outages=[(5.0, 6.0)])
    net = SimulatedNetwork([("a", "b", spec)], seed=0)
    assert net.link_up("a", "b", 4.99) and net.link_up("b", "a", 6.0)
    assert not net.link_up("a", "b", 5.0) and not net.link_up("b", "a", 5.5)
    net.send("a", "b", b"x", 5.5)
    net.send("b", "a", b"y", 5.5)
    assert net.pending() == 0
    assert net.receive("a", 100.0) == [] and net.receive("b", 100.0) == []
    net.send("a", "b", b"z", 6.0)
    assert [d.data for d in net.receive("b", 6.01)] == [b"z"]


# ---------------------------------------------------------------- ordering


def _inversions(deliveries: list[Delivery]) -> int:
    idx = [_index(d) for d in deliveries]
    return sum(1 for x, y in zip(idx, idx[1:]) if y < x)


def test_reorder_happens_when_enabled() -> None:
    net = SimulatedNetwork({("a", "b"): LinkSpec(latency=0.1, reorder=0.3, reorder_delay=0.2)}, seed=8)
    _send_many(net, "a", "b", 300)
    assert _inversions(net.flush()) > 0


def test_fifo_without_jitter_or_reorder() -> None:
    spec = LinkSpec(latency=0.1, drop=0.3, duplicate=0.3)
    net = SimulatedNetwork({("a", "b"): spec}, seed=9)
    _send_many(net, "a", "b", 1000, dt=0.001)
    deliveries = net.flush()
    assert len(deliveries) > 500
    assert _inversions(deliveries) == 0


def test_equal_arrival_times_are_delivered_in_send_order() -> None:
    net = SimulatedNetwork([("a", "c", LinkSpec(latency=1.0)), ("b", "c", LinkSpec(latency=0.5))], seed=0)
    net.send("a", "c", b"first", 0.0)
    net.send("b", "c", b"second", 0.5)
    net.send("a", "c", b"third", 0.0)
    assert [d.data for d in net.receive("c", 1.0)] == [b"first", b"second", b"third"]


@settings(max_examples=60, deadline=None)
@given(
    latency=st.floats(0.0, 2.0),
    drop=st.floats(0.0, 0.9),
    duplicate=st.floats(0.0, 1.0),
    outages=st.lists(st.tuples(st.floats(0.0, 10.0), st.floats(0.01, 2.0)), max_size=3),
    gaps=st.lists(st.floats(0.0, 0.5), min_size=1, max_size=60),
    polls=st.lists(st.floats(0.0, 3.0), max_size=10),
    seed=st.integers(0, 2**32),
)
def test_fifo_property_without_jitter_or_reorder(
    latency: float,
    drop: float,
    duplicate: float,
    outages: list[tuple[float, float]],
    gaps: list[float],
    polls: list[float],
    seed: int,
) -> None:
    spec = LinkSpec(latency=latency, drop=drop, duplicate=duplicate, outages=[(s, s + w) for s, w in outages])
    net = SimulatedNetwork({("a", "b"): spec}, seed=seed)
    t = 0.0
    for k, gap in enumerate(gaps):  # non-decreasing send times, ties allowed
        t += gap
        net.send("a", "b", k.to_bytes(4, "big"), t)
    received: list[Delivery] = []
    until = 0.0
    for step in polls:  # receive in chunks, then flush the rest
        until += step
        chunk = net.receive("b", until)
        assert all(d.t_arrival <= until for d in chunk)
        received += chunk
    received += net.flush()
    assert _inversions(received) == 0
    assert [d.t_arrival for d in received] == sorted(d.t_arrival for d in received)
    assert net.stats.total.delivered == len(received)


# ---------------------------------------------------------------- stats


def test_stats_identity_per_link_and_total() -> None:
    net = SimulatedNetwork(
        [("a", "b", _lossy_spec()), ("b", "c", dataclasses.replace(_lossy_spec(), outages=[(0.5, 0.7)]))], seed=12
    )
    _send_many(net, "a", "b", 300)
    _send_many(net, "b", "c", 200, dt=0.005)
    _send_many(net, "c", "b", 100, dt=0.02, t0=0.1)
    delivered = net.receive("b", 1.0) + net.receive("c", 0.6)
    assert net.pending() > 0

    report = net.stats
    for key, s in report.links.items():
        # The exact identity: every sent message plus every extra copy is delivered, dropped or in flight.
        assert s.sent + s.duplicated == s.delivered + s.dropped + s.in_flight
    for node in net.nodes:
        assert sum(s.in_flight for (_, dst), s in report.links.items() if dst == node) == net.pending(node)
    assert sum(s.in_flight for s in report.links.values()) == net.pending() == report.total.in_flight
    assert report.total == sum(report.links.values(), TransportStats())
    assert report.total.sent == 600
    assert report.total.bytes_sent == 600 * 4
    assert report.total.delivered == len(delivered)

    delivered += net.flush()
    final = net.stats.total
    assert net.pending() == 0 and final.in_flight == 0
    assert final.sent + final.duplicated == final.delivered + final.dropped
    assert final.delivered == len(delivered)
    assert final.bytes_delivered == sum(len(d.data) for d in delivered)
    assert final.dropped > 0 and final.duplicated > 0


def test_pending_counts_copies_in_flight_per_node() -> None:
    net = SimulatedNetwork([("a", "b", LinkSpec(latency=1.0)), ("b", "c", LinkSpec(latency=1.0))], seed=0)
    net.send("a", "b", b"1", 0.0)
    net.send("c", "b", b"2", 0.0)
    net.send("b", "a", b"3", 0.0)
    assert (net.pending(), net.pending("b"), net.pending("a"), net.pending("c")) == (3, 2, 1, 0)


def test_stats_snapshot_is_a_copy() -> None:
    net = SimulatedNetwork([("a", "b", LinkSpec())], seed=0)
    net.send("a", "b", b"abc", 0.0)
    snapshot = net.stats
    snapshot.links[("a", "b")].sent = 99
    assert net.stats.links[("a", "b")].sent == 1
    assert net.stats.links[("b", "a")] == TransportStats()


# ---------------------------------------------------------------- per-link randomness


def test_adding_links_does_not_change_an_existing_links_deliveries() -> None:
    small = SimulatedNetwork([("a", "b", _lossy_spec())], seed=21)
    big = SimulatedNetwork(
        [("c", "d", _lossy_spec()), ("a", "c", _lossy_spec()), ("a", "b", _lossy_spec()), ("d", "e", _lossy_spec())],
        seed=21,
    )
    for k in range(300):
        t = k * 0.01
        payload = k.to_bytes(4, "big")
        small.send("a", "b", payload, t)
        big.send("c", "d", payload, t)  # traffic on the other links in between
        big.send("a", "b", payload, t)
        big.send("a", "c", payload, t)
    assert small.receive("b", 1.5) == big.receive("b", 1.5)
    assert small.flush() == [d for d in big.flush() if d.dst == "b"]


def test_directions_of_an_undirected_link_have_independent_randomness() -> None:
    net = SimulatedNetwork([("a", "b", _lossy_spec())], seed=3)
    _send_many(net, "a", "b", 100)
    _send_many(net, "b", "a", 100)
    ab = [d.t_arrival - d.t_sent for d in net.receive("b", math.inf)]
    ba = [d.t_arrival - d.t_sent for d in net.receive("a", math.inf)]
    assert ab != ba


# ---------------------------------------------------------------- topology and interface


def test_topology_queries() -> None:
    net = SimulatedNetwork({("a", "b"): LinkSpec(), ("b", "a"): LinkSpec(), ("a", "c"): LinkSpec()}, seed=0)
    assert isinstance(net, Transport)
    assert net.nodes == ("a", "b", "c")
    assert net.neighbors("a") == ("b", "c")
    assert net.neighbors("c") == ()
    assert set(net.links) == {("a", "b"), ("b", "a"), ("a", "c")}
    with pytest.raises(ValidationError, match="no link"):
        net.send("c", "a", b"x", 0.0)


def test_delivery_is_frozen() -> None:
    d = Delivery(1.0, "a", "b", b"x", 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.data = b"y"  # type: ignore[misc]


# ---------------------------------------------------------------- validation


def test_from_dict_accepts_all_keys() -> None:
    spec = LinkSpec.from_dict(
        {
            "latency": 0.1,
            "jitter": 0.02,
            "drop": 0.05,
            "duplicate": 0.01,
            "reorder": 0.1,
            "reorder_delay": 0.2,
            "outages": [[3, 4], [1, 2]],
        }
    )
    assert spec.latency == 0.1 and spec.reorder_delay == 0.2
    assert spec.outages == ((1.0, 2.0), (3.0, 4.0))
    assert LinkSpec.from_dict({}) == LinkSpec()


@pytest.mark.parametrize(
    ("d", "key"),
    [
        ({"latncy": 0.1}, "latncy"),
        ({"latency": -0.1}, "latency"),
        ({"latency": "fast"}, "latency"),
        ({"latency": float("nan")}, "latency"),
        ({"jitter": -1}, "jitter"),
        ({"drop": 1.0}, "drop"),
        ({"drop": -0.1}, "drop"),
        ({"drop": True}, "drop"),
        ({"duplicate": 1.5}, "duplicate"),
        ({"reorder": 2}, "reorder"),
        ({"reorder": 0.1}, "reorder_delay"),
        ({"reorder_delay": -1}, "reorder_delay"),
        ({"outages": [(2, 1)]}, "outages"),
        ({"outages": [(1, 2, 3)]}, "outages"),
        ({"outages": [(0, float("inf"))]}, "outages"),
        ({"outages": "never"}, "outages"),
    ],
)
def test_from_dict_rejects_bad_values_naming_the_key(d: dict, key: str) -> None:
    with pytest.raises(ValidationError, match=key):
        LinkSpec.from_dict(d)


def test_from_dict_rejects_non_mapping() -> None:
    with pytest.raises(ValidationError, match="mapping"):
        LinkSpec.from_dict([("latency", 0.1)])  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("links", "seed", "match"),
    [
        ([("a", "b", LinkSpec())], -1, "seed"),
        ([("a", "b", LinkSpec())], 1.5, "seed"),
        ([("a", "a", LinkSpec())], 0, "two different"),
        ([("a", "b", LinkSpec()), ("b", "a", LinkSpec())], 0, "twice"),
        ([("a", "", LinkSpec())], 0, "non-empty"),
        ([("a", "b", {"latency": 1})], 0, "LinkSpec"),
        ([("a", "b")], 0, "triples"),
        ({("a",): LinkSpec()}, 0, "pairs"),
    ],
)
def test_network_rejects_bad_construction(links: object, seed: object, match: str) -> None:
    with pytest.raises(ValidationError, match=match):
        SimulatedNetwork(links, seed=seed)  # type: ignore[arg-type]


def test_bad_calls_raise_and_leave_the_network_unchanged() -> None:
    clean = SimulatedNetwork([("a", "b", _lossy_spec())], seed=5)
    used = SimulatedNetwork([("a", "b", _lossy_spec())], seed=5)
    bad_calls = [
        lambda: used.send("a", "z", b"x", 0.0),
        lambda: used.send("a", "b", "text", 0.0),
        lambda: used.send("a", "b", b"x", float("nan")),
        lambda: used.send("a", "b", b"x", math.inf),
        lambda: used.receive("z", 1.0),
        lambda: used.receive("b", float("nan")),
        lambda: used.link_up("a", "z", 0.0),
        lambda: used.neighbors("z"),
        lambda: used.pending("z"),
    ]
    for call in bad_calls:
        with pytest.raises(ValidationError):
            call()
    _send_many(clean, "a", "b", 50)
    _send_many(used, "a", "b", 50)
    assert clean.flush() == used.flush()
    assert clean.stats == used.stats
