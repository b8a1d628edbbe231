"""A sensor kind written outside dfusion, loaded as a plug-in by `dfusion simulate` and `dfusion run`.

The plug-in is ``tests/data/plugins/range_beacon.py``, the module that
``docs/new-sensor-kind.md`` walks through (the page shows it verbatim: checked here).
"""
from __future__ import annotations

import json
import re
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest

from dfusion.cli import main
from dfusion.errors import ScenarioError
from dfusion.scenario import builtin_kinds, load_plugin, load_scenario
from dfusion.scenario import plugins as plugins_module

ROOT = Path(__file__).resolve().parents[2]
PLUGIN = ROOT / "tests" / "data" / "plugins" / "range_beacon.py"
SCENARIO = ROOT / "tests" / "data" / "plugins" / "beacons.scenario.toml"


def without_plugins_key(tmp_path: Path) -> Path:
    """The beacon scenario without its ``plugins`` line: the plug-in then has to come from elsewhere."""
    text = SCENARIO.read_text().replace('plugins = ["range_beacon.py"]\n', "")
    path = tmp_path / "beacons.scenario.toml"
    path.write_text(text)
    return path


def test_the_plugin_is_one_short_module_and_the_tutorial_shows_it_verbatim():
    code = PLUGIN.read_text()
    assert len(code.splitlines()) < 50
    page = (ROOT / "docs" / "new-sensor-kind.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert code in blocks, "docs/new-sensor-kind.md must show tests/data/plugins/range_beacon.py verbatim"
    assert "dfusion" not in str(PLUGIN.relative_to(ROOT).parts[0])   # not one of dfusion's own files


def test_the_beacon_jacobian_matches_finite_differences():
    kind = load_plugin(str(PLUGIN)).sensors["range_beacon"]
    sensor = kind.sensor({"beacon": [1.0, -1.5], "std": 0.2}, None)
    x = np.array([4.0, 2.5, 0.3, -0.1])
    eps = 1e-6
    num = np.array([(sensor.h(x + eps * e) - sensor.h(x - eps * e)) / (2 * eps) for e in np.eye(4)]).T
    np.testing.assert_allclose(sensor.H(x), num, atol=1e-8)
    assert sensor.h(x)[0] == pytest.approx(5.0)


def test_simulate_with_the_plugin_named_in_the_scenario(capsys):
    assert main(["simulate", str(SCENARIO), "-q"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ("west", "south", "east", "centralized"))
    # the tutorial shows this table as printed (it once showed an older table's columns and rows)
    table = out.splitlines()[:next(i for i, line in enumerate(out.splitlines()) if not line.strip())]
    page = (ROOT / "docs" / "new-sensor-kind.md").read_text()
    shown = re.search(r"```\n(node +RMSE \[m\].*?)\n```", page, re.S)
    assert shown and shown.group(1).splitlines() == table, "docs/new-sensor-kind.md's table is stale:\n" + \
        "\n".join(table)


def test_simulate_with_the_plugin_on_the_command_line(tmp_path):
    path = without_plugins_key(tmp_path)
    with pytest.raises(ScenarioError, match="unknown sensor 'range_beacon'"):
        load_scenario(path)
    out = tmp_path / "out.json"
    assert main(["simulate", str(path), "--plugin", str(PLUGIN), "--json", str(out), "-q"]) == 0
    m = json.loads(out.read_text())
    assert m["measurements"] == 3 * 5 * 30 and m["measurements_refused"] == 0
    for name, v in m["nodes"].items():
        # three ranges fix the position: every node tracks, and ends near the centralized EKF
        # (the range model is nonlinear: nodes linearize at their own estimates)
        assert v["rmse"] < 1.6 * m["centralized"]["rmse"], (name, v)
        assert v["final_gap"] < 0.1, (name, v)
        assert 0.2 < v["anees"] < 12.0, (name, v)


def test_an_installed_entry_point_is_loaded_for_every_scenario(tmp_path, monkeypatch):
    import sys

    monkeypatch.syspath_prepend(str(PLUGIN.parent))
    ep = EntryPoint("beacons", "range_beacon", plugins_module.ENTRY_POINT_GROUP)
    monkeypatch.setattr(plugins_module, "entry_points", lambda group: [ep] if group == ep.group else [])
    sc = load_scenario(without_plugins_key(tmp_path))
    assert sc.nodes["west"].sensor_kind == "range_beacon" and "range_beacon" in sys.modules


def test_plugin_errors_are_clear(tmp_path):
    with pytest.raises(ScenarioError, match="cannot be imported"):
        load_scenario(without_plugins_key(tmp_path), plugins=["no_such_module_xyz"])
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(without_plugins_key(tmp_path), plugins=["missing.py"])
    empty = tmp_path / "empty_plugin.py"
    empty.write_text("X = 1\n")
    with pytest.raises(ScenarioError, match="defines none of"):
        load_scenario(without_plugins_key(tmp_path), plugins=[str(empty)])
    clash = tmp_path / "clash_plugin.py"
    clash.write_text(PLUGIN.read_text().replace('"range_beacon"', '"camera"'))
    with pytest.raises(ScenarioError, match="'camera' is already defined"):
        load_scenario(without_plugins_key(tmp_path), plugins=[str(clash)])
    assert "range_beacon" not in builtin_kinds().sensors   # loading plug-ins registered nothing globally


def test_run_over_processes_loads_the_plugin_in_every_node(tmp_path, capsys):
    path = without_plugins_key(tmp_path)
    text = path.read_text().replace("duration = 30.0", "duration = 6.0")
    path.write_text(text)
    out = tmp_path / "run.json"
    rc = main(["run", str(path), "--plugin", str(PLUGIN), "--speed", "4", "--json", str(out),
               "--run-dir", str(tmp_path / "run"), "--quiet"])
    assert rc == 0, capsys.readouterr()
    m = json.loads(out.read_text())
    assert set(m["nodes"]) == {"west", "south", "east"}
    assert all(v["final_gap"] < 0.1 and v["messages"] > 0 for v in m["nodes"].values()), m["nodes"]
