"""The scenario's links emulated at the sender (dfusion.run.links), against SimulatedNetwork."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from dfusion.run.links import EmulatedLinks, describe, node_links
from dfusion.scenario import load_scenario
from dfusion.sim import run_scenario
from dfusion.transport.simulated import LinkSpec, SimulatedNetwork

from tests.run.test_processes import PAIR

ROOT = Path(__file__).resolve().parents[2]
SPEC = LinkSpec(latency=0.05, jitter=0.1, drop=0.3, duplicate=0.2, reorder=0.3, reorder_delay=0.2,
                outages=((2.0, 3.0), (6.5, 7.25)))


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_emulated_links_deliver_what_the_simulated_network_delivers(speed):
    """The same seed and sends: the same copies arrive, at the same scenario times (independent
    reference: SimulatedNetwork, which dfusion simulate uses)."""
    seed, n = 11, 400
    net = SimulatedNetwork([("a", "b", SPEC)], seed=seed)
    clock = FakeClock()
    wall0 = 1000.0
    sent: list[tuple[bytes, float]] = []   # (payload, scenario time it left the sender)

    def real_send(src, dst, data, t):
        assert (src, dst) == ("a", "b")
        sent.append((data, (clock.now - wall0) * speed))

    em = EmulatedLinks("a", {"b": SPEC}, seed, real_send, speed=speed, clock=clock)

    def advance(to: float) -> None:   # the node's loop: it wakes for every delayed copy that falls due
        while em.next_due() <= to:
            clock.now = em.next_due()
            em.release_due()
        clock.now = to

    for k in range(n):
        t = 0.025 * k
        advance(wall0 + t / speed)
        payload = k.to_bytes(4, "little")
        net.send("a", "b", payload, t)
        em.send("b", payload, t)
    advance(wall0 + 1e6)
    expected = sorted((d.data, round(d.t_arrival, 9)) for d in net.flush())
    got = sorted((data, round(t, 9)) for data, t in sent)
    assert got == expected
    stats = net.stats.links[("a", "b")]
    c = em.counters["b"]
    assert (c.sent, c.dropped, c.duplicated) == (stats.sent, stats.dropped, stats.duplicated)
    assert 0 < c.dropped < n and c.duplicated > 0 and em.pending() == 0


def test_skipped_sends_keep_the_random_stream_aligned():
    """A send skipped (neighbour not alive) still draws: the next messages meet the fates of the
    same-numbered messages in simulate."""
    seed = 5
    net = SimulatedNetwork([("a", "b", SPEC)], seed=seed)
    sent = []
    em = EmulatedLinks("a", {"b": SPEC}, seed, lambda s, d, data, t: sent.append(data), clock=lambda: 0.0)
    for k in range(100):
        payload = bytes([k])
        net.send("a", "b", payload, 0.01 * k)
        em.send("b", payload, 0.01 * k, deliver=k % 3 != 0)
    em.flush()
    expected = sorted(d.data for d in net.flush() if d.data[0] % 3 != 0)
    assert sorted(sent) == expected


def test_flush_and_discard():
    out = []
    clock = FakeClock()
    em = EmulatedLinks("a", {"b": LinkSpec(latency=1.0)}, 0, lambda s, d, data, t: out.append(data), clock=clock)
    assert em.send("b", b"x", 0.0) == 1 and out == [] and em.next_due() == 1.0
    assert em.flush() == 1 and out == [b"x"]
    em.send("b", b"y", 0.0)
    assert em.discard() == 1 and em.pending() == 0 and out == [b"x"]
    em.send("c", b"z", 0.0)   # a link the scenario does not describe: sent at once
    assert out == [b"x", b"z"]


def test_node_links_and_description():
    sc = load_scenario(ROOT / "topologies" / "chain3.scenario.toml")
    assert set(node_links(sc.links, "b")) == {"a", "c"} and set(node_links(sc.links, "a")) == {"b"}
    assert describe(True, sc.links) == "links emulated as in the scenario: latency, drops, outages"
    assert describe(False, sc.links).startswith("links not emulated")


# two nodes on a lossy, delaying link with an outage
LOSSY = PAIR.replace("duration = 60.0", "duration = 8.0").replace("seed = 5", "seed = 21") + """latency = 0.1
jitter = 0.05
drop = 0.3
outages = [[3.0, 4.5]]
"""


def test_dfusion_run_loses_what_simulate_loses(tmp_path, capsys):
    """dfusion run emulates the scenario's links by default: the messages lost are simulate's, and the
    table and the plot title say the links are emulated."""
    pytest.importorskip("zenoh")
    from dfusion.cli import main

    path = tmp_path / "lossy.scenario.toml"
    path.write_text(LOSSY)
    out = tmp_path / "run.json"
    rc = main(["run", str(path), "--speed", "4", "--json", str(out), "--quiet"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    got = json.loads(out.read_text())
    ref = run_scenario(load_scenario(path)).metrics
    assert all(v["sends_skipped_not_alive"] == 0 for v in got["run"]["nodes"].values())
    assert got["messages"] == ref["messages"]
    assert got["messages_dropped"] == ref["messages_dropped"] > 0
    assert sum(v["dropped_emulated"] for v in got["run"]["nodes"].values()) == ref["messages_dropped"]
    assert got["run"]["links_emulated"] is True
    assert "links emulated as in the scenario: latency, jitter, drops, outages" in printed
    for v in got["nodes"].values():
        assert v["final_gap"] < 1e-6
    print(f"dfusion run lost {got['messages_dropped']} of {got['messages']} messages, simulate "
          f"{ref['messages_dropped']} of {ref['messages']}")
