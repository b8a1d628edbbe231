"""The counts of every table add up, checked against counters kept elsewhere: the links'
own statistics (dfusion.transport), the nodes' own counters (dfusion.fusion) and the
world's measurement list."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from dfusion.scenario import load_scenario
from dfusion.sim.runner import run_scenario

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name,duration", [("star5.scenario.toml", 20.0), ("tree7-outage.scenario.toml", 20.0),
                                           ("urus.scenario.toml", 20.0)])
def test_counts_add_up(name, duration):
    sc = load_scenario(ROOT / "topologies" / name, duration=duration)
    res = run_scenario(sc)
    m = res.metrics
    tr, net = m["traffic"], m["traffic"]["network"]
    # the links' statistics: every copy is delivered, dropped or in flight (none at the end)
    assert net["sent"] + net["duplicated"] == net["delivered"] + net["dropped"] + net["in_flight"]
    assert net["in_flight"] == 0
    # every delivered copy is fused or rejected; the nodes' own counters agree
    assert net["delivered"] == tr["fused"] + tr["rejected"]
    assert sum(v["received"] for v in m["nodes"].values()) == tr["fused"] + tr["final_rounds"]
    assert m["messages"] == sum(v["messages"] for v in m["nodes"].values()) == net["sent"] + tr["final_rounds"]
    # the final rounds: diameter + 2 rounds over every directed link (docs/fusion.md, settling rounds)
    import networkx as nx
    assert tr["final_rounds"] == (nx.diameter(sc.graph) + 2) * 2 * sc.graph.number_of_edges()
    # measurements: the world's list = used + rejected by the front end + refused
    md = m["measurements_detail"]
    assert m["measurements"] == len(res.world.measurements) == md["fused"] + md["rejected"] + m["measurements_refused"]
    assert len(res.events) == len(res.world.measurements)
    # the printed lines say the same numbers, and each sum holds as printed
    table = res.table()
    a = re.search(r"(\d+) sent \+ (\d+) duplicated copies = (\d+) delivered \+ (\d+) dropped \+ (\d+) in flight; "
                  r"of the delivered: (\d+) fused \+ (\d+) rejected", table)
    s, d, dl, dr, fl, fu, rj = map(int, a.groups())
    assert s + d == dl + dr + fl and dl == fu + rj and (s, dl) == (net["sent"], net["delivered"])
    b = re.search(r"measurements: (\d+) taken = (\d+) used \+ (\d+) rejected .* \+ (\d+) refused", table)
    n, u, r, f = map(int, b.groups())
    assert n == u + r + f == len(res.world.measurements)
    # units on every column, the ANEES in words
    assert "RMSE [m]" in table and "final gap pos [m]" in table and "final gap vel [m/s]" in table
    assert "a consistent filter averages 4" in table
