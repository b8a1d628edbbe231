"""Strict scenario files: every mistake gets one line naming the file, the table and the key."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

from dfusion.cli import main
from dfusion.errors import ScenarioError
from dfusion.scenario import load_scenario

GOOD = """\
duration = 3.0
dt = 0.1
window = 50

[target]
motion = "constant_velocity"
q = 0.1
initial_mean = [0.0, 0.0, 1.0, 0.0]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]

[[nodes]]
name = "a"
sensor = "position"
std = 0.5
rate = 5.0

[[nodes]]
name = "b"
sensor = "position"
std = 0.5
rate = 5.0

[[links]]
between = ["a", "b"]
latency = 0.1
"""


def write(tmp_path: Path, text: str, name: str = "s.scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def error_of(path: Path) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert "\n" not in msg, "a scenario error is one line"
    assert msg.startswith(str(path)), "it names the file"
    return msg


def test_the_reference_scenario_is_valid(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    assert sorted(sc.nodes) == ["a", "b"] and sc.duration == 3.0 and sc.warnings == []


@pytest.mark.parametrize("old, new, expected", [
    ("duration = 3.0", "duraton = 3.0", ["duraton", "did you mean 'duration'"]),
    ("std = 0.5\nrate = 5.0\n\n[[nodes]]\nname = \"b\"", "sdt = 0.5\nrate = 5.0\n\n[[nodes]]\nname = \"b\"",
     ["nodes[0] (a).sdt", "did you mean 'std'"]),
    ("q = 0.1", "qq = 0.1", ["target.qq", "did you mean 'q'"]),
    ("latency = 0.1", "latncy = 0.1", ["links[0].latncy", "did you mean 'latency'"]),
    ("[[links]]", "[[link]]", ["[[link]]", "did you mean 'links'"]),
    ('between = ["a", "b"]', 'between = ["a", "bb"]', ["links[0].between", "'bb'", "no [[nodes]] table",
                                                       "did you mean 'b'"]),
    ('sensor = "position"\nstd = 0.5\nrate = 5.0\n\n[[nodes]]\nname = "b"',
     'sensor = "positon"\nstd = 0.5\nrate = 5.0\n\n[[nodes]]\nname = "b"', ["sensor", "'positon'", "did you mean 'position'"]),
])
def test_typos_are_errors_that_name_the_table_and_the_key(tmp_path, old, new, expected):
    assert old in GOOD
    msg = error_of(write(tmp_path, GOOD.replace(old, new, 1)))
    for part in expected:
        assert part in msg, msg


@pytest.mark.parametrize("value, expected", [("inf", "duration must be a finite number, got inf"),
                                             ("nan", "duration must be a finite number, got nan"),
                                             ("-1.0", "duration must be positive, got -1.0"),
                                             ("true", "duration must be a finite number, got True")])
def test_a_duration_that_is_not_a_positive_finite_number_is_refused(tmp_path, value, expected):
    """Through dfusion.scenario.values.number, the checks a node file's values go through too."""
    msg = error_of(write(tmp_path, GOOD.replace("duration = 3.0", f"duration = {value}")))
    assert expected in msg, msg


def test_a_top_level_key_after_a_table_is_named_as_misplaced(tmp_path):
    # TOML puts a key written after [target] into [target]
    text = GOOD.replace("window = 50\n", "").replace("q = 0.1\n", "q = 0.1\nwindow = 50\n")
    msg = error_of(write(tmp_path, text))
    assert "target.window" in msg and "top-level key" in msg and "before the first table" in msg, msg


def test_a_key_of_another_sensor_kind_is_an_error(tmp_path):
    msg = error_of(write(tmp_path, GOOD.replace("std = 0.5\nrate", "pixel_std = 2.0\nstd = 0.5\nrate", 1)))
    assert "nodes[0] (a).pixel_std" in msg and "sensor = 'position'" in msg, msg


def test_not_toml_binary_and_missing_files(tmp_path):
    assert "invalid TOML" in error_of(write(tmp_path, "duration = = 3\n"))
    binary = tmp_path / "b.scenario.toml"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    assert "not a TOML scenario file" in error_of(binary)
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")


def test_a_one_node_scenario_is_an_error(tmp_path):
    text = GOOD[: GOOD.index("[[nodes]]\nname = \"b\"")]
    msg = error_of(write(tmp_path, text))
    assert "at least two fusion nodes" in msg, msg


def test_wrong_table_types_are_named(tmp_path):
    msg = error_of(write(tmp_path, GOOD.replace("[target]\nmotion", "[targets]\nmotion")))
    assert "[targets]" in msg and "did you mean 'target'" in msg, msg


