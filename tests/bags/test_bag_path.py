"""The bag path, right and loud (issue 25): bags written with rosbags as a ROS user's
robot records them (tests/helpers/bags.py), each fault of the old bag path once.

* scan poses stamped 1 ms from their scans are matched by nearest stamp (not silently
  replaced by odometry poses); one stamped beyond the tolerance is refused in one line;
* a ``/scan_pose`` of type ``PoseWithCovarianceStamped`` is read as a pose;
* a Humble sqlite3 bag (no message definitions stored) with a custom type on a topic not
  asked for is read; the custom type itself is read with its ``.msg`` file given;
* the examples take topic options (``/base_scan``, MRCLAM topic patterns) and fold a
  laser mounted off the robot's centre in from ``/tf_static``.

The reference is the dataset reader's data (CARMEN: the scans' corrected poses; MRCLAM:
the reader's arrays), and for the mount the SE(2) composition written out here.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from dfusion.bags import carmen_from_bag, mrclam_from_bag
from dfusion.datasets import read_carmen, read_landmarks, read_mrclam
from dfusion.errors import ValidationError
from dfusion.geometry import wrap_angle
from tests.helpers.bags import (SIGHTINGS_MSGDEF, as_humble_sqlite3, carmen_records, mrclam_records, pose_msg,
                                write_bag)
from tests.helpers.examples import load_example

ROOT = Path(__file__).resolve().parents[2]
CARMEN = ROOT / "tests" / "data" / "carmen" / "intel-160scans.log.gz"
MRCLAM = ROOT / "tests" / "data" / "mrclam"
SCANS = 12


@pytest.fixture(scope="module")
def carmen_log():
    log = read_carmen(CARMEN)
    log.scans = log.scans[:SCANS]
    keep = log.odom_t <= log.scans[-1].t
    log.odom_t, log.odom, log.odom_vel = log.odom_t[keep], log.odom[keep], log.odom_vel[keep]
    return log


def _pwc(T, h, x, y, th):
    cov = np.zeros(36)
    cov[0] = cov[7] = 0.01
    cov[35] = 0.001
    return T.geometry_msgs__msg__PoseWithCovarianceStamped(
        header=h, pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x, y, th), covariance=cov))


def _shift_poses(records, offset_ns: int, pwc: bool):
    """``/scan_pose`` stamped ``offset_ns`` after its scan (a localizer's pose of the same
    instant, stamped by another clock), optionally as PoseWithCovarianceStamped."""
    out = []
    for topic, msgtype, st, build in records:
        if topic == "/scan_pose":
            if pwc:
                msgtype = "geometry_msgs/msg/PoseWithCovarianceStamped"
                p = build.__defaults__   # the (x, y, th) the helper bound
                build = (lambda T, h, x=p[0], y=p[1], th=p[2]: _pwc(T, h, x, y, th))
            st += offset_ns
        out.append((topic, msgtype, st, build))
    return out


@pytest.mark.parametrize("pwc", [False, True], ids=["PoseStamped", "PoseWithCovarianceStamped"])
def test_scan_poses_are_matched_by_nearest_stamp_within_the_tolerance(pwc, carmen_log, tmp_path):
    bag = write_bag(tmp_path / "near", "mcap", _shift_poses(carmen_records(carmen_log), 1_000_000, pwc))
    got = carmen_from_bag(bag)
    assert len(got.scans) == SCANS
    for s, r in zip(got.scans, carmen_log.scans):
        np.testing.assert_allclose(wrap_angle(s.laser_pose - r.laser_pose), 0.0, atol=1e-9)
    far = write_bag(tmp_path / "far", "mcap", _shift_poses(carmen_records(carmen_log), 50_000_000, pwc))
    with pytest.raises(ValidationError, match=r"no /scan_pose pose within 10 ms \(nearest 50\.000 ms away"):
        carmen_from_bag(far)
    assert len(carmen_from_bag(far, pose_tolerance=0.06).scans) == SCANS


def _sightings_record(t_ns: int):
    return ("/robot9/sightings", "mrclam_msgs/msg/Sightings", t_ns,
            lambda T, h: T.mrclam_msgs__msg__Sightings(header=h, subject=np.array([7], dtype=np.int32),
                                                       range=np.array([1.5]), bearing=np.array([0.1])))


def test_humble_sqlite3_bag_reads_only_the_topics_asked_for_and_takes_msg_files(carmen_log, tmp_path):
    # a CARMEN bag with a custom type on a topic the pipeline does not read
    recs = carmen_records(carmen_log) + [_sightings_record(int(carmen_log.scans[0].t * 1e9))]
    bag = as_humble_sqlite3(write_bag(tmp_path / "carmen_humble", "sqlite3", recs,
                                      custom={"mrclam_msgs/msg/Sightings": SIGHTINGS_MSGDEF}))
    got = carmen_from_bag(bag)
    for s, r in zip(got.scans, carmen_log.scans):
        np.testing.assert_allclose(wrap_angle(s.laser_pose - r.laser_pose), 0.0, atol=1e-9)
    # MRCLAM, whose sightings are a custom type: refused without its definition, read with its .msg file
    ds = read_mrclam(MRCLAM, duration=20.0)
    mbag = as_humble_sqlite3(write_bag(tmp_path / "mrclam_humble", "sqlite3", mrclam_records(ds, 10**18),
                                       custom={"mrclam_msgs/msg/Sightings": SIGHTINGS_MSGDEF}))
    landmarks = read_landmarks(MRCLAM)[1]
    with pytest.raises(ValidationError, match=r"stores no definition of mrclam_msgs/msg/Sightings; give its \.msg"):
        mrclam_from_bag(mbag, landmarks)
    msg = tmp_path / "share" / "mrclam_msgs" / "msg" / "Sightings.msg"
    msg.parent.mkdir(parents=True)
    msg.write_text(SIGHTINGS_MSGDEF)
    ex = load_example("mrclam_tracking")
    args = ex.build_parser().parse_args([str(MRCLAM), "--bag", str(mbag), "--msg", str(msg)])
    got = ex.load_dataset(args)
    for n, r in ds.robots.items():
        g = got.robots[n]
        for f in ("odom_t", "odom", "meas_t", "meas_range", "meas_bearing", "gt_t"):
            np.testing.assert_allclose(getattr(g, f), getattr(r, f), rtol=0, atol=1e-9, err_msg=f"robot {n} {f}")
        np.testing.assert_array_equal(g.meas_subject, r.meas_subject)


MOUNT = (0.25, -0.05, 0.1)   # the laser on the robot: 25 cm ahead, 5 cm to the right, turned 0.1 rad


def _base_of_laser(laser_pose):
    """The robot's pose whose laser, mounted at MOUNT, has ``laser_pose`` (SE(2), written out)."""
    mx, my, mt = MOUNT
    x, y, th = laser_pose
    tb = th - mt
    return x - (math.cos(tb) * mx - math.sin(tb) * my), y - (math.sin(tb) * mx + math.cos(tb) * my), tb


