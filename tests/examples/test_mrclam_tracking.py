"""The MRCLAM reader and examples/mrclam_tracking.py on the 180 s slice in tests/data/mrclam.

Reader checks use independent parsing of the raw files; the example's accuracy bounds are
a little above the values measured on the slice (docs/robots.md has the full-dataset
results).
"""
from __future__ import annotations

import gzip
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dfusion.datasets import integrate_odometry, mean_velocities, read_mrclam
from dfusion.errors import ValidationError

ROOT = Path(__file__).resolve().parents[2]
SLICE = ROOT / "tests" / "data" / "mrclam"
EXAMPLE = ROOT / "examples" / "mrclam_tracking.py"


def raw_rows(name: str) -> list[list[float]]:
    with gzip.open(SLICE / (name + ".gz"), "rt") as fh:
        return [[float(v) for v in ln.split()] for ln in fh if ln.strip() and not ln.startswith("#")]


@pytest.fixture(scope="module")
def ds():
    return read_mrclam(SLICE)


def test_reader_converts_barcodes_and_times(ds):
    barcodes = {int(b): int(s) for s, b in (ln for ln in raw_rows_plain("Barcodes.dat"))}
    assert barcodes[5] == 1 and barcodes[14] == 2 and barcodes[63] == 6  # README table
    assert sorted(ds.landmarks) == list(range(6, 21))
    assert ds.t0 == pytest.approx(1248444175.103)
    assert 179.0 < ds.duration <= 180.0
    for n in range(1, 6):
        rows = raw_rows(f"Robot{n}_Measurement.dat")
        known = [r for r in rows if int(r[1]) in barcodes]
        r = ds.robots[n]
        assert r.meas_t.size == len(known)
        assert r.unknown_barcode_rows == len(rows) - len(known)
        assert set(np.unique(r.meas_subject)) <= set(range(1, 21))
        np.testing.assert_allclose(r.meas_range, [k[2] for k in known])
        np.testing.assert_array_equal(r.meas_subject, [barcodes[int(k[1])] for k in known])
        np.testing.assert_allclose(r.meas_t, np.array([k[0] for k in known]) - ds.t0, atol=1e-6)
        assert np.all(np.diff(r.gt_t) > 0) and np.all(np.abs(r.gt[:, 2]) <= math.pi)
    assert ds.robots[2].observations_of(1).size > 100  # robot 2 sees robot 1 in the slice


def raw_rows_plain(name: str):
    return [[float(v) for v in ln.split()] for ln in (SLICE / name).read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]


def test_reader_drops_unknown_barcodes_and_errors(tmp_path):
    for f in SLICE.iterdir():
        if f.name != "README.md":
            (tmp_path / f.name).write_bytes(f.read_bytes())
    p = tmp_path / "Robot4_Measurement.dat.gz"
    text = gzip.decompress(p.read_bytes()).decode()
    p.unlink()
    (tmp_path / "Robot4_Measurement.dat").write_text(text + "1248444300.000 \t 34 \t 2.0 \t 0.1\n")
    base = read_mrclam(SLICE).robots[4]
    assert base.unknown_barcode_rows == 3  # barcodes 34, 43, 50 in the slice (README: robot 4 has 3)
    ds = read_mrclam(tmp_path, duration=200.0)
    assert ds.robots[4].unknown_barcode_rows == 4
    assert ds.robots[4].meas_t.size == base.meas_t.size
    early = read_mrclam(tmp_path, duration=60.0).robots[4]
    assert early.meas_t.max() <= 60.0 and early.gt_t.max() <= 60.0 and early.odom_t.max() <= 60.0
    assert early.unknown_barcode_rows == int(np.sum(~np.isin(
        [int(r[1]) for r in raw_rows("Robot4_Measurement.dat") if r[0] - 1248444175.103 <= 60.0],
        [int(b) for _, b in raw_rows_plain("Barcodes.dat")])))
    with pytest.raises(ValidationError):
        read_mrclam(tmp_path / "missing")
    (tmp_path / "Robot5_Odometry.dat.gz").unlink()
    with pytest.raises(ValidationError, match="Robot5_Odometry"):
        read_mrclam(tmp_path)


