"""examples/global_localization_eval.py: the survey's protocol, on a quick setting."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.examples import load_example

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "global_localization_eval.py"
gle = load_example("global_localization_eval")


def test_score_follows_the_protocol():
    dist = np.arange(0.0, 12.01, 0.5)
    n = dist.size
    # correct from 3 m on (after a wrong convergence at 1 m): CLD 3 m, success
    pos = np.where(dist >= 3.0, 0.1, 5.0)
    pos[2] = 0.2
    r = gle.score(dist, pos, np.zeros(n))
    assert r["cld"] == pytest.approx(3.0) and r["success"] and r["error"] == pytest.approx(0.1)
    # heading wrong until 11 m: CLD 11 m > 10 m, a failure, although the position was right
    r = gle.score(dist, np.full(n, 0.1), np.where(dist >= 11.0, 0.0, 1.0))
    assert r["cld"] == pytest.approx(11.0) and not r["success"]
    # never correct: no CLD; the error is taken after 10 m
    pos = np.linspace(20.0, 1.0, n)
    r = gle.score(dist, pos, np.zeros(n))
    assert r["cld"] is None and not r["success"] and r["error"] == pytest.approx(pos[20])
    # correct from the start
    assert gle.score(dist, np.zeros(n), np.zeros(n))["cld"] == 0.0


def test_drive_stays_in_the_corridor():
    rng = np.random.default_rng(0)
    p = gle.drive(np.array([27.0, 1.0, 0.0]), 80, 30.0, rng)
    assert p[:, 0].min() >= 1.0 - 1e-9 and p[:, 0].max() <= 29.0 + 1e-9
    assert np.any(np.abs(np.diff(p[:, 2])) > 3.0)  # it turned round
    g = gle.make_map("repetitive")
    assert not g.is_blocked(p[:, :2]).any()


def test_quick_run(tmp_path):
    js, png = tmp_path / "g.json", tmp_path / "g.png"
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--quick", "--json", str(js), "--plot", str(png)],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "success" in proc.stdout and "CLD" in proc.stdout
    out = json.loads(js.read_text())
    assert set(out["results"]) == {"repetitive-30m", "corridor-8m"}
    for r in out["results"].values():
        assert len(r["tests"]) == 4 and len(r["success_rate_per_waypoint"]) == 2
        assert 0.0 <= r["success_rate"] <= 1.0
        assert r["success_rate"] == pytest.approx(np.mean([t["success"] for t in r["tests"]]))
        for t in r["tests"]:
            assert t["success"] == (t["cld"] is not None and t["cld"] <= 10.0)
            assert t["error"] >= 0
    assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
