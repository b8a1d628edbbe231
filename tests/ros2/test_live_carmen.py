"""A live robot node from nodes/ follows a real CARMEN log played as ROS 2 CDR messages over Zenoh.

The Intel Research Lab log's ODOM stream (tests/data/carmen, 10 s of it: 62 poses) is published at
real time as nav_msgs/Odometry in an ``odom`` frame (with a pose covariance) plus a /tf_static
``map -> odom``, on loopback, in both key conventions (rmw_zenoh and zenoh-bridge-ros2dds). The
node (``nodes/robot_localizer.py`` with a node file) must take the messages, express them in
``map`` through the static transform, use their covariance instead of its scenario's noise (its
scenario says std 1 m, the messages 5 cm), and publish Odometry, PoseWithCovarianceStamped and
DiagnosticArray that rosbags decodes. A relay (``nodes/relay.py``, the scenario's sensorless
neighbour, its own node file) runs next to it, linked over Zenoh, with the same start. The
robot's estimates are compared with the offline run of the same data: ``dfusion.sim.replay.replay_scenario`` on the same poses in ``map`` with the same stamps and a
scenario whose noise is the messages' (5 cm). Errors are against the log's corrected scan poses.
"""
from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore

from dfusion.bags.reader import Bag, BagMessage
from dfusion.datasets import read_carmen
from dfusion.scenario.loader import load_scenario
from dfusion.sim.replay import TopicInput, replay_scenario

ROOT = Path(__file__).resolve().parents[2]
LOG = ROOT / "tests" / "data" / "carmen" / "intel-160scans.log.gz"
T0, SPAN = 110.0, 10.0          # the slice of the log (s): the robot drives 4.6 m
DURATION = 13.0                  # the nodes' run (s): the slice starts 1 s after their start
SIGMA = 0.05                     # the messages' position std (m)
MAP_TO_ODOM = (2.0, -1.0, 0.3)   # the static transform published on /tf_static
TS = get_typestore(Stores.ROS2_JAZZY)   # rosbags' own, independent of dfusion.ros2.codec

SCENARIO = """
duration = {duration}
dt = 0.1
seed = 1
window = 100
[target]
motion = "constant_velocity"
q = 0.05
initial_mean = [{x0}, {y0}, 0.0, 0.0]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]
[[nodes]]
name = "robot"
sensor = "position"
std = {std}
rate = 5.0
send_period = 0.5
[[nodes]]
name = "base"        # a neighbour without a sensor (not started live: the node skips it)
send_period = 0.5
[[links]]
between = ["robot", "base"]
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def se2_inv(p):
    x, y, a = p
    c, s = math.cos(a), math.sin(a)
    return (-c * x - s * y, s * x - c * y, -a)


def se2_mul(a, b):
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def odometry(stamp_ns, frame, pose, var):
    M = TS.types
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    cov = np.zeros(36)
    cov[0] = cov[7] = var
    cov[35] = 0.01
    return M["nav_msgs/msg/Odometry"](
        header=M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame),
        child_frame_id="base_link",
        pose=M["geometry_msgs/msg/PoseWithCovariance"](pose=M["geometry_msgs/msg/Pose"](
            position=M["geometry_msgs/msg/Point"](x=pose[0], y=pose[1], z=0.0),
            orientation=M["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(pose[2] / 2),
                                                          w=math.cos(pose[2] / 2))), covariance=cov),
        twist=M["geometry_msgs/msg/TwistWithCovariance"](twist=M["geometry_msgs/msg/Twist"](
            linear=M["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=M["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))


def tf_static(parent, child, pose):
    M = TS.types
    tr = M["geometry_msgs/msg/TransformStamped"](
        header=M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=parent),
        child_frame_id=child,
        transform=M["geometry_msgs/msg/Transform"](
            translation=M["geometry_msgs/msg/Vector3"](x=pose[0], y=pose[1], z=0.0),
            rotation=M["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(pose[2] / 2), w=math.cos(pose[2] / 2))))
    return M["tf2_msgs/msg/TFMessage"](transforms=[tr])


def keys(convention):
    """The data keys of the topics, written out by hand from the conventions' documents."""
    if convention == "rmw_zenoh":
        def key(topic, t):
            pkg, _, name = t.split("/")
            return f"0/{topic.lstrip('/')}/{pkg}::msg::dds_::{name}_/{TS.hash_rihs01(t)}"
    else:
        def key(topic, t):
            return topic.lstrip("/")
    return key