def test_dead_reckoning_and_mean_velocities_against_fine_steps(ds):
    r = ds.robots[1]
    times = np.array([5.0, 20.0, 47.3, 90.0])
    got = integrate_odometry(r.odom_t, r.odom, r.gt[0], 0.0, times)
    # reference: Euler steps of 1 ms with the velocity valid at each step
    t = np.arange(0.0, 90.0, 1e-3)
    j = np.searchsorted(r.odom_t, t, side="right") - 1
    u = np.where(j[:, None] >= 0, r.odom[np.maximum(j, 0)], 0.0)
    th = r.gt[0, 2] + np.concatenate([[0.0], np.cumsum(u[:-1, 1] * 1e-3)])
    x = r.gt[0, 0] + np.concatenate([[0.0], np.cumsum(u[:-1, 0] * np.cos(th[:-1]) * 1e-3)])
    y = r.gt[0, 1] + np.concatenate([[0.0], np.cumsum(u[:-1, 0] * np.sin(th[:-1]) * 1e-3)])
    k = np.searchsorted(t, times - 1e-9)
    k = np.minimum(k, t.size - 1)
    np.testing.assert_allclose(got[:, 0], x[k], atol=5e-3)
    np.testing.assert_allclose(got[:, 1], y[k], atol=5e-3)
    edges = np.array([0.0, 13.0, 13.5, 40.0, 40.01, 90.0])
    mv = mean_velocities(r.odom_t, r.odom, edges)
    for a, b, m in zip(edges[:-1], edges[1:], mv):
        sel = (t >= a) & (t < b)
        np.testing.assert_allclose(m, u[sel].mean(axis=0), atol=2e-3)


@pytest.fixture(scope="module")
def example_runs(tmp_path_factory):
    """Both target models, run concurrently (two processes); the odometry run (the default)
    also writes the figures."""
    out = tmp_path_factory.mktemp("mrclam")
    flags = {"cv": ["--target-model", "cv"], "odometry": ["--plot", str(out / "fig")]}
    res = run_example_processes(out, flags, ("node robot2", "dead reckoning"))
    for f in ("mrclam_topdown.png", "mrclam_errors.png"):
        assert (out / "fig" / f).stat().st_size > 20_000
    return res


def run_example_processes(out: Path, commands: dict[str, list[str]], expect: tuple[str, ...]) -> dict:
    """Run the example on the slice once per entry of ``commands`` (extra arguments),
    concurrently; check the exit code and that ``expect`` is printed; return the JSONs."""
    procs = {}
    for name, extra in commands.items():
        js = out / f"{name}.json"
        procs[name] = (subprocess.Popen([sys.executable, str(EXAMPLE), str(SLICE), *extra, "--json", str(js)],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT), js)
    res = {}
    for name, (p, js) in procs.items():
        stdout, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr
        assert all(e in stdout for e in expect), stdout
        res[name] = json.loads(js.read_text())
    return res


def test_example_cv_target(example_runs):
    r = example_runs["cv"]
    assert r["target_model"] == "cv" and r["eval_points"] == 359
    assert set(r["nodes"]) == {"2", "3", "4", "5"}
    # measured on the slice: nodes 0.346-0.381 m, centralized 0.354, union 0.341, dead reckoning 0.551
    for o, v in r["nodes"].items():
        assert v["rmse"] < 0.42, (o, v)
        assert v["gap_to_centralized_tracking"] < 0.1
        assert v["messages"] > 100
    assert r["centralized"]["rmse"] < 0.40
    assert r["centralized_tracking"]["rmse"] < 0.38
    assert r["dead_reckoning"]["1"]["rmse"] == pytest.approx(0.551, abs=0.01)
    assert max(v["rmse"] for v in r["nodes"].values()) < 0.8 * r["dead_reckoning"]["1"]["rmse"]
    # self-localization (landmark EKF): measured 0.341, 0.097, 0.185, 0.182 m
    for o, bound in {"2": 0.40, "3": 0.13, "4": 0.23, "5": 0.23}.items():
        assert r["localization"][o]["rmse"] < bound
        assert r["localization"][o]["rmse"] < r["dead_reckoning"][o]["rmse"]


