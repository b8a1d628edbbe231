"""The URUS person-tracking demo: its scenario, an in-process run with the outage, and the figures."""
from __future__ import annotations

import importlib.util
import json
import logging
import re
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from dfusion.scenario import load_scenario
from dfusion.sim import simulate_world

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "topologies" / "urus.scenario.toml"


def _demo_module():
    spec = importlib.util.spec_from_file_location("urus_demo", ROOT / "examples" / "urus_demo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_urus_scenario_is_the_experiment_of_figure_33():
    sc = load_scenario(SCENARIO)
    kinds = {n: s.sensor_kind for n, s in sc.nodes.items()}
    assert sorted(kinds.values()) == ["camera", "camera", "none", "wsn_rssi"]
    assert nx.is_tree(sc.graph)
    [(a, b, t0, t1)] = sc.outages()
    assert 8.0 <= t1 - t0 <= 12.0
    assert sc.nodes["wsn"].sensor.dim_z >= 10
    cams = [s.sensor for s in sc.nodes.values() if s.sensor_kind == "camera"]
    # non-overlapping views over the 30 m x 20 m square
    xs, ys = np.meshgrid(np.arange(0.0, 30.01, 0.25), np.arange(0.0, 20.01, 0.25))
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    views = [np.array([c.in_view(p) for p in pts]) for c in cams]
    assert all(v.any() for v in views) and not (views[0] & views[1]).any()
    # the person stays in the square and walks in and out of each view
    w = simulate_world(sc)
    assert np.all((w.states[:, 0] > 0) & (w.states[:, 0] < 30) & (w.states[:, 1] > 0) & (w.states[:, 1] < 20))
    for c in cams:
        seen = np.array([c.in_view(x) for x in w.states])
        assert 0.1 < seen.mean() < 0.6
        assert np.count_nonzero(np.diff(seen.astype(int))) >= 2       # enters and leaves
    # the outage happens while the person is in the other camera's view
    k = (w.times > t0) & (w.times < t1)
    other = sc.nodes["cam_right"].sensor
    assert np.mean([other.in_view(x) for x in w.states[k]]) > 0.8


def test_demo_runs_in_process_shortened_and_writes_its_figures(tmp_path, capsys, caplog, monkeypatch):
    demo = _demo_module()
    monkeypatch.setattr(demo, "have_run_command", lambda: False)     # the fallback path, with a warning
    caplog.set_level(logging.WARNING)
    rc = demo.main(["--duration", "45", "--out", str(tmp_path)])
    assert rc == 0
    assert "not available" in caplog.text
    out = capsys.readouterr().out
    assert "centralized" in out and "mode: in-process" in out and "outage gateway - cam_left" in out
    written = {p.name for p in tmp_path.iterdir()}
    for name in written:
        assert (tmp_path / name).stat().st_size > 1000
    # the README lists every file the demo writes (it once listed 3 of 6)
    readme = (ROOT / "README.md").read_text()
    assert set(re.findall(r"`out/(urus[\w.]+)`", readme)) == written == {
        "urus_figure33.png", "urus_nodes.png", "urus.json", "urus_topdown.png", "urus.mcap", "urus_series.csv"}
    m = json.loads((tmp_path / "urus.json").read_text())
    assert m["demo"]["mode"] == "in-process" and m["steps"] == 451
    for name, v in m["nodes"].items():
        # nonlinear models and the WSN's particle filter against the centralized EKF: 0.020 measured
        assert v["final_gap"] < 0.05, (name, v["final_gap"])
        assert v["rmse"] < 0.5 and v["anees"] < 11.0
    assert m["centralized"]["rmse"] < 0.4


def test_outage_shows_and_heals_in_the_gap(tmp_path):
    from dfusion.sim import run_scenario

    res = run_scenario(load_scenario(SCENARIO, duration=48.0))
    t = res.times
    gap = np.abs(res.node_mean["cam_left"] - res.central_mean).max(axis=1)
    during = (t > 38.0) & (t < 42.0)
    after = (t > 44.0)
    assert gap[during].max() > 0.2            # cam_left only predicts
    assert gap[after].max() < 0.1             # and catches up once the link returns
    other = np.abs(res.node_mean["wsn"] - res.central_mean).max(axis=1)
    assert other[during].max() < 0.15


def test_plot_figure33_needs_a_known_node(tmp_path):
    from dfusion.viz import plot_figure33
    from dfusion.sim import run_scenario

    res = run_scenario(load_scenario(SCENARIO, duration=3.0))
    with pytest.raises(KeyError, match="nobody"):
        plot_figure33(res, "nobody", tmp_path / "x.png")
    assert plot_figure33(res, "wsn", tmp_path / "wsn.png").stat().st_size > 1000   # no view strip for the WSN


def test_the_readme_sample_table_is_what_the_demo_prints():
    """README.md shows the in-process demo's table (``urus_demo.py --in-process``: deterministic);
    it must be the table of the full run, row for row (it once lacked the central oracle row)."""
    from dfusion.sim import run_scenario

    readme = (ROOT / "README.md").read_text()
    block = re.search(r"```\n(node +RMSE \[m\].*?)\n```", readme, re.S)
    assert block, "README.md has no sample table"
    lines = run_scenario(load_scenario(SCENARIO)).table().splitlines()
    table = lines[:next(i for i, line in enumerate(lines) if not line.strip())]
    assert block.group(1).splitlines() == table, "README.md's sample table is stale; the run prints:\n" + "\n".join(table)
