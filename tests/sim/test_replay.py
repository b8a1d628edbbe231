"""dfusion replay: a simulated world written as a ROS bag (with rosbags directly,
tests/helpers/bags.py) and replayed through the scenario's nodes gives the nodes'
estimates of the in-process run on that world to 1e-9.

Measurements are PointStamped / PoseWithCovarianceStamped fixes and sensor_msgs/Range
readings (float32 in the message: the reference world holds the float32 ranges); their
header stamp is the measurement time, their record time the simulated arrival. The
truth is nav_msgs/Odometry (pose, body-frame twist).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dfusion.errors import ValidationError
from dfusion.scenario import load_scenario
from dfusion.sim.replay import TopicInput, parse_topic_input, replay_scenario, world_from_bag
from dfusion.sim.runner import run_scenario
from dfusion.sim.world import Measurement, World, simulate_world
from tests.helpers.bags import ns, pose_msg, twist_msg, write_bag

ROOT = Path(__file__).resolve().parents[2]
ORIGIN = 1_700_000_000_123_456_789   # epoch stamps: the replay must keep their nanoseconds


def _fix_record(node: str, m: Measurement, kind: str):
    x, y = (float(v) for v in m.z[:2])

    def point(T, h):
        return T.geometry_msgs__msg__PointStamped(header=h, point=T.geometry_msgs__msg__Point(x=x, y=y, z=0.0))

    def pwc(T, h):
        cov = np.zeros(36)
        cov[0] = cov[7] = 0.25
        return T.geometry_msgs__msg__PoseWithCovarianceStamped(
            header=h, pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x, y, 0.0), covariance=cov))

    if kind == "point":
        return (f"/{node}/fix", "geometry_msgs/msg/PointStamped", ns(m.t, ORIGIN), point)
    return (f"/{node}/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", ns(m.t, ORIGIN), pwc)


def _range_record(node: str, m: Measurement):
    def build(T, h):
        return T.sensor_msgs__msg__Range(header=h, radiation_type=1, field_of_view=6.28, min_range=0.0,
                                         max_range=100.0, range=float(m.z[0]))
    return (f"/{node}/range", "sensor_msgs/msg/Range", ns(m.t, ORIGIN), build)


def _truth_records(world: World):
    out = []
    for t, x in zip(world.times, world.states):
        yaw, v = math.atan2(x[3], x[2]), math.hypot(x[2], x[3])

        def build(T, h, x=x, yaw=yaw, v=v):
            return T.nav_msgs__msg__Odometry(
                header=h, child_frame_id="target",
                pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x[0], x[1], yaw), covariance=np.zeros(36)),
                twist=T.geometry_msgs__msg__TwistWithCovariance(twist=twist_msg(T, v, 0.0), covariance=np.zeros(36)))
        out.append(("/truth", "nav_msgs/msg/Odometry", ns(t, ORIGIN), build))
    return out


def _write(tmp_path, world, kinds, fmt="mcap", shuffle=None):
    """Bag with record time = simulated arrival (shuffle: random record times instead)."""
    recs, rec_ns = [], []
    for m in world.measurements:
        kind = kinds[m.node]
        recs.append(_range_record(m.node, m) if kind == "range" else _fix_record(m.node, m, kind))
        rec_ns.append(ns(m.arrival, ORIGIN))
    truth = _truth_records(world)
    recs += truth
    rec_ns += [r[2] for r in truth]
    return write_bag(tmp_path / f"world_{fmt}", fmt, recs, shuffle=shuffle, record_ns=None if shuffle else rec_ns)


def _compare(a, b, tol=1e-9):
    np.testing.assert_allclose(a.times, b.times)
    for nm in a.node_mean:
        np.testing.assert_allclose(b.node_mean[nm], a.node_mean[nm], rtol=0, atol=tol, err_msg=nm)
        np.testing.assert_allclose(b.node_cov[nm], a.node_cov[nm], rtol=0, atol=tol, err_msg=nm)
    np.testing.assert_allclose(b.central_mean, a.central_mean, rtol=0, atol=tol)


def test_replay_of_position_fixes_with_late_measurements(tmp_path):
    sc = load_scenario(ROOT / "topologies" / "chain3.scenario.toml", duration=15.0)
    world = simulate_world(sc)
    late = [m for m in world.measurements if m.arrival > m.t + sc.dt]
    assert late, "the scenario must have measurements that arrive late"
    kinds = {nm: ("pwc" if i % 2 else "point") for i, nm in enumerate(sorted(sc.nodes))}
    bag = _write(tmp_path, world, kinds)
    inputs = [TopicInput(f"/{nm}/fix", nm) for nm in sc.nodes if sc.nodes[nm].sensor is not None]
    ref = run_scenario(sc, world=world)
    # record times are the arrivals: late measurements are late here too
    got = replay_scenario(sc, bag, inputs, truth_topic="/truth", arrival="record")
    _compare(ref, got)
    np.testing.assert_allclose(got.truth, ref.truth, rtol=0, atol=1e-9)   # pose + body twist -> (x, y, vx, vy)
    assert got.metrics["nodes"].keys() == ref.metrics["nodes"].keys()
    for nm, v in ref.metrics["nodes"].items():
        assert got.metrics["nodes"][nm]["rmse"] == pytest.approx(v["rmse"], abs=1e-9)
    # header stamps rule: with arrival = stamp the record order does not matter
    on_time = World(world.times, world.states, [Measurement(m.t, m.node, m.z, m.t) for m in world.measurements])
    ref_stamp = run_scenario(sc, world=on_time)
    shuffled = _write(tmp_path / "s", world, kinds, fmt="sqlite3", shuffle=5)
    _compare(ref_stamp, replay_scenario(sc, shuffled, inputs, truth_topic="/truth"))
    assert np.max(np.abs(ref_stamp.node_mean["b"] - ref.node_mean["b"])) > 1e-6   # lateness did matter


def test_replay_of_ranges_and_a_user_converter(tmp_path):
    sc = load_scenario(ROOT / "tests" / "data" / "plugins" / "beacons.scenario.toml", duration=10.0)
    world = simulate_world(sc)
    # what a sensor_msgs/Range holds: float32
    w32 = World(world.times, world.states, [Measurement(m.t, m.node, np.float32(m.z).astype(float), m.arrival)
                                             for m in world.measurements])
    bag = _write(tmp_path, w32, {nm: "range" for nm in sc.nodes}, fmt="ros1")
    ref = run_scenario(sc, world=w32)
    got = replay_scenario(sc, bag, [TopicInput(f"/{nm}/range", nm) for nm in sc.nodes], truth_topic="/truth",
                          arrival="record")
    _compare(ref, got)
    # a user function maps the message instead (here: the same range, through a file)
    conv = tmp_path / "conv.py"
    conv.write_text("import numpy as np\ndef rng(msg, t):\n    return np.array([msg.range])\n")
    inputs = [parse_topic_input(f"/{nm}/range={nm}:{conv}:rng") for nm in sc.nodes]
    _compare(ref, replay_scenario(sc, bag, inputs, truth_topic="/truth", arrival="record"))
    # without a truth topic the truth is unknown
    w = world_from_bag(sc, bag, inputs[:1], origin_ns=ORIGIN)
    assert np.isnan(w.states).all() and len(w.measurements) == sum(m.node == inputs[0].node for m in world.measurements)


def test_replay_errors(tmp_path):
    sc = load_scenario(ROOT / "topologies" / "chain3.scenario.toml", duration=2.0)
    world = simulate_world(sc)
    bag = _write(tmp_path, world, {nm: "point" for nm in sc.nodes})
    with pytest.raises(ValidationError, match="not in the scenario"):
        world_from_bag(sc, bag, [TopicInput("/a/fix", "nobody")])
    with pytest.raises(ValidationError, match="no topic"):
        world_from_bag(sc, bag, [TopicInput("/nope", "a")])
    with pytest.raises(ValidationError, match="arrival"):
        world_from_bag(sc, bag, [TopicInput("/a/fix", "a")], arrival="soon")
    with pytest.raises(ValidationError, match="TOPIC=NODE"):
        parse_topic_input("/a/fix")
    from dfusion.bags.convert import Velocity, convert, standard_z
    with pytest.raises(ValidationError, match="no measurement"):
        standard_z(Velocity(0.0, 1.0, 0.1))
    with pytest.raises(ValidationError, match="no converter"):
        convert("vendor_msgs/msg/Blob", object(), 0.0)


def test_replay_command_writes_series_json_csv_and_figures(tmp_path, capsys):
    import csv
    import json

    from dfusion.cli import main

    sc = load_scenario(ROOT / "topologies" / "chain3.scenario.toml", duration=6.0)
    world = simulate_world(sc)
    bag = _write(tmp_path, world, {nm: "point" for nm in sc.nodes}, fmt="ros1")
    out = tmp_path / "out"
    code = main(["replay", str(ROOT / "topologies" / "chain3.scenario.toml"), str(bag), "--duration", "6",
                 "--topic", "/a/fix=a", "--topic", "/b/fix=b", "--topic", "/c/fix=c", "--truth", "/truth",
                 "--arrival", "record", "--json", str(out / "r.json"), "--csv", str(out / "r.csv"),
                 "--plot", str(out / "e.png"), "--topdown", str(out / "t.png"), "--mcap", str(out / "r.mcap"), "-q"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "RMSE [m]" in printed and "final gap pos [m]" in printed
    ref = run_scenario(sc, world=world)
    data = json.loads((out / "r.json").read_text())
    ser = data["series"]
    assert ser["state"] == ["x [m]", "y [m]", "vx [m/s]", "vy [m/s]"]
    np.testing.assert_allclose(ser["t"], ref.times)
    for nm in sc.nodes:
        np.testing.assert_allclose(ser["nodes"][nm]["mean"], ref.node_mean[nm], atol=1e-9)
        np.testing.assert_allclose(ser["nodes"][nm]["var"], np.diagonal(ref.node_cov[nm], axis1=1, axis2=2), atol=1e-9)
        # NEES and gaps, independently: e' P^-1 e with a plain solve; distances to the centralized mean
        e = ref.node_mean[nm] - ref.truth
        nees_ref = [float(v @ np.linalg.solve(P, v)) for v, P in zip(e, ref.node_cov[nm])]
        np.testing.assert_allclose(ser["nodes"][nm]["nees"], nees_ref, rtol=1e-7)
        d = ref.node_mean[nm] - ref.central_mean
        np.testing.assert_allclose(ser["nodes"][nm]["gap_position"], np.hypot(d[:, 0], d[:, 1]), atol=1e-9)
        np.testing.assert_allclose(ser["nodes"][nm]["gap_velocity"], np.hypot(d[:, 2], d[:, 3]), atol=1e-9)
    with (out / "r.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(ref.times) * (len(sc.nodes) + 1)
    b_rows = [r for r in rows if r["node"] == "b"]
    np.testing.assert_allclose([float(r["mean_vx_mps"]) for r in b_rows], ref.node_mean["b"][:, 2], atol=1e-9)
    np.testing.assert_allclose([float(r["var_y_m2"]) for r in b_rows], ref.node_cov["b"][:, 1, 1], atol=1e-9)
    np.testing.assert_allclose([float(r["truth_x_m"]) for r in b_rows], ref.truth[:, 0], atol=1e-9)
    for f in ("e.png", "t.png", "r.mcap"):
        assert (out / f).stat().st_size > 10_000


def _scan_record(node: str, m: Measurement):
    def build(T, h):
        n = m.z.size
        return T.sensor_msgs__msg__LaserScan(
            header=h, angle_min=-math.pi, angle_max=math.pi - 2 * math.pi / n, angle_increment=2 * math.pi / n,
            time_increment=0.0, scan_time=0.0, range_min=0.0, range_max=10.0,
            ranges=np.asarray(m.z, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32))
    return (f"/{node}/scan", "sensor_msgs/msg/LaserScan", ns(m.t, ORIGIN), build)


def test_replay_of_laser_scans_into_mcl_and_icp_nodes(tmp_path):
    """sensor_msgs/LaserScan into robot_mcl and robot_icp nodes (the scans' float32 ranges
    in the reference world too)."""
    from tests.frontends.test_robot_frontends import robot_scenario

    spec = robot_scenario()
    spec["duration"] = 4.0
    spec["nodes"] = [n for n in spec["nodes"] if n["name"] in ("mcl", "icp")]
    spec["links"] = [{"between": ["mcl", "icp"], "latency": 0.05}]
    sc = load_scenario(spec)
    world = simulate_world(sc)
    w32 = World(world.times, world.states, [Measurement(m.t, m.node, m.z.astype(np.float32).astype(float), m.arrival)
                                             for m in world.measurements])
    recs = [_scan_record(m.node, m) for m in w32.measurements] + _truth_records(w32)
    bag = write_bag(tmp_path / "scans", "mcap", recs)
    ref = run_scenario(sc, world=w32)
    got = replay_scenario(sc, bag, [TopicInput("/mcl/scan", "mcl"), TopicInput("/icp/scan", "icp")],
                          truth_topic="/truth")
    _compare(ref, got)
    assert max(v["rmse"] for v in got.metrics["nodes"].values()) < 0.2   # the robots are localized


SCENARIO = str(ROOT / "topologies" / "chain3.scenario.toml")
TOPICS = ["--topic", "/a/fix=a", "--topic", "/b/fix=b", "--topic", "/c/fix=c"]


@pytest.fixture(scope="module")
def chain_world():
    sc = load_scenario(SCENARIO, duration=6.0)
    return sc, simulate_world(sc)


def test_replay_refuses_a_truth_topic_that_does_not_cover_the_run(chain_world, tmp_path, capsys):
    """Issue 25: a truth topic that starts after the other topics printed RMSE nan and then
    crashed --topdown; now it is refused in one line giving the part it covers."""
    from dfusion.cli import main

    sc, world = chain_world
    recs = [_fix_record(m.node, m, "point") for m in world.measurements]
    late_truth = [r for r in _truth_records(world) if r[2] >= ns(2.0, ORIGIN)]
    bag = write_bag(tmp_path / "late", "mcap", recs + late_truth)
    code = main(["replay", SCENARIO, str(bag), "--duration", "6", *TOPICS, "--truth", "/truth",
                 "--topdown", str(tmp_path / "t.png"), "-q"])
    err = capsys.readouterr().err
    # time 0 is the first fix, at 0.2 s: the truth (2-6 s) covers 1.8-5.8 s of the run
    assert code == 2 and "truth topic /truth covers 1.800-5.800 s of the run's 0.000-6.000 s" in err
    assert f"--origin-ns {ns(2.0, ORIGIN)} --duration 4.000" in err and not (tmp_path / "t.png").exists()


def test_replay_refuses_a_message_type_that_does_not_fit_the_node(chain_world, tmp_path):
    """Issue 25: a LaserScan fed to a position node was cut to its first two ranges."""
    sc, world = chain_world
    scans = [_scan_record(m.node, Measurement(m.t, m.node, np.full(90, 3.0), m.arrival)) for m in world.measurements]
    bag = write_bag(tmp_path / "scans", "mcap", scans)
    with pytest.raises(ValidationError, match=r"topic /a/scan: a sensor_msgs/msg/LaserScan gives 90 numbers, but "
                                              r"node 'a' \(position\) takes 2"):
        world_from_bag(sc, bag, [TopicInput("/a/scan", "a")])


def test_replay_without_truth_draws_no_nan_and_shows_progress_when_piped(chain_world, tmp_path, capsys, monkeypatch):
    """Issue 25: without a truth the table says 'unknown' (not nan) and the top-down figure
    is drawn (it crashed on NaN axis limits); --plot, which needs a truth, is refused; a
    piped run prints progress lines (it printed nothing until the end)."""
    import dfusion.sim.runner as runner
    from dfusion.cli import main

    sc, world = chain_world
    bag = _write(tmp_path, world, {nm: "point" for nm in sc.nodes})
    code = main(["replay", SCENARIO, str(bag), "--duration", "6", *TOPICS, "--plot", str(tmp_path / "e.png")])
    assert code == 2 and "--plot draws errors against the truth: give --truth" in capsys.readouterr().err
    monkeypatch.setattr(runner, "PROGRESS_INTERVAL", 0.0)
    out = tmp_path / "out"
    code = main(["replay", SCENARIO, str(bag), "--duration", "6", *TOPICS, "--topdown", str(out / "t.png")])
    cap = capsys.readouterr()
    assert code == 0 and "nan" not in cap.out.lower() and "unknown" in cap.out
    assert f"progress: {sc.steps}/{sc.steps} steps (100 %)" in cap.err and cap.err.count("progress: ") == sc.steps
    assert (out / "t.png").stat().st_size > 10_000


def test_replay_records_the_mcap_in_the_bags_time_with_ros_diagnostics(tmp_path):
    """Issue 25: the recording of a replay was stamped in scenario time from 0, so it could
    not be overlaid on its bag; its /diagnostics were a foxglove.Log. Log times and stamps
    are now the bag's header stamps, and /diagnostics decode with rosbags as
    diagnostic_msgs/msg/DiagnosticArray."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    from dfusion.cli import main

    sc = load_scenario(SCENARIO, duration=21.0)   # a link goes down at 20 s: a diagnostic
    world = simulate_world(sc)
    bag = _write(tmp_path, world, {nm: "point" for nm in sc.nodes})
    out = tmp_path / "r.mcap"
    assert main(["replay", SCENARIO, str(bag), "--duration", "21", *TOPICS, "--truth", "/truth", "--arrival",
                 "record", "--mcap", str(out), "-q"]) == 0
    ros2 = get_typestore(Stores.ROS2_HUMBLE)
    est, diag = [], []
    with out.open("rb") as fh:
        for schema, ch, msg in make_reader(fh).iter_messages(topics=["/nodes/a/estimate", "/diagnostics"]):
            if ch.topic == "/diagnostics":
                assert (schema.name, schema.encoding, ch.message_encoding) == (
                    "diagnostic_msgs/msg/DiagnosticArray", "ros2msg", "cdr")
                diag.append((msg.log_time, ros2.deserialize_cdr(msg.data, schema.name)))
            else:
                est.append(msg.log_time)
    ref = run_scenario(sc, world=world)
    origin = ORIGIN   # the truth's first stamp, at t = 0: the earliest of the topics read
    assert est == [origin + int(round(t * 1e9)) for t in ref.times]
    [(log_time, d)] = diag
    assert log_time == origin + 20 * 10**9 and d.status[0].level == 1 and " down " in d.status[0].message
    for log_time, d in diag:
        assert d.header.stamp.sec * 10**9 + d.header.stamp.nanosec == log_time >= origin
        assert d.status[0].name.startswith("dfusion/") and d.status[0].level in (0, 1)