def test_example_odometry_target(example_runs):
    r = example_runs["odometry"]
    # the per-step series reproduce the reported RMSE; the figures are written
    ser = r["series"]
    for o, v in r["nodes"].items():
        e = np.asarray(ser["nodes"][o]["mean"]) - np.asarray(ser["truth"])
        assert float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) == pytest.approx(v["rmse"], rel=1e-9)
    assert r["target_model"] == "odometry" and r["eval_points"] == 359  # the default model
    # measured on the slice: nodes 0.216-0.228 m, joint EKF 0.184, union 0.204
    for o, v in r["nodes"].items():
        assert v["rmse"] < 0.27, (o, v)
        # far better than robot 1's dead reckoning, close to both centralized references
        assert v["rmse"] < 0.5 * r["dead_reckoning"]["1"]["rmse"]
        assert abs(v["rmse"] - r["centralized_tracking"]["rmse"]) < 0.05
        assert abs(v["rmse"] - r["centralized"]["rmse"]) < 0.06
        assert v["gap_to_centralized_tracking"] < 0.1
    assert r["centralized"]["rmse"] < 0.23
    assert r["centralized_tracking"]["rmse"] < 0.25


# --------------------------------------------------------------------------- perturbed copies
@pytest.fixture(scope="module")
def perturbed_runs(tmp_path_factory):
    """The three perturbed copies of the slice, and a stress copy (robot 1's own odometry
    x 1.2, which locks plain gating out) with and without the protection."""
    stress = ["--perturb", "odometry-scale", "--odometry-robot", "1", "--odometry-scale", "1.2"]
    cmds = {
        "perturbed": ["--perturb", "outliers", "gap", "odometry-scale", "--jobs", "2"],
        "stress": stress,
        "stress_plain": [*stress, "--no-robust"],
    }
    return run_example_processes(tmp_path_factory.mktemp("mrclam_perturbed"), cmds, ("x joint", "recov."))


def test_robust_tracking_on_perturbed_slices(example_runs, perturbed_runs):
    """On the slice the nodes are already 1.17-1.23x the joint EKF without perturbation
    (the joint EKF is unusually good in the first 180 s: docs/robots.md); what the slice
    can check honestly is that no perturbation makes the nodes fall further behind the
    joint EKF given the same perturbed data (measured: largest node / joint 1.233
    unperturbed, 1.226 outliers, 1.050 gap, 1.262 odometry scale) nor far off (at most
    0.28 m)."""
    none = example_runs["odometry"]
    assert none["robust"] is not None and none["perturbation"] == "none"   # robust by default
    base_ratio = max(v["rmse"] for v in none["nodes"].values()) / none["centralized"]["rmse"]
    runs = perturbed_runs["perturbed"]["runs"]
    assert set(runs) == {"outliers", "gap", "odometry-scale"}
    assert len(perturbed_runs["perturbed"]["summary"]) == 3 * 6   # 4 nodes and 2 references per run
    for kind, r in runs.items():
        assert r["perturbation"] == kind and r["robust"] is not None
        joint = r["centralized"]["rmse"]
        for o, v in r["nodes"].items():
            assert v["rmse"] / joint < base_ratio + 0.1, (kind, o, v["rmse"], joint)
            assert v["rmse"] < 0.32, (kind, o)
            assert 0.5 < v["anees"] < 50
    # the outliers are gated: at least half of the 10 % replaced sightings
    out = runs["outliers"]
    gated = sum(v["gated"] for v in out["nodes"].values())
    seen = sum(v["target"] for v in out["nodes"].values())
    assert gated >= 0.05 * seen
    assert out["centralized"]["gated"] >= 0.05 * out["centralized"]["target"]


def test_lockout_recovery_is_what_keeps_the_stressed_track(perturbed_runs):
    """Robot 1's odometry scaled by 1.2: with plain gating the nodes' fixes are gated out
    and the track drifts (measured 0.61-0.63 m, robot 3's node rejects 53 of 71 fixes);
    with the protection the nodes recover (measured 0.35-0.37 m, joint EKF 0.37 m). This
    test fails when the recovery is disabled."""
    good, plain = perturbed_runs["stress"], perturbed_runs["stress_plain"]
    assert plain["robust"] is None
    assert sum(v["lockouts"] for v in plain["nodes"].values()) >= 1          # detected, not recovered
    assert sum(v["recoveries"] for v in plain["nodes"].values()) == 0
    assert sum(v["recoveries"] for v in good["nodes"].values()) >= 1
    for o, v in good["nodes"].items():
        assert v["rmse"] < 0.45, (o, v["rmse"])
        assert v["rmse"] < 0.7 * plain["nodes"][o]["rmse"]
        assert v["rmse"] < 1.2 * good["centralized"]["rmse"]
    assert min(v["rmse"] for v in plain["nodes"].values()) > 0.5