def test_degenerate_settings_are_warned_about(tmp_path, caplog):
    short = GOOD.replace("window = 50", "window = 2").replace("latency = 0.1", "latency = 1.0")
    with caplog.at_level(logging.WARNING, logger="dfusion.scenario.loader"):
        sc = load_scenario(write(tmp_path, short))
    assert any("shorter than" in w and "minimum_window" in w for w in sc.warnings), sc.warnings
    assert any("shorter than" in r.getMessage() for r in caplog.records)
    silent = GOOD.replace('sensor = "position"\nstd = 0.5\nrate = 5.0', 'sensor = "none"')
    sc = load_scenario(write(tmp_path, silent, "silent.toml"))
    assert any("no node has a sensor" in w for w in sc.warnings), sc.warnings


def test_the_command_line_prints_one_line_and_exits_2(tmp_path, capsys):
    path = write(tmp_path, GOOD.replace("duration = 3.0", "duraton = 3.0"))
    assert main(["simulate", str(path), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "duraton" in err and str(path) in err, err


def test_shipped_scenarios_are_strictly_valid():
    root = Path(__file__).resolve().parents[2]
    for path in sorted((root / "topologies").glob("*.scenario.toml")) + sorted((root / "tests" / "data").rglob("*.scenario.toml")):
        sc = load_scenario(path)
        assert sc.nodes, path


def test_the_security_table_is_checked_when_the_scenario_is_loaded(tmp_path):
    good = GOOD + '\n[security]\nnetwork_key_file = "net.key"\n[security.tls]\ndir = "certs"\n'
    sc = load_scenario(write(tmp_path, good))
    assert sc.security.network_key_file == str(tmp_path / "net.key")
    assert sc.security.tls_dir == str(tmp_path / "certs") and sc.security.tls
    msg = error_of(write(tmp_path, good.replace('dir = "certs"', 'dri = "certs"')))
    assert "security.tls.dri" in msg and "unknown key" in msg
    msg = error_of(write(tmp_path, 'security = "on"\n' + GOOD))
    assert "security" in msg and "must be a table [security]" in msg


def test_the_protection_table_is_checked_strictly(tmp_path):
    from dfusion.fusion.guard import GuardConfig

    text = GOOD.replace("[target]", "[protection]\nfalse_alarm = 0.01\nquarantine = [2, 5]\nrelease = 4\n\n[target]")
    sc = load_scenario(write(tmp_path, text))
    assert sc.protection.node_guard() == GuardConfig(0.01, 2, 5, 4)
    assert load_scenario(write(tmp_path, GOOD, "plain.toml")).protection.node_guard() == GuardConfig()   # on by default
    assert load_scenario(write(tmp_path, text, "off.toml"), protection=False).protection.node_guard() is None
    off = GOOD.replace("[target]", "[protection]\nnetwork_check = false\n\n[target]")
    assert load_scenario(write(tmp_path, off, "nocheck.toml")).protection.node_guard() is None
    for i, (bad, words) in enumerate([
            ("quarantine = [5, 2]", ["protection", "must not exceed"]),
            ('clutter_model = "mht"', ["protection.clutter_model", "'mht'"]),
            ('enabled = "yes"', ["protection.enabled", "true or false"]),
            ("false_alarm = 1.5", ["protection", "false_alarm"]),
            ("relase = 3", ["protection.relase", "did you mean 'release'"]),
            ("quarantine = 3", ["protection.quarantine", "[failures, window]"])]):
        msg = error_of(write(tmp_path, GOOD.replace("[target]", f"[protection]\n{bad}\n\n[target]"), f"bad{i}.toml"))
        for part in words:
            assert part in msg, msg


def test_an_odd_initial_mean_names_the_right_lengths_and_a_cycle_names_the_scenario_key(tmp_path):
    """Issue 25: 3 entries once advised 2, which then ran silently as a 1-D target; the
    cycle's hint named a Python function instead of the scenario key."""
    msg = error_of(write(tmp_path, GOOD.replace("[0.0, 0.0, 1.0, 0.0]", "[0.0, 0.0, 1.0]")))
    assert "2 entries per axis: [x, y, vx, vy] in 2-D" in msg and "got 3 entries; 2 would be a 1-D target" in msg
    ring = GOOD + '\n[[nodes]]\nname = "c"\nsensor = "position"\nstd = 0.5\nrate = 5.0\n' \
        '\n[[links]]\nbetween = ["b", "c"]\n\n[[links]]\nbetween = ["c", "a"]\n'
    msg = error_of(write(tmp_path, ring, "ring.scenario.toml"))
    assert "not a tree: cycle" in msg and "set spanning_tree = true at the top of the scenario file" in msg
    assert "spanning_tree()" not in msg
    sc = load_scenario(write(tmp_path, "spanning_tree = true\n" + ring, "ring2.scenario.toml"))
    assert sc.graph.number_of_edges() == 2
