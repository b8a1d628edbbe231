"""dfusion.ros2 and the node file: keys against the conventions' documents, CDR, tf, covariances, bad input."""
from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from dfusion.errors import ValidationError
from dfusion.ros2.codec import decode, diagnostics, encode, estimate_messages, make, register_definition
from dfusion.ros2.inputs import reading_of
from dfusion.ros2.keys import Convention, rmw_attachment
from dfusion.ros2.link import Ros2Link
from dfusion.bags.tf import StaticTransforms
from dfusion.run.live import main
from dfusion.run.nodefile import load_node_file
from tests.ros2.scenarios import TWO_NODES

TS = get_typestore(Stores.ROS2_JAZZY)
#: rmw_zenoh's docs/design.md: the `chatter` topic (std_msgs/String) in namespace /robot1, and the
#: `talker` node's publisher token of session 8b20917502ee955ac4476e0266340d5c (domain 2, QoS depth 7)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DOC_KEY = f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
DOC_TOKEN = ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
             f"{STRING_HASH}/::,7:,:,:,,")


def test_keys_and_tokens_are_those_of_the_conventions_documents():
    assert Convention("rmw_zenoh").data_key("/robot1/chatter", "std_msgs/msg/String") == DOC_KEY
    tok = Convention("rmw_zenoh", 2).entity_token("MP", "8b20917502ee955ac4476e0266340d5c", "talker", "/chatter",
                                                  "std_msgs/msg/String", entity_id=10)
    assert tok.rsplit("/", 1)[0] == DOC_TOKEN.rsplit("/", 1)[0]   # the QoS chunk: ours says depth 10
    assert Convention("rmw_zenoh", 2).node_token("aac3178e146ba6f1fc6e6a4085e77f21", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    # zenoh-bridge-ros2dds: the topic without its leading slash, after the bridge's namespace
    assert Convention("ros2dds").data_key("/chatter", "std_msgs/msg/String") == "chatter"
    assert Convention("ros2dds", namespace="/bot1").data_key("/a/b", "std_msgs/msg/String") == "bot1/a/b"
    assert Convention("ros2dds").entity_token("MS", "abc", "n", "/a/b", "std_msgs/msg/String").startswith(
        "@/abc/@ros2_lv/MS/a\u00a7b/std_msgs\u00a7msg\u00a7String/")
    with pytest.raises(ValidationError, match="convention must be one of"):
        Convention("dds")
    with pytest.raises(ValidationError, match="not a ROS 2 name"):
        Convention().data_key("/a/**", "std_msgs/msg/String")


def test_rmw_attachment_layout():
    gid = bytes(range(16))
    a = rmw_attachment(7, 1_700_000_000_000_000_001, gid)
    assert struct.unpack("<qqB", a[:17]) == (7, 1_700_000_000_000_000_001, 16) and a[17:] == gid


def test_estimate_messages_decode_with_rosbags_and_carry_the_planar_estimate():
    mean = np.array([1.0, -2.0, 0.3, 0.4])
    cov = np.diag([0.04, 0.09, 0.01, 0.02])
    odom, pose = estimate_messages(mean, cov, 1_700_000_000_123_456_789, "map", "base_link")
    o = TS.deserialize_cdr(encode(odom), "nav_msgs/msg/Odometry")
    p = TS.deserialize_cdr(encode(pose), "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert (o.header.stamp.sec, o.header.stamp.nanosec, o.header.frame_id) == (1_700_000_000, 123_456_789, "map")
    yaw = math.atan2(0.4, 0.3)
    assert 2 * math.atan2(o.pose.pose.orientation.z, o.pose.pose.orientation.w) == pytest.approx(yaw)
    C = np.asarray(p.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(C[:2, :2], cov[:2, :2])
    # heading variance, first order: (vx^2 var(vy) + vy^2 var(vx)) / |v|^4 for independent vx, vy
    assert C[5, 5] == pytest.approx((0.3 ** 2 * 0.02 + 0.4 ** 2 * 0.01) / 0.5 ** 4)
    assert o.twist.twist.linear.x == pytest.approx(0.5)
    d = TS.deserialize_cdr(encode(diagnostics(5, "dfusion/a", "h", "warn", "late", {"n": 3})),
                           "diagnostic_msgs/msg/DiagnosticArray")
    assert d.status[0].level == 1 and d.status[0].values[0].value == "3"


def test_a_pose_in_another_frame_comes_through_the_static_transform_with_its_covariance_rotated():
    tf = StaticTransforms()
    tf.add("map", "odom", np.array([2.0, -1.0, 0.0]))
    tf.add("odom", "gps", np.array([0.5, 0.0, math.pi / 2]))   # map <- odom <- gps
    C = np.diag([0.01, 0.04])
    msg = TS.types["geometry_msgs/msg/PoseWithCovarianceStamped"]
    cov6 = np.zeros((6, 6))
    cov6[:2, :2] = C
    m = msg(header=TS.types["std_msgs/msg/Header"](stamp=TS.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                                   frame_id="gps"),
            pose=TS.types["geometry_msgs/msg/PoseWithCovariance"](pose=TS.types["geometry_msgs/msg/Pose"](
                position=TS.types["geometry_msgs/msg/Point"](x=1.0, y=0.0, z=0.0),
                orientation=TS.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
                covariance=cov6.reshape(-1)))
    r = reading_of("geometry_msgs/msg/PoseWithCovarianceStamped", m, "map", tf)
    # (1, 0) in gps, gps turned 90 deg at (0.5, 0) in odom -> (0.5, 1) in odom -> (2.5, 0) in map
    np.testing.assert_allclose(r.z, [2.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(r.R, np.diag([0.04, 0.01]), atol=1e-15)   # x and y swap under 90 deg
    m.header.frame_id = "camera"
    with pytest.raises(ValidationError, match="not connected"):
        reading_of("geometry_msgs/msg/PoseWithCovarianceStamped", m, "map", tf)
    cov6[:] = 0   # ROS's "unknown": the node's own noise
    m.header.frame_id = "map"
    m.pose.covariance = cov6.reshape(-1)
    assert reading_of("geometry_msgs/msg/PoseWithCovarianceStamped", m, "map", tf).R is None


def test_a_scan_gives_its_ranges_and_an_unsupported_type_is_refused():
    M = TS.types
    scan = M["sensor_msgs/msg/LaserScan"](
        header=M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="laser"),
        angle_min=-1.0, angle_max=1.0, angle_increment=1.0, time_increment=0.0, scan_time=0.1, range_min=0.1,
        range_max=30.0, ranges=np.array([1.5, np.inf, 2.25], dtype=np.float32), intensities=np.zeros(0, np.float32))
    r = reading_of("sensor_msgs/msg/LaserScan", scan, "map", StaticTransforms())
    assert r.z.tolist() == [1.5, math.inf, 2.25] and r.R is None and r.frame == "laser"
    with pytest.raises(ValidationError, match="is not supported"):
        reading_of("sensor_msgs/msg/Image", scan, "map", StaticTransforms())


def loopback_session():
    cfg = zenoh.Config()
    for path, value in {"mode": "peer", "listen/endpoints": ["tcp/127.0.0.1:0"], "scouting/multicast/enabled": False,
                        "scouting/gossip/enabled": False}.items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def take_until(link, n, keys=("received", "decode_errors", "frame_errors", "converter_errors", "skipped")):
    got, deadline = [], time.time() + 5
    while time.time() < deadline and sum(link.counters[k] for k in keys) < n:
        got += link.take()
        time.sleep(0.02)
    return got + link.take()


RSSI_MSG = "std_msgs/Header header\nfloat64[] rssi\n"


def test_a_custom_type_with_its_definition_and_a_user_converter():
    register_definition("vendor_msgs/msg/Rssi", RSSI_MSG)
    s = loopback_session()
    link = None
    try:
        conv = Convention("ros2dds")

        def first_two(msg, stamp_s):
            if len(msg.rssi) == 0:
                return None
            if len(msg.rssi) == 1:
                raise ValueError("one reading")
            return msg.rssi[:2]

        link = Ros2Link(s, conv, "dfusion_w", "map", {"/rssi": "vendor_msgs/msg/Rssi"}, {}, {"/rssi": first_two})
        Header, Time = TS.types["std_msgs/msg/Header"], TS.types["builtin_interfaces/msg/Time"]
        for values in ([-60.0, -70.0, -80.0], [], [-1.0]):
            msg = make("vendor_msgs/msg/Rssi", header=Header(stamp=Time(sec=2, nanosec=0), frame_id="w"),
                       rssi=np.array(values))
            s.put(conv.data_key("/rssi", "vendor_msgs/msg/Rssi"), encode(msg))
        got = take_until(link, 3)
        assert [r.reading.z.tolist() for r in got] == [[-60.0, -70.0]]
        assert (link.counters["skipped"], link.counters["converter_errors"]) == (1, 1)
    finally:
        if link is not None:
            link.close()
        s.close()


def test_bad_bytes_and_unknown_frames_are_counted_not_fused():
    s = loopback_session()
    link = None
    try:
        conv = Convention("rmw_zenoh")
        link = Ros2Link(s, conv, "dfusion_a", "map", {"/fix": "geometry_msgs/msg/PointStamped"}, {})
        key = conv.data_key("/fix", "geometry_msgs/msg/PointStamped")
        M = TS.types
        good = M["geometry_msgs/msg/PointStamped"](
            header=M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=3, nanosec=5), frame_id="map"),
            point=M["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0))
        s.put(key, b"\x00\x01\x00\x00garbage")
        s.put(key, bytes(TS.serialize_cdr(good, "geometry_msgs/msg/PointStamped")))
        good.header.frame_id = "elsewhere"
        s.put(key, bytes(TS.serialize_cdr(good, "geometry_msgs/msg/PointStamped")))
        got = take_until(link, 3)
        assert [(r.stamp_ns, r.reading.z.tolist()) for r in got] == [(3_000_000_005, [1.0, 2.0])]
        assert (link.counters["decode_errors"], link.counters["frame_errors"]) == (1, 1)
    finally:
        if link is not None:
            link.close()
        s.close()
    with pytest.raises(ValidationError, match="not a CDR"):
        decode(b"\x00\x01\x00\x00", "nav_msgs/msg/Odometry")


def test_the_input_queue_is_bounded_in_bytes_and_oversized_samples_are_refused(monkeypatch):
    import dfusion.ros2.link as link_mod

    s = loopback_session()
    link = None
    try:
        conv = Convention("rmw_zenoh")
        link = Ros2Link(s, conv, "dfusion_a", "map", {"/fix": "geometry_msgs/msg/PointStamped"}, {})
        M = TS.types
        msg = M["geometry_msgs/msg/PointStamped"](
            header=M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=3, nanosec=5), frame_id="map"),
            point=M["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0))
        data = bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PointStamped"))
        monkeypatch.setattr(link_mod, "QUEUE_BYTES", 2 * len(data))   # room for two samples
        key = conv.data_key("/fix", "geometry_msgs/msg/PointStamped")
        for _ in range(5):
            s.put(key, data)
        s.put(key, data + bytes(link_mod.MAX_SAMPLE_BYTES))
        deadline = time.time() + 5
        while time.time() < deadline and link.counters["shed"] + link.counters["oversized"] < 4:
            time.sleep(0.02)
        assert len(link.take()) == 2
        assert (link.counters["shed"], link.counters["oversized"]) == (3, 1)
    finally:
        if link is not None:
            link.close()
        s.close()


NODE = """name = "robot"
kind = "robot"
scenario = "s.toml"
[ros]
convention = "rmw_zenoh"
[[inputs]]
topic = "/odom"
type = "nav_msgs/msg/Odometry"
"""


@pytest.mark.parametrize("change, error", [
    (("[ros]", "[ross]"), "unknown key 'ross' (did you mean 'ros'?)"),
    (('convention = "rmw_zenoh"', "convention = 3"), "ros.convention must be str, got int 3"),
    (('convention = "rmw_zenoh"', 'convention = "dds"'), "ros.convention must be one of"),
    (('kind = "robot"\n', ""), "missing key 'kind'"),
    (('kind = "robot"', 'kind = "drone"'), "kind must be one of camera, wsn, robot, relay"),
    (("nav_msgs/msg/Odometry", "sensor_msgs/msg/Image"), "inputs[0].type 'sensor_msgs/msg/Image' is not supported"),
    (('topic = "/odom"', 'topic = "odom"'), "inputs[0].topic: a ROS 2 topic is a fully qualified name"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nduration = -1'), "duration must be positive"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nduration = inf'), "duration must be a finite number, got inf"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nduration = nan'), "duration must be a finite number, got nan"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nstart = inf'), "start must be a finite number, got inf"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nstart = -5.0'), "start must be positive, got -5.0"),
    (('convention = "rmw_zenoh"', 'convention = "rmw_zenoh"\nstale_after = inf'),
     "ros.stale_after must be a finite number, got inf"),
    (('convention = "rmw_zenoh"', 'convention = "rmw_zenoh"\ndiagnostics_period = -1'),
     "ros.diagnostics_period must be positive, got -1"),
    (('convention = "rmw_zenoh"', 'convention = "rmw_zenoh"\nlatency = nan'), "ros.latency must be a finite number"),
    (('scenario = "s.toml"', 'scenario = "s.toml"\nrun_id = 42'), "run_id must be str, got int 42"),
    (('type = "nav_msgs/msg/Odometry"', 'type = "nav_msgs/msg/Odometry"\nconvert = "nowhere.py:f"'),
     "inputs[0].convert: "),
    (('type = "nav_msgs/msg/Odometry"', 'type = "nav_msgs/msg/Odometry"\nconvert = "f"'),
     "inputs[0].convert must be FILE.py:FUNCTION, got 'f'"),
    (('convention = "rmw_zenoh"', 'convention = "rmw_zenoh"\nlatency = -0.1'), "ros.latency must be in [0, 10]"),
    (('convention = "rmw_zenoh"', 'convension = "rmw_zenoh"'),
     "unknown key 'ros.convension' (did you mean 'convention'?)"),
])
def test_the_node_file_loader_is_strict(tmp_path, change, error):
    f = tmp_path / "n.toml"
    f.write_text(NODE.replace(*change))
    with pytest.raises(ValidationError) as e:
        load_node_file(f)
    assert error in str(e.value) and "\n" not in str(e.value)


def test_the_node_files_run_id_authenticates_the_nodes_messages_for_that_run(tmp_path):
    """run_id (default none: "") reaches the live node: its fusion messages carry a MAC for the
    network key and that run, so a neighbour of that run fuses them and one of another run refuses
    them (issue 25, hosts: a live node beside host processes started with --run-id)."""
    from dfusion.errors import MessageError
    from dfusion.run.live import LiveNodeProcess
    from dfusion.scenario.build import build_node
    from dfusion.scenario.loader import load_scenario

    (tmp_path / "s.toml").write_text(TWO_NODES.format(duration=5.0))
    f = tmp_path / "n.toml"
    f.write_text(NODE)
    assert load_node_file(f).run_id is None
    f.write_text(NODE.replace('scenario = "s.toml"', 'scenario = "s.toml"\nrun_id = "plant-7"'))
    nf = load_node_file(f)
    assert nf.run_id == "plant-7"
    sc = load_scenario(nf.scenario)
    key = b"k" * 32
    robot = LiveNodeProcess(sc, "robot", nf, network="n", network_key=key, run_id=nf.run_id).node
    robot.predict(0.1)
    message = robot.message_to("base")
    for run, fused in (("plant-7", 1), ("", 0)):
        base = build_node(sc, "base", network_key=key, network="n", run=run, epoch=2)
        base.predict(0.1)
        try:
            base.receive(message)
        except MessageError:   # refused (unauthenticated): counted below
            pass
        assert (base.stats.messages_received, base.stats.messages_rejected) == (fused, 1 - fused), run


def test_an_input_that_does_not_fit_the_node_is_refused_at_start(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(TWO_NODES.format(duration=5.0))
    f = tmp_path / "n.toml"
    f.write_text(NODE.replace("/odom", "/range").replace("nav_msgs/msg/Odometry", "sensor_msgs/msg/Range"))
    assert main([str(f)], kind="robot") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "input /range (sensor_msgs/msg/Range) gives 1 value(s), but node 'robot' (position) " \
        "takes 2" in err[0], err


def test_a_program_refuses_a_node_file_of_another_kind(tmp_path, capsys):
    f = tmp_path / "n.toml"
    f.write_text(NODE)
    assert main([str(f)], kind="camera") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "kind is 'robot', but this is the camera program" in err[0]


CUSTOM_INPUT = """
[[inputs]]
topic = "/rssi"
type = "{msgtype}"
convert = "conv.py:{func}"
{definition}"""


@pytest.mark.parametrize("msgtype, definition, convert, func, error", [
    ("vendor_msgs/msg/RssiA", "float64[ rssi\n", "def f(msg, t):\n    return None\n", "f",
     "the definition of vendor_msgs/msg/RssiA does not parse: at 'float64[ rssi'"),
    ("vendor_msgs/msg/RssiB", "std_msgs/Header header\nvendor_msgs/Nowhere x\n", "def f(msg, t):\n    return None\n",
     "f", "the definition of vendor_msgs/msg/RssiB uses the unknown type 'vendor_msgs/msg/Nowhere'"),
    ("vendor_msgs/msg/RssiC", None, "def f(msg, t):\n    return None\n", "f",
     "unknown ROS 2 message type 'vendor_msgs/msg/RssiC'"),
    ("vendor_msgs/msg/RssiD", RSSI_MSG, "def f(msg, t)\n    return None\n", "f",
     "conv.py does not load: SyntaxError"),
    ("vendor_msgs/msg/RssiE", RSSI_MSG, "import not_a_module_of_anyone\n", "f",
     "conv.py does not load: ModuleNotFoundError"),
    ("vendor_msgs/msg/RssiF", RSSI_MSG, "def f(msg, t):\n    return None\n", "g", "conv.py has no function 'g'"),
], ids=["unparsable-msg", "unknown-nested-type", "no-definition", "syntax-error", "failing-import", "no-function"])
def test_a_bad_definition_or_converter_stops_the_node_with_one_line_before_it_joins(
        tmp_path, capsys, monkeypatch, msgtype, definition, convert, func, error):
    """The .msg definitions are registered, the input types checked and the converters loaded
    before the node opens its Zenoh session: a bad one is one line, and no session is opened."""
    from dfusion.run.node_process import Host

    opened = []
    monkeypatch.setattr(Host, "_open_transport", lambda self: opened.append(1) or pytest.fail("joined the network"))
    (tmp_path / "s.toml").write_text(TWO_NODES.format(duration=5.0))
    (tmp_path / "conv.py").write_text(convert)
    text = NODE + CUSTOM_INPUT.format(msgtype=msgtype, func=func, definition="")
    if definition is not None:
        (tmp_path / "Rssi.msg").write_text(definition)
        text += 'definition = "Rssi.msg"\n'
    f = tmp_path / "n.toml"
    f.write_text(text)
    assert main([str(f)], kind="robot") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(f) in err[0] and error in err[0], err
    assert opened == []
