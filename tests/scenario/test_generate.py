"""Scenarios on random trees (dfusion.scenario.generate)."""
from __future__ import annotations

import subprocess
import sys
import tomllib

import networkx as nx
import pytest

from dfusion.errors import ValidationError
from dfusion.scenario import load_scenario
from dfusion.scenario.generate import random_tree_scenario, scenario_toml
from dfusion.sim import run_scenario


@pytest.mark.parametrize("n", [2, 8, 33])
def test_a_random_tree_scenario_is_a_valid_scenario_with_an_exact_window(n):
    raw = random_tree_scenario(n, seed=n, duration=5.0)
    sc = load_scenario(raw)
    assert sorted(sc.nodes) == sorted(f"n{k}" for k in range(n))
    assert nx.is_tree(sc.graph) and sc.graph.number_of_nodes() == n
    assert not sc.warnings   # the window is at least the minimum the tree needs (the loader checks it)
    d = nx.diameter(sc.graph)
    assert sc.window * sc.dt >= d * (0.02 + 0.5)


def test_toml_text_loads_to_the_same_scenario(tmp_path):
    raw = random_tree_scenario(12, seed=3, drop=0.1, window=50)
    text = scenario_toml(raw, "a comment\nof two lines")
    assert text.startswith("# a comment\n# of two lines\n")
    assert tomllib.loads(text) == raw
    path = tmp_path / "t.toml"
    path.write_text(text)
    assert load_scenario(path).raw == load_scenario(raw).raw


def test_fusion_on_a_generated_tree_ends_on_the_centralized_estimate():
    """simulate on a 16-node random tree (measurements every step, on the grid): every node ends within
    1e-9 of the centralized EKF, the independent reference of the runner."""
    res = run_scenario(load_scenario(random_tree_scenario(16, seed=5, duration=6.0)))
    gaps = [v["final_gap"] for v in res.metrics["nodes"].values()]
    assert len(gaps) == 16 and max(gaps) <= 1e-9


def test_bad_settings_and_the_command_line(tmp_path):
    with pytest.raises(ValidationError):
        random_tree_scenario(4, drop=1.0)
    with pytest.raises(ValidationError):
        random_tree_scenario(0)
    out = tmp_path / "t.toml"
    proc = subprocess.run([sys.executable, "-m", "dfusion.scenario.generate", "20", "--seed", "2", "--rate", "5",
                           "-o", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    sc = load_scenario(out)
    assert len(sc.nodes) == 20 and sc.nodes["n3"].rate == 5.0 and sc.seed == 2
