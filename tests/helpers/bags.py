"""Write ROS bags from the test data with rosbags directly (not with dfusion's code).

``FORMATS``: ROS 2 MCAP, ROS 2 sqlite3, ROS 1. ``write_bag`` takes records
``(topic, msgtype, stamp_ns, build)`` where ``build(types, header)`` returns the message
(``types`` the typestore's classes, ``header`` a ``std_msgs/Header`` with the stamp).
Record times are the stamps plus 5 ms; with ``shuffle`` (a seed) they are the stamps
plus random delays of 0-3 s, so that the record order (the order a recorder writes, by
record time) differs from the stamp order: a message often reaches the bag after
messages taken up to 3 s later.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

FORMATS = ("mcap", "sqlite3", "ros1")

Record = tuple[str, str, int, Callable[[Any, Any], Any]]


def typestore(fmt: str, custom: dict[str, str] | None = None):
    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    for name, msgdef in (custom or {}).items():
        ts.register(get_types_from_msg(msgdef, name))
    return ts


class _Types:
    def __init__(self, ts):
        self._ts = ts

    def __getattr__(self, name):   # types.geometry_msgs__msg__Pose -> the class
        return self._ts.types[name.replace("__", "/")]


def write_bag(path: Path, fmt: str, records: list[Record], *, custom: dict[str, str] | None = None,
              shuffle: int | None = None, record_ns: list[int] | None = None) -> Path:
    """Write ``records``; ``record_ns`` gives each record's record time (default: see above)."""
    ts = typestore(fmt, custom)
    types = _Types(ts)
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    rec_ns = list(record_ns) if record_ns is not None else [r[2] + 5_000_000 for r in records]
    if shuffle is not None:
        rng = np.random.default_rng(shuffle)
        rec_ns = [r[2] + int(rng.integers(0, 3_000_000_000)) for r in records]
    order = sorted(range(len(records)), key=lambda i: rec_ns[i])   # a recorder writes in record order
    if fmt == "ros1":
        path = path.with_suffix(".bag")
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
    seq = 0
    with writer:
        conns = {}
        for topic, msgtype, _, _ in records:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for i in order:
            topic, msgtype, st, build = records[i]
            stamp = Time(sec=st // 1_000_000_000, nanosec=st % 1_000_000_000)
            if fmt == "ros1":
                header = Header(seq=seq, stamp=stamp, frame_id="map")
                seq += 1
            else:
                header = Header(stamp=stamp, frame_id="map")
            msg = build(types, header)
            data = ts.serialize_ros1(msg, msgtype) if fmt == "ros1" else ts.serialize_cdr(msg, msgtype)
            writer.write(conns[topic], rec_ns[i], data)
    return path


def pose_msg(types, x: float, y: float, yaw: float):
    P = types.geometry_msgs__msg__Pose
    return P(position=types.geometry_msgs__msg__Point(x=float(x), y=float(y), z=0.0),
             orientation=types.geometry_msgs__msg__Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw),
                                                              w=math.cos(0.5 * yaw)))


def twist_msg(types, v: float, w: float):
    V = types.geometry_msgs__msg__Vector3
    return types.geometry_msgs__msg__Twist(linear=V(x=float(v), y=0.0, z=0.0), angular=V(x=0.0, y=0.0, z=float(w)))


def ns(t: float, origin_ns: int = 0) -> int:
    return origin_ns + int(round(t * 1e9))


SIGHTINGS_MSGDEF = """std_msgs/Header header
int32[] subject
float64[] range
float64[] bearing
"""


def mrclam_records(ds, origin_ns: int) -> list[Record]:
    """MRCLAM as TwistStamped odometry, PoseStamped ground truth and one Sightings message
    per robot and time stamp (everything one camera frame saw)."""
    out: list[Record] = []
    for n, r in ds.robots.items():
        for t, (v, w) in zip(r.odom_t, r.odom):
            out.append((f"/robot{n}/odom", "geometry_msgs/msg/TwistStamped", ns(t, origin_ns),
                        lambda T, h, v=v, w=w: T.geometry_msgs__msg__TwistStamped(header=h, twist=twist_msg(T, v, w))))
        for t, (x, y, th) in zip(r.gt_t, r.gt):
            out.append((f"/robot{n}/ground_truth", "geometry_msgs/msg/PoseStamped", ns(t, origin_ns),
                        lambda T, h, x=x, y=y, th=th: T.geometry_msgs__msg__PoseStamped(header=h,
                                                                                       pose=pose_msg(T, x, y, th))))
        ts, first = np.unique(r.meas_t, return_index=True)
        bounds = list(first) + [r.meas_t.size]
        for k, t in enumerate(ts):
            sl = slice(bounds[k], bounds[k + 1])
            s, rr, b = r.meas_subject[sl], r.meas_range[sl], r.meas_bearing[sl]
            out.append((f"/robot{n}/sightings", "mrclam_msgs/msg/Sightings", ns(t, origin_ns),
                        lambda T, h, s=s, rr=rr, b=b: T.mrclam_msgs__msg__Sightings(
                            header=h, subject=np.asarray(s, dtype=np.int32), range=np.asarray(rr, dtype=np.float64),
                            bearing=np.asarray(b, dtype=np.float64))))
    return out


