"""Tests of the BLE RSSI dataset reader and of examples/ble_rssi_tracking.py on the slice in tests/data.

Expected values are the ones stated in the dataset's README (receiver table, node
counts); the baseline is checked against a plain per-row loop.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dfusion.datasets import BLERSSIDataset, find_dataset_root, read_track
from dfusion.localization import calibrate_path_loss, PathLossCalibration, weighted_centroid
from dfusion.metrics import error_stats
from dfusion.localization import calibrate_radio_map
from dfusion.errors import ValidationError
from dfusion.models import fit_path_loss, RSSISensor
from dfusion.localization import fit_radio_map, kernel_residual_map, RadioMap, WSNTracker

ROOT = Path(__file__).resolve().parents[2]
SLICE = ROOT / "tests" / "data" / "ble_rssi"
TRACK = SLICE / "trk" / "straight_03_all_sensors.mbd"
EXAMPLE = ROOT / "examples" / "ble_rssi_tracking.py"

# From the dataset README's receiver table.
README_RECEIVERS = {
    "sensor10": ("b827eb4521b4", 7.00, 7.09, 1.22), "sensor11": ("000000000101", 7.18, 0.68, 2.30),
    "sensor12": ("000000000102", 0.71, 6.16, 2.30), "sensor20": ("b827eb917e19", 7.25, 11.36, 1.22),
    "sensor21": ("000000000201", 0.76, 12.13, 2.30), "sensor22": ("000000000202", 7.18, 17.64, 2.30),
    "sensor30": ("b827ebf7d096", 13.14, 12.33, 1.22), "sensor31": ("000000000301", 12.82, 16.83, 2.30),
    "sensor32": ("000000000302", 18.12, 11.93, 2.30), "sensor40": ("b827ebfd7811", 13.01, 5.51, 1.22),
    "sensor41": ("000000000401", 17.77, 6.33, 2.30), "sensor42": ("000000000402", 12.76, 0.27, 2.30),
}


@pytest.fixture(scope="module")
def ds():
    return BLERSSIDataset(SLICE)


def test_receivers_match_the_readme(ds):
    assert len(ds.receivers) == 12
    for r in ds.receivers:
        mac, x, y, z = README_RECEIVERS[r.alias]
        assert r.mac == mac
        np.testing.assert_allclose(r.position, [x, y, z])
    assert list(ds.beacons) == ["e78f135624ce"]
    np.testing.assert_allclose(ds.limits, [0.0, 0.0, 20.660138018121128, 17.64103475472807])
    assert find_dataset_root(TRACK) == SLICE


def test_track_reader(ds):
    tr = ds.load_track("straight_03")
    assert tr.name == "straight_03" and len(tr) == 1061 and tr.n_dropped == 0
    assert tr.duration == pytest.approx(46.8, abs=0.05)
    assert np.all(np.diff(tr.t) >= 0) and np.all(tr.rssi < 0)
    assert tr.rssi.min() == -98 and tr.rssi.max() == -51  # README: -98 to -51 dBm
    assert set(np.unique(tr.receiver)) == set(range(12))
    counts = np.bincount(tr.receiver)
    assert counts.min() == 80 and counts.max() == 98  # README: 80-98 rows per receiver
    assert tr.truth[:, 1].min() == pytest.approx(-0.144, abs=1e-3)
    # the first data row of the file, parsed by hand
    first = TRACK.read_text().splitlines()[0].split(",")
    k = int(np.argmin(np.abs(tr.t - float(first[0]))))
    assert tr.rssi[k] == float(first[3])
    np.testing.assert_allclose(tr.truth[k], [float(v) for v in first[4:7]])


def test_track_pitfalls(tmp_path, ds):
    rows = [
        "1581249601.5,b827eb4521b4,e78f135624ce,-87,1.0,2.0,1.8,9,9,9,9,9,9,9,9,9",
        "1581249601.4,000000000101,e78f135624ce,-70,1.1,2.1,1.8,0,0,0,0,0,0,0,0,0",  # backwards in time
        "1581249601.6,b827ebf7d096,e78f135624ce,42,1.2,2.2,1.8,0,0,0,0,0,0,0,0,0",  # positive RSSI
        "1581249601.7,b827ebf7d096,e78f135624ce,-60,1.3,2.3,1.8,0,0,0,0,0,0,0,0,0",
    ]
    f = tmp_path / "x_all_sensors.mbd"
    f.write_text("\n".join(rows) + "\n")
    tr = read_track(f, ds.receiver_macs)
    assert tr.n_dropped == 1 and len(tr) == 3
    np.testing.assert_allclose(tr.t, [1581249601.4, 1581249601.5, 1581249601.7])
    np.testing.assert_array_equal(tr.rssi, [-70, -87, -60])
    np.testing.assert_array_equal(tr.receiver, [1, 0, 6])
    f.write_text(rows[0].replace("b827eb4521b4", "ffffffffffff") + "\n")
    with pytest.raises(ValidationError, match="unknown receiver"):
        read_track(f, ds.receiver_macs)


def test_occupancy_grid_of_the_slice(ds):
    g = ds.load_grid(0.2)
    assert g.shape == (105, 90)  # README: 105 x 90 nodes
    assert int(g.occupied.sum()) == 4401  # README: 4,401 nodes with value 1
    # value 1 = occupied: the border is occupied, 11 of the 12 receivers stand on 1-nodes
    assert g.occupied[0, :].all() and g.occupied[:, 0].all()
    assert int(g.is_occupied(ds.receiver_positions[:, :2]).sum()) == 11
    tr = ds.load_track("straight_03")
    assert g.is_free(tr.truth[:, :2]).mean() > 0.8
    with pytest.raises(ValidationError):
        ds.load_grid(0.1)  # not in the slice


def test_weighted_centroid_against_a_loop(ds):
    tr = ds.load_track("straight_03")
    pos = ds.receiver_positions
    got = weighted_centroid(tr, pos, window=2.0)
    for k in range(0, len(tr), 37):
        sel = np.zeros(len(tr), bool)
        sel[: k + 1] = True
        sel &= tr.t > tr.t[k] - 2.0
        num, den = np.zeros(2), 0.0
        for r in range(12):
            m = sel & (tr.receiver == r)
            if m.any():
                w = 10 ** (tr.rssi[m].mean() / 10)
                num += w * pos[r, :2]
                den += w
        np.testing.assert_allclose(got[k], num / den, rtol=1e-12)


def test_calibration_and_json_round_trip(ds):
    tr = ds.load_track("straight_03")
    cal = calibrate_path_loss([tr], ds.receiver_positions, ds.receiver_macs)
    j = 3
    sel = tr.receiver == j
    d = np.linalg.norm(tr.truth[sel] - ds.receiver_positions[j], axis=1)
    np.testing.assert_allclose([cal.p0[j], cal.exponent[j], cal.std[j]], fit_path_loss(d, tr.rssi[sel]))
    back = PathLossCalibration.from_json(json.loads(json.dumps(cal.to_json())), ds.receiver_macs)
    np.testing.assert_allclose(back.p0, cal.p0)
    np.testing.assert_allclose(back.exponent, cal.exponent)
    assert back.height == pytest.approx(tr.truth[:, 2].mean())
    sensors = back.sensors(ds.receiver_positions)
    assert len(sensors) == 12 and sensors[j].p0 == pytest.approx(cal.p0[j])
    stored = PathLossCalibration.from_json(json.loads((SLICE / "path_loss.json").read_text()), ds.receiver_macs)
    assert "straight_03" not in stored.tracks and len(stored.tracks) == 4


def test_error_stats():
    e = np.array([3.0, 4.0, 0.0, 1.0])
    s = error_stats(e)
    assert s["rmse"] == pytest.approx(np.sqrt(26 / 4)) and s["median_error"] == pytest.approx(2.0)


def test_example_beats_the_baseline_on_the_slice(tmp_path):
    out = tmp_path / "res.json"
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(TRACK), "--particles", "2000", "--json", str(out),
                           "--plot", str(tmp_path / "fig")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "straight_03" in proc.stdout and "PF RMSE" in proc.stdout
    res = json.loads(out.read_text())
    for f in ("ble_straight_03_topdown.png", "ble_straight_03_errors.png"):
        assert (tmp_path / "fig" / f).stat().st_size > 20_000
    ser = res["series"]["straight_03"]   # the per-packet series: its errors give the reported RMSE
    err = np.linalg.norm(np.subtract(ser["mean"], ser["truth"]), axis=1)
    assert float(np.sqrt(np.mean(err**2))) == pytest.approx(res["rmse"], rel=1e-9)
    assert np.shape(ser["cov"]) == (res["rows"], 2, 2)
    for key in ("rmse", "median_error", "baseline_rmse"):
        assert np.isfinite(res[key]) and res[key] > 0
    assert res["model"] == "radio-map"  # the default, from the shipped radio_map.npz
    assert res["calibration_tracks"] and "straight_03" not in res["calibration_tracks"]
    assert res["rmse"] < res["baseline_rmse"]
    # the shipped split-normal directional map: 1.96-1.97 m against 3.31 m over seeds 0-2 (0.59-0.60)
    assert res["rmse"] < 0.7 * res["baseline_rmse"]
    assert res["median_error"] < 1.5


def test_example_refuses_to_run_without_an_out_of_sample_calibration(tmp_path):
    d = tmp_path / "ds"
    shutil.copytree(SLICE, d)
    (d / "path_loss.json").unlink()
    (d / "radio_map.npz").unlink()
    for model in ("radio-map", "path-loss"):
        proc = subprocess.run([sys.executable, str(EXAMPLE), str(d / "trk" / TRACK.name), "--model", model],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and "calibration" in proc.stderr
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--all"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0  # no dataset directory given


# ----------------------------------------------------------------------------- radio map


def _synthetic_training(rng, n=600):
    """Two receivers, points along two crossing aisles, residual = smooth bump + noise."""
    t = rng.uniform(0, 1, n)
    pts = np.where((np.arange(n) % 2 == 0)[:, None], np.column_stack([1 + 8 * t, 4 + 0.1 * rng.standard_normal(n)]),
                   np.column_stack([5 + 0.1 * rng.standard_normal(n), 0.5 + 7 * t]))
    j = rng.integers(0, 2, n)
    bump = 6.0 * np.exp(-((pts[:, 0] - 4) ** 2 + (pts[:, 1] - 4) ** 2) / 4.0) * np.where(j == 0, 1.0, -1.0)
    return pts, j, bump + rng.standard_normal(n) * np.where(j == 0, 2.0, 3.0)


def _base(j, xy):
    rec = np.array([[2.0, 2.0], [8.0, 6.0]])
    d = np.hypot(xy[:, 0] - rec[j, 0], xy[:, 1] - rec[j, 1])
    return -55.0 - 20.0 * np.log10(np.maximum(d, 0.5))


def test_radio_map_lookup_equals_the_direct_kernel_formula():
    rng = np.random.default_rng(3)
    pts, j, res = _synthetic_training(rng)
    z = np.array([_base(jj, p[None])[0] for jj, p in zip(j, pts)]) + res
    s0 = np.array([4.0, 5.0])
    kw = dict(cell=0.2, bandwidth=1.0, prior_weight=0.05)
    rm = fit_radio_map(pts, j, z, _base, s0, origin=(0.0, 0.0), shape=(51, 46), tracks=["a"], **kw)
    q = rng.uniform([0.5, 0.5], [9.5, 8.5], (400, 2))
    # 1 m or more from the receivers, where the log-distance term is smooth at the 0.2 m scale
    q = q[(np.hypot(q[:, 0] - 2, q[:, 1] - 2) > 1) & (np.hypot(q[:, 0] - 8, q[:, 1] - 6) > 1)]
    for r in range(2):
        sel = j == r
        m_dir, s_dir = kernel_residual_map(q, pts[sel], res[sel], s0[r], **kw)
        mean, std = rm.lookup(q, [r])
        # binning moves a point by at most 0.14 m (1/7 of the bandwidth), bilinear look-up at 0.2 m
        np.testing.assert_allclose(mean[:, 0], _base(r, q) + m_dir, atol=0.3)
        np.testing.assert_allclose(std[:, 0], s_dir, atol=0.3)
        assert np.max(np.abs(m_dir)) > 3.0  # the bump is learnt, not a trivial zero map
    # far from every training point: back to the base model
    far = np.array([[0.2, 8.8], [9.8, 8.8]])
    mean, std = rm.lookup(far, [0, 1])
    np.testing.assert_allclose(mean, np.column_stack([_base(0, far), _base(1, far)]), atol=0.05)
    np.testing.assert_allclose(std, np.tile(s0, (2, 1)), atol=0.05)


def test_radio_map_log_likelihood_against_a_gaussian():
    rng = np.random.default_rng(4)
    pts, j, res = _synthetic_training(rng)
    z = np.array([_base(jj, p[None])[0] for jj, p in zip(j, pts)]) + res
    rm = fit_radio_map(pts, j, z, _base, np.array([4.0, 5.0]), origin=(0.0, 0.0), cell=0.2, shape=(51, 46))
    zr, jr = np.array([-70.0, -63.0, -80.0]), np.array([0, 1, 0])
    # at nodes the bilinear look-up is exact: the Gaussian log-density (up to a constant)
    nodes = np.column_stack([0.2 * rng.integers(0, 51, 50), 0.2 * rng.integers(0, 46, 50)])
    ix, iy = np.rint(nodes / 0.2).astype(int).T
    M, S = rm.mean[jr][:, ix, iy].T, rm.std[jr][:, ix, iy].T
    ref = (-0.5 * ((zr - M) / S) ** 2 - np.log(S)).sum(axis=1)
    np.testing.assert_allclose(rm.log_likelihood(zr, jr, nodes), ref, rtol=1e-10, atol=1e-9)
    for s in (1.0, 1.7):
        np.testing.assert_allclose(rm.log_likelihood(zr, jr, nodes, std_scale=s),
                                   (-0.5 * ((zr - M) / (s * S)) ** 2 - np.log(S)).sum(axis=1), rtol=1e-10)
    # between nodes: close to the Gaussian with interpolated mean and std
    q = rng.uniform([0.5, 0.5], [9.5, 8.5], (200, 2))
    M, S = rm.lookup(q, jr)
    ref = (-0.5 * ((zr - M) / S) ** 2 - np.log(S)).sum(axis=1)
    np.testing.assert_allclose(rm.log_likelihood(zr, jr, q), ref, rtol=0.01, atol=0.05)


def test_tracker_with_a_plain_path_loss_map_matches_the_annulus(ds):
    cal = PathLossCalibration.from_json(json.loads((SLICE / "path_loss.json").read_text()), ds.receiver_macs)
    pos = ds.receiver_positions
    # bandwidth 0: the map is the log-distance model sampled on the 0.2 m nodes
    rm = fit_radio_map(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), lambda j, xy: cal.mean_rssi(j, xy, pos),
                       cal.std, origin=(0, 0), cell=0.2, shape=(105, 90), bandwidth=0.0)
    a = WSNTracker(cal.sensors(pos), 3000, bounds=ds.limits, seed=1)
    b = WSNTracker(RSSISensor(pos, -60.0, 2.0, 5.0), 3000, bounds=ds.limits, seed=1, radio_map=rm)
    a.initialize()
    b.initialize()
    x = a.particles
    x = x[np.min(np.hypot(x[:, None, 0] - pos[:, 0], x[:, None, 1] - pos[:, 1]), axis=1) > 0.5]
    z, jr = np.array([-75.0, -62.0, -88.0]), np.array([3, 7, 11])
    la = a.log_likelihood(z, jr, particles=x)
    lb = b.log_likelihood(z, jr, particles=x) + np.log(cal.std[jr]).sum()
    assert np.ptp(la) > 20  # informative readings
    np.testing.assert_allclose(lb, la, atol=0.05 * np.ptp(la))
    np.testing.assert_allclose(np.exp(lb - lb.max()), np.exp(la - la.max()), atol=0.02)


def test_radio_map_npz_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    rm = RadioMap((0.0, 0.2), 0.2, rng.normal(-70, 8, (3, 6, 5)), rng.uniform(2, 7, (3, 6, 5)), ["x", "y"])
    rm.to_npz(tmp_path / "m.npz")
    back = RadioMap.from_npz(tmp_path / "m.npz")
    np.testing.assert_allclose(back.mean, rm.mean, atol=0.0051)
    np.testing.assert_allclose(back.std, rm.std, atol=0.0051)
    np.testing.assert_allclose(back.origin, rm.origin)
    assert back.tracks == ["x", "y"] and back.cell == 0.2


def test_radio_map_calibration_never_sees_the_evaluated_track(tmp_path, ds, monkeypatch):
    tr = ds.load_track("straight_03")
    with pytest.raises(ValidationError, match="evaluated track"):
        calibrate_radio_map([tr], ds.receiver_positions, ds.receiver_macs, limits=ds.limits, exclude="straight_03")
    # a dataset with two tracks: the map for one is learnt from the other only
    d = tmp_path / "ds"
    shutil.copytree(SLICE, d)
    rows = TRACK.read_text().splitlines()
    (d / "trk" / "mirror_all_sensors.mbd").write_text("\n".join(rows[::2]) + "\n")
    import importlib.util
    spec = importlib.util.spec_from_file_location("ble_example", EXAMPLE)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    seen: list[list[str]] = []
    real = ex.calibrate_radio_map

    def spy(tracks, *a, **kw):
        seen.append([t.name for t in tracks])
        return real(tracks, *a, **kw)

    monkeypatch.setattr(ex, "calibrate_radio_map", spy)
    dd = BLERSSIDataset(d)
    res = ex.evaluate_track(dd, d / "trk" / TRACK.name, particles=300)
    assert seen == [["mirror"]] and res["calibration_tracks"] == ["mirror"]
    res = ex.evaluate_track(dd, d / "trk" / "mirror_all_sensors.mbd", particles=300)
    assert seen[-1] == ["straight_03"]
    # the shipped map and a map file listing the evaluated track
    shipped = RadioMap.from_npz(SLICE / "radio_map.npz")
    assert len(shipped.tracks) == 4 and "straight_03" not in shipped.tracks
    bad = tmp_path / "bad.npz"
    RadioMap(shipped.origin, shipped.cell, shipped.mean, shipped.std, ["straight_03"]).to_npz(bad)
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(TRACK), "--radio-map", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "in-sample" in proc.stderr


def test_example_path_loss_model_beats_the_baseline_on_the_slice(tmp_path):
    out = tmp_path / "res.json"
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(TRACK), "--particles", "2000", "--model", "path-loss",
                           "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(out.read_text())
    assert res["model"] == "path-loss" and "straight_03" not in res["calibration_tracks"]
    assert res["rmse"] < 0.9 * res["baseline_rmse"]


# ----------------------------------------------------------------------------- directional path loss, selection


def _pieces(tr, k=3):
    """``k`` interleaved sub-tracks of one track (every k-th row), as separate calibration tracks."""
    from dfusion.datasets import Track
    return [Track(f"{tr.name}_{i}", tr.t[i::k], tr.receiver[i::k], tr.rssi[i::k], tr.truth[i::k]) for i in range(k)]


def _synthetic_tracks(ds, rng, n_tracks=3, rows=900):
    """Tracks along random aisles of the slice's area whose RSSI has a strong azimuthal gain."""
    from dfusion.datasets import Track
    pos = ds.receiver_positions
    out = []
    for i in range(n_tracks):
        a, b = rng.uniform([1, 1], [19, 16], (2, 2))
        s = np.linspace(0, 1, rows)
        xy = a + s[:, None] * (b - a) + rng.normal(0, 0.1, (rows, 2))
        j = rng.integers(0, 12, rows)
        d = np.sqrt(((xy - pos[j, :2]) ** 2).sum(1) + (1.8 - pos[j, 2]) ** 2)
        phi = np.arctan2(xy[:, 1] - pos[j, 1], xy[:, 0] - pos[j, 0])
        z = -60 - 20 * np.log10(d) + 6 * np.cos(phi + j) + 3 * np.sin(2 * phi) + rng.normal(0, 3, rows)
        out.append(Track(f"syn{i}", np.arange(rows) * 0.04, j, z, np.column_stack([xy, np.full(rows, 1.8)])))
    return out


