"""A flood of 1 MiB publications at the launcher's monitor: bounded memory, counted, results intact.

The full 20 s measurement is ``benchmarks/monitor_flood.py``; this one floods for 4 s.
"""
from __future__ import annotations

import pytest

pytest.importorskip("zenoh")

from dfusion.run.common import status_limit  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402

from tests.helpers.flood import run_with_flood  # noqa: E402
from tests.run.test_supervision import scenario  # noqa: E402

MIB = 1 << 20


def test_a_flood_of_1mib_publications_at_the_monitor(tmp_path):
    """The launcher's peak memory stays under 300 MB, every flooded publication is counted, and
    every node finishes exact. (The monitor's per-step records may miss a few steps under a flood
    on a loaded machine: the nodes publish for the monitor with CongestionControl.DROP and never
    wait for it; the benchmark reports them.)"""
    path = scenario(tmp_path, 7.0)
    run = run_with_flood(path, tmp_path / "run", size=MIB, flood_s=4.0)
    m = run.metrics
    rm = m["run"]
    assert run.sent > 100, run.sent   # a flood, not a trickle
    assert run.rss_peak_mb < 300, (run.rss_before_mb, run.rss_peak_mb, run.rss_samples_mb)
    q = rm["monitor_queue"]
    assert q["max_publication_bytes"] == status_limit(load_scenario(path)) < MIB
    # every flooded publication that reached the monitor was dropped as it arrived, and counted
    assert q["oversized"] > 100 and q["oversized_bytes"] == q["oversized"] * MIB, q
    assert rm["monitor_rejections"].get("oversized") == q["oversized"], rm["monitor_rejections"]
    assert q["peak_bytes"] < 1 * MIB, q   # the genuine publications: a few kB at a time
    assert not rm["failures"], rm["failures"]
    for name, v in m["nodes"].items():   # every node's result intact (linear chain: exact)
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
        assert rm["nodes"][name]["finished"] and rm["nodes"][name]["incarnations"] == 1, rm["nodes"][name]
