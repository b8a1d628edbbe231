"""dfusion replay BAG --detections: recorded detection arrays tracked by the multi-target tracker.

Bags are written with rosbags directly (tests/helpers/bags.py): people walking on straight
lines (constant velocity, crossing paths), detected at 10 Hz with probability 0.9 and noise
N(0, 0.3^2 I), among Poisson clutter. The tracker is judged against a bound computed from the
same draws, independently of dfusion: the mean GOSPA an oracle would reach that takes each
person's own detection as its estimate (the detection's error when detected, c/2 when missed).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dfusion.bags import read_bag
from dfusion.bags.detections import DetectionTopic
from dfusion.cli import main
from dfusion.errors import ValidationError
from dfusion.sim.bag_scans import ScanCounts, scan_covariance, scans_from_bag
from tests.helpers.bags import VISION_MSGDEFS, as_humble_sqlite3, ns, pose_msg, tf_static_record, write_bag

ORIGIN = 1_700_000_000_000_000_000
DT, STD, PD, C = 0.1, 0.3, 0.9, 2.0
AREA = (20.0, 15.0)
#: start position and velocity (m, m/s) of each person: paths cross, never closer than 1 m
PEOPLE = [((2.0, 2.0), (1.0, 0.5)), ((18.0, 4.0), (-1.0, 0.4)), ((3.0, 12.0), (0.9, -0.5)),
          ((17.0, 12.0), (-0.8, -0.6))]


def _walk(steps: int, seed: int, clutter_mean: float):
    """Truth (steps, n, 2), detections per frame (list of (k, 2), shuffled) and the oracle GOSPA per frame."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(1, steps + 1)
    truth = np.stack([np.array(p) + np.outer(t, v) for p, v in PEOPLE], axis=1)
    dets, oracle = [], []
    for k in range(steps):
        seen = rng.random(len(PEOPLE)) < PD
        noise = rng.normal(0.0, STD, (len(PEOPLE), 2))
        z = truth[k][seen] + noise[seen]
        clutter = rng.uniform((0, 0), AREA, (rng.poisson(clutter_mean), 2))
        frame = np.concatenate([z, clutter])
        dets.append(frame[rng.permutation(len(frame))])
        oracle.append(float(np.sum(np.linalg.norm(noise[seen], axis=1)) + C / 2 * np.sum(~seen)))
    return t, truth, dets, np.array(oracle)


def _pose_array(points):
    def build(T, h):
        return T.geometry_msgs__msg__PoseArray(header=h, poses=[pose_msg(T, x, y, 0.0) for x, y in points])
    return build


def _pose_stamped(x, y):
    def build(T, h):
        return T.geometry_msgs__msg__PoseStamped(header=h, pose=pose_msg(T, x, y, 0.0))
    return build


