"""examples/indoor_localization.py end to end on the two-walk slice of site1-F1 (tests/data/indoor).

With two walks and two folds each walk is localized with a map and Weinberg gain from the other
one; there is no WiFi database (fingerprint calibration needs two training walks), so the radio
methods have no output and the fused network none either. PDR and the magnetic filter from the
true start run on both walks.
"""
from __future__ import annotations

import json

import numpy as np

from tests.helpers.examples import load_example

indoor = load_example("indoor_localization")


def test_indoor_example_runs_on_the_slice(tmp_path, capsys):
    from pathlib import Path

    data = Path(__file__).resolve().parents[1] / "data" / "indoor"
    out = tmp_path / "indoor.json"
    fig = tmp_path / "indoor.png"
    assert indoor.main([str(data), "--all", "--folds", "2", "--json", str(out), "--figure", str(fig)]) == 0
    table = capsys.readouterr().out
    for label in indoor.LABELS.values():
        assert label in table
    res = json.loads(out.read_text())["results"]
    assert [r["floor"] for r in res] == ["site1-F1"]
    rows = res[0]["rows"]
    n_eval = 6 + 6  # waypoints of both walks but each walk's first
    assert rows["pdr_true_start"]["n"] == n_eval and rows["magnetic_true_start"]["n"] == n_eval
    assert np.isfinite(rows["magnetic_true_start"]["mean"]) and rows["magnetic_true_start"]["mean"] < 6.0
    assert rows["wifi_knn"]["n"] == 0 and rows["wifi_knn"]["missing"] == n_eval and rows["wifi_knn"]["mean"] is None
    assert fig.is_file()


def test_localized_at_needs_every_later_error_within():
    assert indoor.localized_at([5.0, 1.0, 3.0, 1.0, 1.5], 2.0) == 3
    assert indoor.localized_at([None, 1.0], 2.0) == 1
    assert indoor.localized_at([1.0, 3.0], 2.0) is None