def carmen_records(log, *, fov: float = math.pi, max_range: float = 81.83) -> list[Record]:
    """CARMEN as LaserScan (``/scan``), the scan's pose (``/scan_pose``, PoseStamped) and the
    ODOM stream (``/odom``, nav_msgs/Odometry)."""
    out: list[Record] = []
    for s in log.scans:
        n = s.ranges.size
        inc = fov / n
        out.append(("/scan", "sensor_msgs/msg/LaserScan", ns(s.t),
                    lambda T, h, r=s.ranges, n=n, inc=inc: T.sensor_msgs__msg__LaserScan(
                        header=h, angle_min=-fov / 2, angle_max=-fov / 2 + (n - 1) * inc, angle_increment=inc,
                        time_increment=0.0, scan_time=0.0, range_min=0.0, range_max=max_range,
                        ranges=np.asarray(r, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32))))
        x, y, th = s.laser_pose
        out.append(("/scan_pose", "geometry_msgs/msg/PoseStamped", ns(s.t),
                    lambda T, h, x=x, y=y, th=th: T.geometry_msgs__msg__PoseStamped(header=h, pose=pose_msg(T, x, y, th))))
    for t, (x, y, th), (v, w, _) in zip(log.odom_t, log.odom, log.odom_vel):
        def build(T, h, x=x, y=y, th=th, v=v, w=w):
            return T.nav_msgs__msg__Odometry(
                header=h, child_frame_id="base_link",
                pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x, y, th), covariance=np.zeros(36)),
                twist=T.geometry_msgs__msg__TwistWithCovariance(twist=twist_msg(T, v, w), covariance=np.zeros(36)))
        out.append(("/odom", "nav_msgs/msg/Odometry", ns(t), build))
    return out


def as_humble_sqlite3(path: Path) -> Path:
    """Turn a sqlite3 bag written by rosbags into what ROS 2 Humble's recorder writes: no
    message definitions (sqlite3 schema 3: no ``message_definitions`` table, no type
    hashes; ``metadata.yaml`` version 5), so only the reader's own type store can decode it."""
    import sqlite3

    import yaml

    db = next(path.glob("*.db3"))
    con = sqlite3.connect(db)
    with con:
        con.execute("DROP TABLE message_definitions")
        con.execute("CREATE TABLE topics3(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
                    "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL)")
        con.execute("INSERT INTO topics3 SELECT id, name, type, serialization_format, offered_qos_profiles FROM topics")
        con.execute("DROP TABLE topics")
        con.execute("ALTER TABLE topics3 RENAME TO topics")
        con.execute("DELETE FROM metadata")
        con.execute("UPDATE schema SET schema_version = 3, ros_distro = 'humble'")
    con.close()
    meta = yaml.safe_load((path / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["version"], info["ros_distro"] = 5, "humble"
    for t in info["topics_with_message_count"]:
        t["topic_metadata"].pop("type_description_hash", None)
        t["topic_metadata"]["offered_qos_profiles"] = ""
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return path


#: vision_msgs 4.x (ROS 2 Humble and later), transcribed for the tests from the package's .msg
#: files (ros-perception/vision_msgs, Apache-2.0), independently of dfusion.bags.msgdefs.
VISION_MSGDEFS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y",
    "vision_msgs/msg/Pose2D": "vision_msgs/msg/Point2D position\nfloat64 theta",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/msg/Pose2D center\nfloat64 size_x\nfloat64 size_y",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/msg/Pose center\ngeometry_msgs/msg/Vector3 size",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score",
    "vision_msgs/msg/ObjectHypothesisWithPose": "vision_msgs/msg/ObjectHypothesis hypothesis\n"
                                                "geometry_msgs/msg/PoseWithCovariance pose",
    "vision_msgs/msg/Detection2D": "std_msgs/msg/Header header\nvision_msgs/msg/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/msg/BoundingBox2D bbox\nstring id",
    "vision_msgs/msg/Detection2DArray": "std_msgs/msg/Header header\nvision_msgs/msg/Detection2D[] detections",
    "vision_msgs/msg/Detection3D": "std_msgs/msg/Header header\nvision_msgs/msg/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/msg/BoundingBox3D bbox\nstring id",
    "vision_msgs/msg/Detection3DArray": "std_msgs/msg/Header header\nvision_msgs/msg/Detection3D[] detections",
}


def tf_static_record(stamp_ns: int, transforms: list[tuple[str, str, float, float, float]]) -> Record:
    """A ``/tf_static`` message: ``(parent, child, x, y, yaw)`` per transform."""
    def build(T, h):
        out = []
        for parent, child, x, y, yaw in transforms:
            hh = T.std_msgs__msg__Header(stamp=h.stamp, frame_id=parent)
            tr = T.geometry_msgs__msg__Transform(
                translation=T.geometry_msgs__msg__Vector3(x=float(x), y=float(y), z=0.0),
                rotation=T.geometry_msgs__msg__Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw)))
            out.append(T.geometry_msgs__msg__TransformStamped(header=hh, child_frame_id=child, transform=tr))
        return T.tf2_msgs__msg__TFMessage(transforms=out)
    return ("/tf_static", "tf2_msgs/msg/TFMessage", stamp_ns, build)