def session(*connect):
    cfg = zenoh.Config()
    for path, value in {"mode": "peer", "listen/endpoints": ["tcp/127.0.0.1:0"], "connect/endpoints": list(connect),
                        "scouting/multicast/enabled": False, "scouting/gossip/enabled": False,
                        "timestamping/enabled": True, "connect/exit_on_failure": False,
                        "connect/retry": {"period_init_ms": 100, "period_max_ms": 200, "period_increase_factor": 2},
                        }.items():   # as rmw_zenoh's sessions (advanced publishers)
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


@pytest.mark.parametrize("convention", ["rmw_zenoh", "ros2dds"])
def test_live_node_follows_a_carmen_log_like_the_offline_run(tmp_path, convention):
    log = read_carmen(LOG)
    sel = (log.odom_t >= T0) & (log.odom_t < T0 + SPAN)
    t_log, poses = log.odom_t[sel] - T0, log.odom[sel]
    assert len(t_log) >= 50
    scans_t = np.array([s.t for s in log.scans]) - T0
    scans_p = np.array([s.laser_pose for s in log.scans])
    x0, y0 = poses[0, :2]
    (tmp_path / "live.scenario.toml").write_text(SCENARIO.format(duration=DURATION, x0=x0, y0=y0, std=1.0))
    (tmp_path / "offline.scenario.toml").write_text(SCENARIO.format(duration=DURATION, x0=x0, y0=y0, std=SIGMA))
    port, port_base = free_port(), free_port()
    start = time.time() + 4.0   # scenario time 0 of both nodes: time to start them and see their tokens
    common = f'scenario = "live.scenario.toml"\nstart = {start!r}\nduration = {DURATION}\n'
    ros = f'[ros]\nconvention = "{convention}"\nframe = "map"\n'
    (tmp_path / "base.node.toml").write_text(
        f'name = "base"\nkind = "relay"\n{common}[zenoh]\nlisten = ["tcp/127.0.0.1:{port_base}"]\n'
        f'connect = ["tcp/127.0.0.1:{port}"]\n{ros}[outputs]\nodometry = "/dfusion/base/odom"\n')
    (tmp_path / "robot.node.toml").write_text(
        f'name = "robot"\nkind = "robot"\n{common}[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        f'connect = ["tcp/127.0.0.1:{port_base}"]\n{ros}'
        '[[inputs]]\ntopic = "/odom"\ntype = "nav_msgs/msg/Odometry"\n'
        '[outputs]\nodometry = "/dfusion/robot/odom"\npose = "/dfusion/robot/pose"\ndiagnostics = "/diagnostics"\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    key = keys(convention)
    got: dict[str, list[bytes]] = {"odom": [], "pose": [], "diag": [], "base": []}
    s = node = base = None
    published: list[tuple[int, tuple]] = []
    try:
        s = session(f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{port_base}")   # peers do not route for others
        tf_key = key("/tf_static", "tf2_msgs/msg/TFMessage")
        tf_bytes = bytes(TS.serialize_cdr(tf_static("map", "odom", MAP_TO_ODOM), "tf2_msgs/msg/TFMessage"))
        if convention == "rmw_zenoh":   # transient local, as rmw_zenoh publishes /tf_static: before the node starts
            tf_pub = zenoh.ext.declare_advanced_publisher(s, tf_key, cache=zenoh.ext.CacheConfig(1),
                                                          publisher_detection=True)
            tf_pub.put(tf_bytes)
        node = subprocess.Popen([sys.executable, str(ROOT / "nodes" / "robot_localizer.py"),
                                 str(tmp_path / "robot.node.toml"), "--result", str(tmp_path / "result.json")],
                                env=env, stderr=subprocess.PIPE, text=True)
        base = subprocess.Popen([sys.executable, str(ROOT / "nodes" / "relay.py"), str(tmp_path / "base.node.toml"),
                                 "--result", str(tmp_path / "base.json")], env=env, stderr=subprocess.PIPE, text=True)
        subs = [s.declare_subscriber(key(topic, t), lambda smp, k=k: got[k].append(smp.payload.to_bytes()))
                for k, topic, t in (("odom", "/dfusion/robot/odom", "nav_msgs/msg/Odometry"),
                                    ("pose", "/dfusion/robot/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
                                    ("diag", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
                                    ("base", "/dfusion/base/odom", "nav_msgs/msg/Odometry"))]
        # the node's liveliness tokens: its subscription of /odom must be seen before playing; the node
        # declares its entities one after another, so wait for every token this test checks
        pattern = "@ros2_lv/0/**" if convention == "rmw_zenoh" else "@/*/@ros2_lv/**"

        def all_declared(tokens: list[str]) -> bool:
            return (any("/MS/" in t and "odom" in t for t in tokens) and any("/MP/" in t and "diagnostics" in t for t in tokens)
                    and (convention != "rmw_zenoh" or any("/NN/%/%/dfusion_robot" in t for t in tokens)))

        deadline, tokens = time.time() + 20, []
        while time.time() < deadline and node.poll() is None and not all_declared(tokens):
            tokens = [str(r.ok.key_expr) for r in s.liveliness().get(pattern, timeout=1.0) if r.ok is not None]
            time.sleep(0.1)
        assert any("/MS/" in t and "odom" in t for t in tokens), (tokens, node.poll() is None or node.stderr.read())
        assert any("/MP/" in t and "diagnostics" in t for t in tokens), tokens
        if convention == "rmw_zenoh":
            assert any("/NN/%/%/dfusion_robot" in t for t in tokens), tokens
        if convention == "ros2dds":
            s.put(tf_key, tf_bytes)
        pub = s.declare_publisher(key("/odom", "nav_msgs/msg/Odometry"))
        odom_of_map = se2_inv(MAP_TO_ODOM)
        assert time.time() < start, "the nodes took too long to come up"
        for tl, p in zip(t_log, poses):
            time.sleep(max(0.0, start + 1.0 + tl - time.time()))
            stamp = time.time_ns()
            msg = odometry(stamp, "odom", se2_mul(odom_of_map, tuple(p)), SIGMA ** 2)
            pub.put(bytes(TS.serialize_cdr(msg, "nav_msgs/msg/Odometry")))
            published.append((stamp, tuple(p)))
        _, err = node.communicate(timeout=DURATION + 30)
        assert node.returncode == 0, err[-3000:]
        _, err = base.communicate(timeout=30)
        assert base.returncode == 0, err[-3000:]
        time.sleep(0.2)
        for sub in subs:
            sub.undeclare()
    finally:
        for proc in (node, base):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        if s is not None:
            s.close()

    # everything decodes with rosbags
    odoms = [TS.deserialize_cdr(b, "nav_msgs/msg/Odometry") for b in got["odom"]]
    poses_out = [TS.deserialize_cdr(b, "geometry_msgs/msg/PoseWithCovarianceStamped") for b in got["pose"]]
    diags = [TS.deserialize_cdr(b, "diagnostic_msgs/msg/DiagnosticArray") for b in got["diag"]]
    assert len(odoms) >= 100 and len(poses_out) == len(odoms) and len(diags) >= 5
    assert all(o.header.frame_id == "map" and o.child_frame_id == "base_link" for o in odoms)
    # health: WARN before the first input (the slice starts 1 s after the start), then OK while fusing
    levels = [(d.status[0].level, d.status[0].message) for d in diags]
    assert levels[0][0] == 1 and levels[0][1].startswith("no input fused yet"), levels
    assert sum(lv == (0, "fusing") for lv in levels) >= 5, levels
    values = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert diags[-1].status[0].name == "dfusion/robot" and values["phase"] == "final"
    assert int(values["measurements_fused"]) == len(published)
    assert int(values["inputs_with_covariance"]) == len(published)
    assert int(values["ros_frame_errors"]) == 0 and int(values["ros_tf_static"]) == 1
    start_ns = int(values["start_ns"])
    assert start_ns == int(round(start * 1e9))
    assert len(got["base"]) >= 100

    # the offline run of the same data: the same poses (in map) and stamps, noise = the messages'
    M = TS.types
    msgs = [BagMessage("/odom", "nav_msgs/msg/Odometry", st, st, i, True, odometry(st, "map", p, SIGMA ** 2))
            for i, (st, p) in enumerate(published)]
    bag = Bag(tmp_path / "same-data", msgs, {"/odom": "nav_msgs/msg/Odometry"}, msgs[0].stamp_ns)
    off = replay_scenario(load_scenario(tmp_path / "offline.scenario.toml"), bag, [TopicInput("/odom", "robot")],
                          origin_ns=start_ns)
    off_t = np.round(off.times, 6)
    live = {}
    for o in poses_out:
        t = round((o.header.stamp.sec * 1_000_000_000 + o.header.stamp.nanosec - start_ns) * 1e-9, 6)
        live[t] = (o.pose.pose.position.x, o.pose.pose.position.y)
    # compare where the truth (the corrected scan poses, interpolated) is known, after the first measurement
    t_first = (published[0][0] - start_ns) * 1e-9
    inside = (scans_t >= -5) & (scans_t <= SPAN + 5)
    rows = []
    for i, t in enumerate(off_t):
        t_in_log = t - t_first + t_log[0]
        if t in live and t > t_first + 0.5 and scans_t[inside].min() <= t_in_log <= scans_t[inside].max():
            truth = [np.interp(t_in_log, scans_t[inside], scans_p[inside, j]) for j in (0, 1)]
            rows.append((live[t], off.node_mean["robot"][i, :2], truth))
    assert len(rows) >= 40
    L, O, T = (np.array([r[j] for r in rows]) for j in range(3))
    rmse_live = float(np.sqrt(np.mean(np.sum((L - T) ** 2, axis=1))))
    rmse_off = float(np.sqrt(np.mean(np.sum((O - T) ** 2, axis=1))))
    rms_gap = float(np.sqrt(np.mean(np.sum((L - O) ** 2, axis=1))))
    print(f"{convention}: {len(rows)} steps, RMSE live {rmse_live:.4f} m, offline {rmse_off:.4f} m, "
          f"RMS live - offline {rms_gap:.2e} m")
    assert abs(rmse_live - rmse_off) <= 0.01 * rmse_off
    # and the final estimates (every measurement fused in both) agree
    final = json.loads((tmp_path / "result.json").read_text())
    np.testing.assert_allclose(np.array(final["mean"])[:2], off.node_mean["robot"][-1, :2], atol=1e-6)
    # the relay (nodes/relay.py) got the robot's information over Zenoh: the same final estimate
    assert int(values["messages_received"]) > 0
    final_base = json.loads((tmp_path / "base.json").read_text())
    np.testing.assert_allclose(np.array(final_base["mean"])[:2], off.node_mean["base"][-1, :2], atol=1e-6)
    np.testing.assert_allclose(final_base["mean"], final["mean"], atol=1e-9)