def test_directional_path_loss_calibration(ds):
    from dfusion.localization import fit_directional_path_loss, path_loss_design
    tr = ds.load_track("straight_03")
    pos = ds.receiver_positions
    cal = calibrate_path_loss([tr], pos, ds.receiver_macs, order=2, ridge=50.0)
    assert cal.order == 2 and cal.harmonics.shape == (12, 4) and cal.ridge == 50.0
    j = 6
    sel = tr.receiver == j
    d = np.linalg.norm(tr.truth[sel] - pos[j], axis=1)
    phi = np.arctan2(tr.truth[sel, 1] - pos[j, 1], tr.truth[sel, 0] - pos[j, 0])
    p0, n, h, s = fit_directional_path_loss(d, phi, tr.rssi[sel], 2, 50.0)
    np.testing.assert_allclose([cal.p0[j], cal.exponent[j], cal.std[j], *cal.harmonics[j]], [p0, n, s, *h])
    # mean_rssi at the calibration height, by the formula
    q = np.array([[3.0, 4.0], [15.0, 2.5]])
    dq = np.sqrt(((q - pos[j, :2]) ** 2).sum(1) + (cal.height - pos[j, 2]) ** 2)
    pq = np.arctan2(q[:, 1] - pos[j, 1], q[:, 0] - pos[j, 0])
    ref = (p0 - 10 * n * np.log10(dq) + h[0] * np.cos(pq) + h[1] * np.sin(pq) + h[2] * np.cos(2 * pq)
           + h[3] * np.sin(2 * pq))
    np.testing.assert_allclose(cal.mean_rssi(j, q, pos), ref)
    np.testing.assert_allclose(path_loss_design(dq, pq, 2)[:, 2:] @ h, ref - p0 + 10 * n * np.log10(dq))
    back = PathLossCalibration.from_json(json.loads(json.dumps(cal.to_json())), ds.receiver_macs)
    np.testing.assert_allclose(back.harmonics, cal.harmonics)
    np.testing.assert_allclose(back.mean_rssi(j, q, pos), ref)
    with pytest.raises(ValidationError, match="directional"):
        cal.sensors(pos)  # an RSSISensor has no directional gain
    with pytest.raises(ValidationError):
        calibrate_path_loss([tr], pos, ds.receiver_macs, per_receiver=False, order=1)
    # order 0 is unchanged: the plain fit_path_loss per receiver
    cal0 = calibrate_path_loss([tr], pos, ds.receiver_macs)
    assert cal0.order == 0 and "harmonics" not in json.dumps(cal0.to_json())
    np.testing.assert_allclose([cal0.p0[j], cal0.exponent[j], cal0.std[j]], fit_path_loss(d, tr.rssi[sel]))