def _robot_records(log, first_ns: int):
    """As a robot records: scans on /base_scan in the laser's frame, poses of base_link, the mount on /tf_static."""
    out = []
    for topic, msgtype, st, build in carmen_records(log):
        if topic == "/scan":
            out.append(("/base_scan", msgtype, st,
                        lambda T, h, b=build: b(T, dataclasses.replace(h, frame_id="laser"))))
        elif topic == "/scan_pose":
            x, y, th = _base_of_laser(build.__defaults__)
            out.append(("/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", st,
                        lambda T, h, x=x, y=y, th=th: _pwc(T, h, x, y, th)))
        else:
            out.append((topic, msgtype, st, build))

    def tf(T, h):
        tr = T.geometry_msgs__msg__TransformStamped(
            header=dataclasses.replace(h, frame_id="base_link"), child_frame_id="laser",
            transform=T.geometry_msgs__msg__Transform(
                translation=T.geometry_msgs__msg__Vector3(x=MOUNT[0], y=MOUNT[1], z=0.3),
                rotation=T.geometry_msgs__msg__Quaternion(x=0.0, y=0.0, z=math.sin(MOUNT[2] / 2),
                                                          w=math.cos(MOUNT[2] / 2))))
        return T.tf2_msgs__msg__TFMessage(transforms=[tr])
    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", first_ns, tf))
    return out


def test_examples_take_topic_options_and_fold_the_laser_mount_in_from_tf(carmen_log, tmp_path):
    bag = write_bag(tmp_path / "robot", "mcap", _robot_records(carmen_log, int(carmen_log.odom_t[0] * 1e9)))
    ex = load_example("carmen_localization")
    args = ex.build_parser().parse_args(["--bag", str(bag), "--scan-topic", "/base_scan", "--pose-topic", "/amcl_pose"])
    got = ex.load_log(args)
    assert len(got.scans) == SCANS
    with pytest.raises(ValidationError, match=r"no topic '/scan_pose'.*\(--pose-topic none\)"):
        ex.load_log(ex.build_parser().parse_args(["--bag", str(bag), "--scan-topic", "/base_scan"]))
    for s, r in zip(got.scans, carmen_log.scans):
        np.testing.assert_allclose(wrap_angle(s.laser_pose - r.laser_pose), 0.0, atol=1e-9)
        assert np.max(np.abs(s.odom_pose[:2] - r.laser_pose[:2])) > 0.2   # the mount did matter
    # MRCLAM topics named as another robot's recorder names them
    ds = read_mrclam(MRCLAM, duration=20.0)
    renamed = [(t.replace("/robot", "/r").replace("/odom", "/odometry"), ty, st, b)
               for t, ty, st, b in mrclam_records(ds, 10**18)]
    mbag = write_bag(tmp_path / "mrclam", "mcap", renamed, custom={"mrclam_msgs/msg/Sightings": SIGHTINGS_MSGDEF})
    mex = load_example("mrclam_tracking")
    margs = mex.build_parser().parse_args([str(MRCLAM), "--bag", str(mbag), "--odom-topic", "/r{n}/odometry",
                                           "--sightings-topic", "/r{n}/sightings", "--truth-topic", "/r{n}/ground_truth"])
    got = mex.load_dataset(margs)
    for n, r in ds.robots.items():
        np.testing.assert_allclose(got.robots[n].odom, r.odom, rtol=0, atol=1e-12)
        assert got.robots[n].meas_t.size == r.meas_t.size and got.robots[n].gt_t.size == r.gt_t.size