def test_pose_array_bag_replayed_end_to_end_follows_every_person(tmp_path, capsys):
    t, truth, dets, oracle = _walk(100, seed=3, clutter_mean=2.0)
    dets[40] = np.concatenate([dets[40], [[np.nan, 1.0]]])           # one broken detection: refused, counted
    recs = [("/people", "geometry_msgs/msg/PoseArray", ns(tk, ORIGIN), _pose_array(z)) for tk, z in zip(t, dets)]
    recs.append(("/people", "geometry_msgs/msg/PoseArray", ns(t[-1] + DT, ORIGIN), _pose_array(np.zeros((0, 2)))))
    for i in range(len(PEOPLE)):
        recs += [(f"/person{i}/pose", "geometry_msgs/msg/PoseStamped", ns(tk, ORIGIN), _pose_stamped(*truth[k, i]))
                 for k, tk in enumerate(t)]
    bag = write_bag(tmp_path / "people", "mcap", recs)
    out = tmp_path / "tracks.json"
    density = 2.0 / (AREA[0] * AREA[1])
    argv = ["replay", str(bag), "--detections", f"/people=cam,clutter={density}", "--json", str(out)]
    for i in range(len(PEOPLE)):
        argv += ["--truth", f"/person{i}/pose"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "mean GOSPA" in printed and "not_finite 1" in printed
    res = json.loads(out.read_text())
    assert res["counts"]["scans"] == 101 and res["counts"]["empty_scans"] == 1
    assert res["counts"]["rejected_detections"] == {"not_finite": 1}
    assert res["counts"]["detections"] == sum(len(z) for z in dets) - 1
    # per scan: identity, mean (x, y, vx, vy), covariance
    last = res["scans"][-2]
    assert len(last["tracks"]) == len(PEOPLE)
    for tr in last["tracks"]:
        assert len(tr["mean"]) == 4 and np.array(tr["cov"]).shape == (4, 4)
        P = np.array(tr["cov"])
        assert np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
    ends = np.array([tr["mean"][:2] for tr in last["tracks"]])
    d = np.linalg.norm(ends[:, None] - truth[-1][None], axis=2)
    assert np.all(d.min(axis=0) < 3 * STD)                              # a track on every person at the end
    # after the tracks are confirmed (1 s), the tracker beats the oracle that takes each person's own detection
    g = np.array([(s["t"], s["gospa"]) for s in res["gospa"]])
    keep = g[:, 0] >= 1.0 - 1e-9
    mine = float(g[keep, 1].mean())
    bound = float(oracle[t >= 1.0 - 1e-9].mean())
    assert mine < bound, (mine, bound)
    m = res["metrics"]
    assert m["idf1"] >= 0.9 and m["switches"] <= 1 and m["truth_targets"] == len(PEOPLE)


def _vision_types(T, h, points, covs, frame):
    """A Detection3DArray in ``frame``: each detection's best hypothesis holds the position and covariance;
    a worse hypothesis and the box centre hold wrong positions (the converter must take the best)."""
    hh = T.std_msgs__msg__Header(stamp=h.stamp, frame_id=frame)
    out = []
    for i, ((x, y), C3) in enumerate(zip(points, covs)):
        cov = np.zeros(36)
        if C3 is not None:
            cov[[0, 1, 6, 7]] = np.asarray(C3).ravel()
            cov[14] = cov[21] = cov[28] = cov[35] = 1.0
        good = T.vision_msgs__msg__ObjectHypothesisWithPose(
            hypothesis=T.vision_msgs__msg__ObjectHypothesis(class_id="person", score=0.8),
            pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x, y, 0.0), covariance=cov))
        bad = T.vision_msgs__msg__ObjectHypothesisWithPose(
            hypothesis=T.vision_msgs__msg__ObjectHypothesis(class_id="dog", score=0.1),
            pose=T.geometry_msgs__msg__PoseWithCovariance(pose=pose_msg(T, x + 5, y, 0.0), covariance=cov))
        box = T.vision_msgs__msg__BoundingBox3D(center=pose_msg(T, x + (0 if C3 is None else 9), y, 0.0),
                                                size=T.geometry_msgs__msg__Vector3(x=0.5, y=0.5, z=1.8))
        out.append(T.vision_msgs__msg__Detection3D(header=hh, results=[bad, good], bbox=box, id=f"p{i}"))
    return T.vision_msgs__msg__Detection3DArray(header=hh, detections=out)