def test_held_out_residuals_and_split_noise_calibration(ds):
    from dfusion.localization import held_out_residuals, held_out_score
    from dfusion.localization import fit_split_normal, split_normal_logpdf
    parts = _pieces(ds.load_track("straight_03"))
    pos, macs = ds.receiver_positions, ds.receiver_macs
    st = dict(order=1, ridge=30.0, bandwidth=0.8, prior_weight=0.1)
    (u, S), = held_out_residuals(parts, pos, macs, limits=ds.limits, settings=[st])
    # by hand: each piece predicted by the map of the two others
    us, ss = [], []
    for i, t in enumerate(parts):
        rm, _ = calibrate_radio_map(parts[:i] + parts[i + 1:], pos, macs, limits=ds.limits, order=1, ridge=30.0,
                                    bandwidth=0.8, prior_weight=0.1, exclude=t.name)
        M, Sd = rm.lookup(t.truth[:, :2], np.arange(12))
        k = np.arange(len(t))
        us.append((t.rssi - M[k, t.receiver]) / Sd[k, t.receiver])
        ss.append(Sd[k, t.receiver])
    np.testing.assert_allclose(u, np.concatenate(us))
    np.testing.assert_allclose(S, np.concatenate(ss))
    # scores: mean held-out log-density per reading
    sc, law = held_out_score(u, S, "split-normal")
    assert law == pytest.approx(fit_split_normal(u))
    assert sc == pytest.approx(np.mean(split_normal_logpdf(u, *law) - np.log(S)))
    sg, none = held_out_score(u, S, "gaussian")
    assert none is None and sg == pytest.approx(np.mean(stats_norm_logpdf(u) - np.log(S)))
    assert sc > sg  # the residuals are skewed: the split normal predicts them better
    # calibrate_radio_map(noise="split-normal") stores exactly that law
    rm, cal = calibrate_radio_map(parts, pos, macs, limits=ds.limits, noise="split-normal", **st)
    assert rm.noise == pytest.approx(law) and cal.order == 1
    assert rm.settings["bandwidth"] == 0.8 and rm.settings["order"] == 1
    with pytest.raises(ValidationError):
        calibrate_radio_map(parts[:1], pos, macs, limits=ds.limits, noise="split-normal")
    with pytest.raises(ValidationError):
        calibrate_radio_map(parts, pos, macs, limits=ds.limits, noise="student")


