"""Robot recordings in: the MRCLAM and CARMEN test slices written as ROS bags (ROS 2 MCAP,
ROS 2 sqlite3, ROS 1) with rosbags directly (tests/helpers/bags.py), read back by
dfusion.bags and run through the examples' pipelines.

The reference is the same pipeline on the direct dataset reader's result. MRCLAM: as
read (the reader's relative times are whole nanoseconds, as a header stamp's): the bag
gives the same floats and the estimates agree to 1e-12 (RMSE to 1e-10 relative). CARMEN:
holding what a ROS message can hold, ranges rounded to float32 and beam angles
``angle_min + i * angle_increment`` from float32 fields (``sensor_msgs/LaserScan``),
to 1e-9. Also for bags whose record order differs from the stamp order (header stamps
rule).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from dfusion.bags import carmen_from_bag, mrclam_from_bag, read_bag
from dfusion.datasets import read_carmen, read_landmarks, read_mrclam
from dfusion.datasets.carmen import LaserScan
from dfusion.geometry import wrap_angle
from tests.helpers.bags import FORMATS, SIGHTINGS_MSGDEF, carmen_records, mrclam_records, write_bag
from tests.helpers.examples import load_example

ROOT = Path(__file__).resolve().parents[2]
MRCLAM = ROOT / "tests" / "data" / "mrclam"
CARMEN = ROOT / "tests" / "data" / "carmen" / "intel-160scans.log.gz"
DURATION = 30.0
# (format, shuffle seed): every format, and bags whose record order differs from the stamp order
MRCLAM_CASES = [(fmt, None) for fmt in FORMATS] + [("mcap", 7)]
CARMEN_CASES = [(fmt, None) for fmt in FORMATS] + [("sqlite3", 9)]


def _ids(case):
    fmt, sh = case
    return fmt if sh is None else f"{fmt}-record-order-shuffled"


def _record_order_differs(path: Path, topic: str) -> bool:
    """Whether the record order (log time) of ``topic`` differs from its stamp order (read with rosbags)."""
    with AnyReader([path]) as r:
        stamps = []
        for conn, _, raw in r.messages(connections=[c for c in r.connections if c.topic == topic]):
            h = r.deserialize(raw, conn.msgtype).header
            stamps.append(h.stamp.sec * 10**9 + h.stamp.nanosec)
    return bool(np.any(np.diff(stamps) < 0))


# ----------------------------------------------------------------------------- MRCLAM

@pytest.fixture(scope="module")
def mrclam_reference():
    ex = load_example("mrclam_tracking")
    args = ex.build_parser().parse_args([str(MRCLAM), "--duration", str(DURATION)])
    ds = read_mrclam(MRCLAM, duration=DURATION)   # as read: its times are whole nanoseconds already
    return ex, args, ds, ex.run(args, ds)


@pytest.mark.parametrize("case", MRCLAM_CASES, ids=_ids)
def test_mrclam_bag_gives_the_readers_estimates(case, mrclam_reference, tmp_path):
    ex, args, ds, ref = mrclam_reference
    fmt, shuffle = case
    origin = int(round(ds.t0 * 1e9))
    bag = write_bag(tmp_path / f"mrclam_{fmt}", fmt, mrclam_records(ds, origin),
                    custom={"mrclam_msgs/msg/Sightings": SIGHTINGS_MSGDEF}, shuffle=shuffle)
    assert _record_order_differs(bag, "/robot3/odom") == (shuffle is not None)
    got = mrclam_from_bag(bag, read_landmarks(MRCLAM)[1])
    for n, r in ds.robots.items():
        g = got.robots[n]
        for f in ("gt_t", "odom_t", "odom", "meas_t", "meas_range", "meas_bearing"):   # the same floats
            np.testing.assert_array_equal(getattr(g, f), getattr(r, f), err_msg=f"robot {n} {f}")
        np.testing.assert_array_equal(g.meas_subject, r.meas_subject)
        np.testing.assert_allclose(wrap_angle(g.gt - r.gt), 0.0, atol=1e-9)
    bag_args = ex.build_parser().parse_args([str(MRCLAM), "--bag", str(bag), "--duration", str(DURATION)])
    res = ex.run(bag_args)
    a, b = ref["series"], res["series"]
    assert len(b["t"]) == len(a["t"]) > 50
    np.testing.assert_allclose(b["t"], a["t"], atol=1e-9)
    for o in a["nodes"]:   # 1e-12: only the ground truth's yaw goes through a quaternion
        for key in ("mean", "cov"):
            np.testing.assert_allclose(b["nodes"][o][key], a["nodes"][o][key], rtol=0, atol=1e-12)
            np.testing.assert_allclose(b["observers"][o][key], a["observers"][o][key], rtol=0, atol=1e-12)
    np.testing.assert_allclose(b["centralized"], a["centralized"], rtol=0, atol=1e-12)
    for o, v in ref["nodes"].items():
        assert res["nodes"][o]["target"] == v["target"]
        assert res["nodes"][o]["rmse"] == pytest.approx(v["rmse"], rel=1e-10, abs=0)
    assert sum(v["target"] for v in ref["nodes"].values()) > 10   # robot 1 is seen: the fusion has work


# ----------------------------------------------------------------------------- CARMEN

def _as_laser_scan_message(log, fov: float = math.pi):
    """The reader's log with float32 ranges and LaserScan's float32 angle fields."""
    for s in log.scans:
        n = s.ranges.size
        a = float(np.float32(-fov / 2)) + np.arange(n) * float(np.float32(fov / n))
        r = s.ranges.astype(np.float32).astype(np.float64)
        valid = np.isfinite(r) & (r > 0) & (r < float(np.float32(81.83)) - 1e-6)
        yield LaserScan(s.t, r, a, s.laser_pose.copy(), s.laser_pose.copy(), valid)


@pytest.fixture(scope="module")
def carmen_reference():
    ex = load_example("carmen_localization")
    args = ex.build_parser().parse_args([str(CARMEN), "--max-scans", "40"])
    log = read_carmen(CARMEN)
    log.scans = list(_as_laser_scan_message(log))
    return ex, args, log, ex.run(args, log)


@pytest.mark.parametrize("case", CARMEN_CASES, ids=_ids)
def test_carmen_bag_gives_the_readers_estimates(case, carmen_reference, tmp_path):
    ex, args, log, ref = carmen_reference
    fmt, shuffle = case
    bag = write_bag(tmp_path / f"carmen_{fmt}", fmt, carmen_records(read_carmen(CARMEN)), shuffle=shuffle)
    assert _record_order_differs(bag, "/odom") == (shuffle is not None)
    got = carmen_from_bag(bag)
    assert len(got.scans) == len(log.scans) == 160
    for s, r in zip(got.scans, log.scans):
        assert s.t == pytest.approx(r.t, abs=1e-9)
        np.testing.assert_array_equal(s.ranges, r.ranges)
        np.testing.assert_allclose(s.angles, r.angles, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(s.valid, r.valid)
        np.testing.assert_allclose(wrap_angle(s.laser_pose - r.laser_pose), 0.0, atol=1e-9)
    # the odometry stream: the same rows (the log has equal stamps with different poses,
    # whose order only the record order can tell)
    np.testing.assert_allclose(got.odom_t, log.odom_t, atol=1e-9)
    key = np.lexsort
    np.testing.assert_allclose(got.odom[key(got.odom.T)], log.odom[key(log.odom.T)], atol=1e-9)
    bag_args = ex.build_parser().parse_args(["--bag", str(bag), "--max-scans", "40"])
    res = ex.run(bag_args)
    for loc in ("mcl", "scan_matching"):
        for k in ("mean", "cov"):
            np.testing.assert_allclose(wrap_angle(np.subtract(res["series"][loc][k], ref["series"][loc][k])) if k == "mean"
                                       else np.subtract(res["series"][loc][k], ref["series"][loc][k]),
                                       0.0, rtol=0, atol=1e-9, err_msg=f"{loc} {k}")
        assert res[loc]["rmse"] == pytest.approx(ref[loc]["rmse"], abs=1e-9)
    assert ref["mcl"]["rmse"] < 0.2 and ref["scan_matching"]["rmse"] < 0.2   # the pipeline does localize


# ----------------------------------------------------------------------------- reader

def test_reader_orders_by_stamp_and_reports_topics(tmp_path):
    ds = read_mrclam(MRCLAM, duration=20.0)
    bag = write_bag(tmp_path / "b", "mcap", mrclam_records(ds, 10**18),
                    custom={"mrclam_msgs/msg/Sightings": SIGHTINGS_MSGDEF}, shuffle=3)
    b = read_bag(bag, topics=["/robot1/odom", "/robot2/odom"])
    stamps = [m.stamp_ns for m in b.messages]
    assert stamps == sorted(stamps) and {m.topic for m in b.messages} == {"/robot1/odom", "/robot2/odom"}
    assert len(b.messages) == ds.robots[1].odom_t.size + ds.robots[2].odom_t.size
    assert any(m.record_ns < p.record_ns for p, m in zip(b.messages, b.messages[1:]))   # late ones
    assert b.topics["/robot3/sightings"] == "mrclam_msgs/msg/Sightings"
    assert b.origin_ns == stamps[0] and b.seconds(stamps[-1]) == pytest.approx(ds.robots[2].odom_t[-1] - min(
        ds.robots[1].odom_t[0], ds.robots[2].odom_t[0]), abs=1e-9)
    from dfusion.errors import ValidationError
    with pytest.raises(ValidationError, match="no topic"):
        read_bag(bag, topics=["/nope"])
    with pytest.raises(ValidationError, match="no such bag"):
        read_bag(tmp_path / "missing.bag")