def _cam_frame(points_map, pose):
    """``points_map`` (k, 2) in a frame whose pose in map is ``pose = (x, y, yaw)``."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    R = np.array([[c, -s], [s, c]])
    return (np.asarray(points_map) - (x, y)) @ R            # R^T (p - t), row-wise


def test_detection3d_array_with_covariances_in_a_camera_frame(tmp_path):
    """Humble sqlite3 (no definitions in the bag: dfusion's vision_msgs definitions read it); positions from
    the best hypothesis in frame cam (tf_static: map -> cam); covariance from the message, rotated into map."""
    cam = (4.0, -2.0, 0.7)
    t, truth, dets, oracle = _walk(60, seed=5, clutter_mean=0.0)
    C_cam = np.array([[0.04, 0.01], [0.01, 0.09]])
    recs = [tf_static_record(ORIGIN, [("map", "cam", *cam)])]
    for tk, z in zip(t, dets):
        zc = _cam_frame(z, cam)
        recs.append(("/cam/objects", "vision_msgs/msg/Detection3DArray", ns(tk, ORIGIN),
                     lambda T, h, zc=zc: _vision_types(T, h, zc, [C_cam] * len(zc), "cam")))
    truth_rec = [("/truth", "vision_msgs/msg/Detection3DArray", ns(tk, ORIGIN),
                  lambda T, h, p=truth[k]: _vision_types(T, h, p, [None] * len(p), "map")) for k, tk in enumerate(t)]
    bag = as_humble_sqlite3(write_bag(tmp_path / "objects", "sqlite3", recs + truth_rec, custom=VISION_MSGDEFS))
    b = read_bag(bag, ["/cam/objects", "/truth"], optional=["/tf_static"])
    counts = ScanCounts()
    scans = list(scans_from_bag(b, [DetectionTopic("/cam/objects", "cam", std=1.0)], counts=counts))
    th = cam[2]
    Rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    for (sensor, scan), z in zip(scans, dets):
        assert sensor == "cam"
        assert np.allclose(scan.detections, z, atol=1e-9)              # back in map, the best hypothesis's position
        assert np.allclose(scan.sensor.R, Rot @ C_cam @ Rot.T, atol=1e-12)
    assert counts.covariance_stated == sum(len(z) for z in dets)
    # end to end with the truth named by the detections' ids (the box centres: no covariance stated)
    out = tmp_path / "tracks.json"
    assert main(["replay", str(bag), "--detections", "/cam/objects=cam,clutter=1e-4", "--truth", "/truth",
                 "--association", "gnn", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["settings"]["association"] == "gnn" and res["metrics"]["truth_targets"] == len(PEOPLE)
    g = np.array([(s["t"], s["gospa"]) for s in res["gospa"]])
    assert g[g[:, 0] >= 1.0 - 1e-9, 1].mean() < oracle[t >= 1.0 - 1e-9].mean()
    # without the transform: one line naming the frames
    b2 = read_bag(bag, ["/cam/objects"])
    with pytest.raises(ValidationError, match="no static transform from frame 'cam' to 'map'"):
        list(scans_from_bag(b2, [DetectionTopic("/cam/objects", "cam")]))


def test_detection2d_boxes_become_ground_positions_through_a_homography(tmp_path):
    """A camera 6 m up looking down at 45 degrees: ground-to-image homography G = K [r1 r2 t] built here;
    the boxes' bottom centres are the people's projected feet; H = G^-1 brings them back."""
    f, cx, cy = 800.0, 640.0, 360.0
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    a = math.radians(45.0)
    # camera at (10, -8, 6) looking along +y, tilted down by a: rows are the camera's axes in the world
    Rcw = np.array([[1.0, 0, 0], [0, -math.sin(a), -math.cos(a)], [0, math.cos(a), -math.sin(a)]])
    C = np.array([10.0, -8.0, 6.0])
    tcw = -Rcw @ C
    G = K @ np.c_[Rcw[:, 0], Rcw[:, 1], tcw]
    feet = np.array([[8.0, 2.0], [12.5, 5.0], [10.0, 0.5]])
    uvw = np.c_[feet, np.ones(3)] @ G.T
    assert np.all(uvw[:, 2] > 0)
    uv = uvw[:, :2] / uvw[:, 2:]
    sky = np.array([cx, cy - 2 * f])                                    # a pixel above the horizon

    def boxes(T, h):
        out = []
        for u, v in [*uv, sky]:
            box = T.vision_msgs__msg__BoundingBox2D(
                center=T.vision_msgs__msg__Pose2D(position=T.vision_msgs__msg__Point2D(x=u, y=v - 40.0), theta=0.0),
                size_x=30.0, size_y=80.0)
            out.append(T.vision_msgs__msg__Detection2D(header=h, results=[], bbox=box, id=""))
        return T.vision_msgs__msg__Detection2DArray(header=h, detections=out)

    bag = write_bag(tmp_path / "boxes", "mcap", [("/cam/boxes", "vision_msgs/msg/Detection2DArray", ORIGIN, boxes)],
                    custom=VISION_MSGDEFS)
    b = read_bag(bag, ["/cam/boxes"])
    with pytest.raises(ValidationError, match="pixel boxes, which need a camera model.*homography"):
        list(scans_from_bag(b, [DetectionTopic("/cam/boxes", "cam")]))
    counts = ScanCounts()
    [(_, scan)] = list(scans_from_bag(b, [DetectionTopic("/cam/boxes", "cam", homography=np.linalg.inv(G))],
                                      counts=counts))
    assert np.allclose(scan.detections, feet, atol=1e-9)
    assert dict(counts.rejected) == {"above_horizon": 1}


def test_two_cameras_seeing_everyone_one_frame_per_stamp(tmp_path):
    """Two PoseArray topics with the same stamps: one scan per message, both in one tracker, metrics once per
    stamp; the second camera's independent detections make the tracks more accurate than the first alone."""
    t, truth, dets_a, oracle = _walk(60, seed=3, clutter_mean=1.0)
    _, truth_b, dets_b, _ = _walk(60, seed=11, clutter_mean=1.0)
    assert np.array_equal(truth, truth_b)
    recs = [("/a", "geometry_msgs/msg/PoseArray", ns(tk, ORIGIN), _pose_array(z)) for tk, z in zip(t, dets_a)]
    recs += [("/b", "geometry_msgs/msg/PoseArray", ns(tk, ORIGIN), _pose_array(z)) for tk, z in zip(t, dets_b)]
    for i in range(len(PEOPLE)):
        recs += [(f"/person{i}/pose", "geometry_msgs/msg/PoseStamped", ns(tk, ORIGIN), _pose_stamped(*truth[k, i]))
                 for k, tk in enumerate(t)]
    bag = write_bag(tmp_path / "two", "mcap", recs)
    truth_args = [a for i in range(len(PEOPLE)) for a in ("--truth", f"/person{i}/pose")]
    density = 1.0 / (AREA[0] * AREA[1])
    res = {}
    for name, topics in (("one", ["/a=a"]), ("two", ["/a=a", "/b=b"])):
        out = tmp_path / f"{name}.json"
        argv = ["replay", str(bag), *[a for tp in topics for a in ("--detections", f"{tp},clutter={density}")],
                *truth_args, "--json", str(out)]
        assert main(argv) == 0
        res[name] = json.loads(out.read_text())
    two = res["two"]
    assert two["counts"]["scans"] == 2 * len(t) and two["metrics"]["frames"] == len(t)
    assert [s["sensor"] for s in two["scans"][:4]] == ["a", "b", "a", "b"]
    assert two["metrics"]["localization"] < res["one"]["metrics"]["localization"]
    g = np.array([(s["t"], s["gospa"]) for s in two["gospa"]])
    assert g[g[:, 0] >= 1.0 - 1e-9, 1].mean() < oracle[t >= 1.0 - 1e-9].mean()


def test_a_topic_of_another_type_is_refused_in_one_line(tmp_path, capsys):
    bag = write_bag(tmp_path / "poses", "mcap", [("/robot/pose", "geometry_msgs/msg/PoseStamped", ORIGIN,
                                                  _pose_stamped(1.0, 2.0))])
    assert main(["replay", str(bag), "--detections", "/robot/pose=cam"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "topic /robot/pose: a geometry_msgs/msg/PoseStamped is no detection array" in err
    assert "/robot/pose=cam:FILE.py:FUNCTION" in err
    # options of the scenario replay do not apply: refused in one line too
    assert main(["replay", str(bag), "--detections", "/robot/pose=cam", "--mcap", str(tmp_path / "o.mcap")]) == 2
    assert capsys.readouterr().err.strip() == ("dfusion: error: --mcap does not apply to --detections (the tracker "
                                               "takes the scans in stamp order; its output is --json)")


def test_one_covariance_per_scan_covers_every_detection():
    """Different stated covariances: R = s M covers each (R - R_j >= 0) and touches one (s is the least)."""
    rng = np.random.default_rng(0)
    covs = []
    for _ in range(5):
        A = rng.normal(size=(2, 2))
        covs.append(A @ A.T + 0.05 * np.eye(2))
    R, widened = scan_covariance(np.array(covs), np.eye(2))
    assert widened
    gaps = [np.linalg.eigvalsh(R - Cj).min() for Cj in covs]
    assert min(gaps) > -1e-12 and abs(min(gaps)) < 1e-9
    M = np.mean(covs, axis=0)
    assert np.allclose(R / M, (R / M)[0, 0])                          # a multiple of the mean
    same, widened = scan_covariance(np.array([covs[0]] * 3), np.eye(2))
    assert not widened and np.allclose(same, covs[0])


def test_any_other_type_through_a_user_function(tmp_path):
    """The converter hook of --detections: TOPIC=SENSOR:FILE.py:FUNCTION with per-topic keys after it."""
    from dfusion.sim.track_replay import parse_detection_topic

    conv = tmp_path / "conv.py"
    conv.write_text("import numpy as np\n\n"
                    "def people(msg, t):\n"
                    "    return np.array([[p.x, p.y] for p in msg.polygon.points]).reshape(-1, 2)\n\n"
                    "def broken(msg, t):\n"
                    "    return np.zeros(3)\n")
    pts = [np.array([[1.5, 2.25], [3.0, -4.5]]), np.zeros((0, 2))]

    def polygon(p):
        def build(T, h):
            return T.geometry_msgs__msg__PolygonStamped(header=h, polygon=T.geometry_msgs__msg__Polygon(
                points=[T.geometry_msgs__msg__Point32(x=float(x), y=float(y), z=0.0) for x, y in p]))
        return build

    bag = write_bag(tmp_path / "poly", "mcap", [("/poly", "geometry_msgs/msg/PolygonStamped", ORIGIN + k * 10**8,
                                                 polygon(p)) for k, p in enumerate(pts)])
    b = read_bag(bag, ["/poly"])
    opts = parse_detection_topic(f"/poly=cam:{conv}:people,std=0.5,pd=0.8,clutter=0.01")
    assert (opts.sensor, opts.std, opts.detection_probability, opts.clutter_density) == ("cam", 0.5, 0.8, 0.01)
    scans = [s for _, s in scans_from_bag(b, [opts])]
    assert [s.time for s in scans] == [0.0, 0.1]
    assert np.array_equal(scans[0].detections, pts[0]) and scans[1].detections.shape == (0, 2)
    assert np.allclose(scans[0].sensor.R, 0.25 * np.eye(2)) and scans[0].detection_probability == 0.8
    with pytest.raises(ValidationError, match=r"returned shape \(3,\)"):
        list(scans_from_bag(b, [parse_detection_topic(f"/poly=cam:{conv}:broken")]))
    with pytest.raises(ValidationError, match="is no KEY=VALUE"):
        parse_detection_topic("/poly=cam,speed=3")
    # a view: the scan knows where its sensor sees (P_D follows it, a track out of view is not missed)
    [(_, s)] = list(scans_from_bag(b, [parse_detection_topic(f"/poly=cam:{conv}:people,view=0:10:-5:5")]))[:1]
    P = 0.01 * np.eye(4)
    assert s.visibility(np.array([5.0, 0.0, 0, 0]), P) > 0.999 and s.visibility(np.array([12.0, 0.0, 0, 0]), P) < 1e-6
    with pytest.raises(ValidationError, match="x1 > x0"):
        parse_detection_topic("/poly=cam,view=3:1:0:5")