def stats_norm_logpdf(u):
    from scipy.stats import norm
    return norm.logpdf(u)


def test_select_radio_map_settings(ds):
    from dfusion.localization import held_out_residuals, held_out_score, select_radio_map_settings
    rng = np.random.default_rng(12)
    tracks = _synthetic_tracks(ds, rng)
    pos, macs = ds.receiver_positions, ds.receiver_macs
    grid = {"order": (0, 2), "ridge": (10.0,), "bandwidth": (1.0, 2.0), "prior_weight": (0.05,)}
    best, table = select_radio_map_settings(tracks, pos, macs, limits=ds.limits, grid=grid)
    assert len(table) == 4 and best["order"] == 2  # the data have a directional gain
    # every score is the held-out score of its setting, and the best is the maximum
    for st, sc in table:
        (u, S), = held_out_residuals(tracks, pos, macs, limits=ds.limits, settings=[st])
        assert sc == pytest.approx(held_out_score(u, S)[0])
    assert best["score"] == max(sc for _, sc in table)
    with pytest.raises(ValidationError, match="evaluated track"):
        select_radio_map_settings(tracks, pos, macs, limits=ds.limits, grid=grid, exclude="syn1")
    with pytest.raises(ValidationError):
        select_radio_map_settings(tracks[:1], pos, macs, limits=ds.limits, grid=grid)


