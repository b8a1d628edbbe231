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
    # measured: MCL 0.094 m / 0.0136 rad, scan matching 0.063 m / 0.0084 rad
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


def test_result_has_the_recovery_counts(result):
    for key in ("mcl", "scan_matching"):
        v = result[key]
        for field in ("recoveries", "gated", "alarms", "max_after", "ms_per_scan", "events"):
            assert field in v
        assert v["max_after"] < 1.0  # no lock-out on the slice
    # the events list the scans with a divergence alarm, each with what was done
    for ev in result["scan_matching"]["events"]:
        assert ev["status"] in ("recovered", "recovery_failed") and 0 <= ev["scan"] < result["localized_scans"]


def test_all_mode_tables_every_log_with_pooled_figures(tmp_path):
    """--all over a folder with two logs (the slice twice: the runs must agree) and two seeds."""
    folder = tmp_path / "logs"
    folder.mkdir()
    for name in ("a.log.gz", "b.log.gz"):
        (folder / name).write_bytes(SLICE.read_bytes())
    (folder / "notes.txt").write_text("not a log")
    out = tmp_path / "all.json"
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--all", str(folder), "--seeds", "0,1", "--max-scans", "60",
                           "--jobs", "2", "--json", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "pooled" in proc.stdout and "recov" in proc.stdout
    res = json.loads(out.read_text())
    runs = res["runs"]
    assert [(Path(r["log"]).name, r["seed"]) for r in runs] == [("a.log.gz", 0), ("a.log.gz", 1), ("b.log.gz", 0),
                                                              ("b.log.gz", 1)]
    assert runs[0]["mcl"]["rmse"] == runs[2]["mcl"]["rmse"]  # same log, same seed
    # worker processes give what one run in this process gives
    direct = carmen.run_log(folder / "a.log.gz", 1, max_scans=60)
    for key in ("mcl", "scan_matching"):
        assert runs[1][key]["rmse"] == direct[key]["rmse"]
    assert [row["log"] for row in res["per_log"]] == [r["log"] for r in runs[::2]]
    assert res["per_log"][0]["mcl"]["rmse_worst"] == max(runs[0]["mcl"]["rmse"], runs[1]["mcl"]["rmse"])
    n = sum(r["localized_scans"] for r in runs)
    for key in ("mcl", "scan_matching"):
        pool = res["pooled"][key]
        # pooled RMSE from the per-run RMSEs (independent of the pooled error arrays)
        ref = np.sqrt(sum(r[key]["rmse"] ** 2 * r["localized_scans"] for r in runs) / n)
        assert pool["rmse"] == pytest.approx(ref, rel=1e-9)
        assert pool["max_after"] == max(r[key]["max_after"] for r in runs)
        assert pool["recoveries"] == sum(r[key]["recoveries"] for r in runs)
    assert res["settings"]["icp"]["robust"] == "cauchy"


def test_all_mode_needs_logs(tmp_path, capsys):
    assert carmen.main(["--all", str(tmp_path)]) == 1
    assert "no CARMEN logs" in capsys.readouterr().err


def test_only_runs_one_localizer_with_the_same_numbers(tmp_path):
    """--only scan_matching: the scan matcher alone, its figures those of the run of both."""
    both = carmen.run_log(SLICE, 1, max_scans=60, series=False)
    alone = carmen.run_log(SLICE, 1, max_scans=60, series=False, only="scan_matching")
    assert "mcl" not in alone
    assert alone["scan_matching"]["rmse"] == both["scan_matching"]["rmse"]
    assert alone["scan_matching"]["max_after"] == both["scan_matching"]["max_after"]
    out = tmp_path / "only.json"
    folder = tmp_path / "logs"
    folder.mkdir()
    (folder / "a.log.gz").write_bytes(SLICE.read_bytes())
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--all", str(folder), "--seeds", "1", "--max-scans", "60",
                           "--only", "scan_matching", "--json", str(out)], capture_output=True, text=True, cwd=ROOT,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "ICP + odometry EKF" in proc.stdout and "MCL" not in proc.stdout
    res = json.loads(out.read_text())
    assert set(res["pooled"]) == {"scan_matching"}
    assert res["runs"][0]["scan_matching"]["rmse"] == both["scan_matching"]["rmse"]
    with pytest.raises(carmen.ValidationError, match="only must be"):
        carmen.run_log(SLICE, 1, max_scans=60, only="ekf")
