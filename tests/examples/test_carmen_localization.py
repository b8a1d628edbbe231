"""examples/carmen_localization.py on the first 160 scans of the Intel Research Lab log.

The slice (tests/data/carmen/intel-160scans.log.gz, source and citation in the README
there) holds the log's first 3,386 lines unchanged. Accuracy bounds are a little above
the values measured on it (docs/robots.md has the full-log results).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.examples import load_example

ROOT = Path(__file__).resolve().parents[2]
SLICE = ROOT / "tests" / "data" / "carmen" / "intel-160scans.log.gz"
EXAMPLE = ROOT / "examples" / "carmen_localization.py"
carmen = load_example("carmen_localization")


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("carmen") / "res.json"
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(SLICE), "--json", str(out), "--plot", str(out.parent)],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "MCL (likelihood field)" in proc.stdout and "ICP + odometry EKF" in proc.stdout
    for f in ("carmen_topdown.png", "carmen_errors.png"):
        assert (out.parent / f).stat().st_size > 20_000
    return json.loads(out.read_text())


def test_protocol(result):
    assert result["scans"] == 160
    assert result["map_scans"] == 80 and result["localized_scans"] == 80  # disjoint halves
    assert result["map"]["occupied_cells"] > 1000
    # the simulated odometry drifts by metres: the localizers have work to do
    assert result["odometry"]["rmse"] > 1.0


def test_series_give_the_table(result):
    """The per-scan series in the JSON reproduce the reported RMSE (computed here from them)."""
    ser = result["series"]
    truth = np.asarray(ser["truth"])[:, :2]
    for key in ("mcl", "scan_matching"):
        e = np.asarray(ser[key]["mean"])[:, :2] - truth
        assert float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) == pytest.approx(result[key]["rmse"], rel=1e-9)
        assert np.shape(ser[key]["cov"]) == (result["localized_scans"], 3, 3)


def test_accuracy(result):
    # measured: MCL 0.094 m / 0.0136 rad, scan matching 0.071 m / 0.0085 rad
    assert result["mcl"]["rmse"] < 0.12
    assert result["mcl"]["heading_rmse"] < 0.02
    assert result["scan_matching"]["rmse"] < 0.09
    assert result["scan_matching"]["heading_rmse"] < 0.012
    assert result["scan_matching"]["icp_failures"] == 0


def test_max_scans_and_noise_free_odometry():
    r = carmen.main([str(SLICE), "--max-scans", "3"])
    assert r == 1  # fewer than 6 scans: an error message, not a traceback
    rng = np.random.default_rng(0)
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.3], [1.05, 0.08, 0.9], [0.5, 0.5, -3.0]])
    np.testing.assert_allclose(carmen.noisy_odometry(poses, rng, scale=0.0), poses, atol=1e-12)
    noisy = carmen.noisy_odometry(poses, rng, scale=1.0)
    assert not np.allclose(noisy, poses)