def test_example_selects_map_settings_without_the_evaluated_track(tmp_path, ds, monkeypatch):
    """With three tracks, each evaluation selects and calibrates on the two others only."""
    d = tmp_path / "ds"
    shutil.copytree(SLICE, d)
    (d / "radio_map.npz").unlink()
    rows = TRACK.read_text().splitlines()
    (d / "trk" / "odd_all_sensors.mbd").write_text("\n".join(rows[1::2]) + "\n")
    (d / "trk" / "third_all_sensors.mbd").write_text("\n".join(rows[::3]) + "\n")
    import importlib.util
    spec = importlib.util.spec_from_file_location("ble_example", EXAMPLE)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    seen: list[tuple[str, list[str]]] = []
    real_sel, real_cal = ex.select_radio_map_settings, ex.calibrate_radio_map

    def spy_sel(tracks, *a, **kw):
        seen.append(("select", [t.name for t in tracks]))
        return real_sel(tracks, *a, **kw)

    def spy_cal(tracks, *a, **kw):
        seen.append(("calibrate", [t.name for t in tracks]))
        return real_cal(tracks, *a, **kw)

    monkeypatch.setattr(ex, "select_radio_map_settings", spy_sel)
    monkeypatch.setattr(ex, "calibrate_radio_map", spy_cal)
    monkeypatch.setattr(ex, "MAP_SETTINGS_GRID", {"order": (0, 1), "ridge": (100.0,), "bandwidth": (1.0,),
                                                  "prior_weight": (0.05, 0.2)})
    dd = BLERSSIDataset(d)
    res = ex.evaluate_track(dd, d / "trk" / TRACK.name, particles=300)
    assert seen == [("select", ["odd", "third"]), ("calibrate", ["odd", "third"])]
    st = res["map_settings"]
    assert st["how"] == "selected" and st["order"] in (0, 1) and st["prior_weight"] in (0.05, 0.2)
    assert len(st["noise"]) == 3 and res["calibration_tracks"] == ["odd", "third"]
    # fixed settings: nothing to select, the noise law is still fitted out of sample
    seen.clear()
    res = ex.evaluate_track(dd, d / "trk" / "odd_all_sensors.mbd", particles=300, map_order=1, map_ridge=30.0,
                            map_bandwidth=0.8, map_prior_weight=0.1)
    assert [names for _, names in seen] == [["straight_03", "third"]] * 2
    assert res["map_settings"]["how"] == "given" and res["map_settings"]["bandwidth"] == 0.8
