"""``dfusion simulate`` of a multi-target scenario: a TrackingNode per node over the scenario's tree.

The tracks are checked against references independent of dfusion: filterpy's Kalman filter per
target given that target's own detections (the association known: an oracle), and a distance
bound from the sensors' noise alone."""
from __future__ import annotations

import json

import numpy as np
from filterpy.kalman import KalmanFilter

from dfusion.cli import main
from dfusion.scenario import load_scenario
from dfusion.sim.tracking_runner import CENTRAL, run_tracking_scenario
from tests.helpers.fusion_harness import cv_F, cv_Q
from tests.scenario.test_loader import write
from tests.scenario.test_multi_target_loader import MULTI

STD = 0.3          # the cameras' detection noise (std of MULTI's "detections" nodes, the default)
BOUND = 1.0        # metres: a track on a target is within 3.3 standard deviations of one detection


def oracle_kalman(world, target: str, q: float) -> dict[float, tuple[np.ndarray, int]]:
    """filterpy's Kalman filter (constant velocity, ``q``) given every camera detection of ``target``
    (known from the simulator) in time order: ``{step time: (position, detections in the last second)}``."""
    meas = sorted(((f.t, f.scan.detections[i]) for f in world.frames if f.scan is not None
                   for i, src in enumerate(f.source) if src == target), key=lambda m: m[0])
    out, kf, t_prev, k = {}, None, None, 0
    for t in world.times[1:]:
        while k < len(meas) and meas[k][0] <= t + 1e-9:
            tm, z = meas[k]
            if kf is None:
                kf = KalmanFilter(dim_x=4, dim_z=2)
                kf.x = np.array([z[0], z[1], 0.0, 0.0]).reshape(4, 1)
                kf.P = np.diag([STD**2, STD**2, 1.5**2, 1.5**2])
                kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
                kf.R = STD**2 * np.eye(2)
            else:
                kf.F, kf.Q = cv_F(tm - t_prev), cv_Q(tm - t_prev, q)
                kf.predict()
                kf.update(z.reshape(2, 1))
            t_prev = tm
            k += 1
        if kf is not None:
            dt = t - t_prev
            x = cv_F(dt) @ kf.x if dt > 0 else kf.x
            recent = sum(1 for tm, _ in meas[:k] if t - tm <= 1.0)
            out[float(t)] = (x.ravel()[:2], recent)
    return out


def test_every_node_tracks_every_target_in_view_close_to_the_oracle_kalman_filter(tmp_path):
    sc = load_scenario(write(tmp_path, MULTI))
    res = run_tracking_scenario(sc)
    m = res.metrics
    assert set(m["nodes"]) == {"cam_e", "cam_w", "wsn"}
    oracle = {t.name: oracle_kalman(res.world, t.name, sc.tracking.q) for t in sc.targets}
    for node in list(m["nodes"]) + [CENTRAL]:
        near = pairs = 0
        err_node, err_oracle = [], []
        for t in res.history.times(node):
            if t < 2.0:
                continue
            names, X = res.world.truth.at(t)
            _, Y = res.history.positions(node, t)
            for name, x in zip(names, X):
                got = oracle[name].get(float(t))
                if got is None or got[1] < 5:        # the target has not been seen in the last second
                    continue
                pairs += 1
                d = np.linalg.norm(Y - x, axis=1) if len(Y) else np.array([np.inf])
                if d.min() <= BOUND:
                    near += 1
                    err_node.append(d.min())
                    err_oracle.append(np.linalg.norm(got[0] - x))
        assert pairs > 200, (node, pairs)
        assert near >= 0.9 * pairs, (node, near, pairs)
        rmse_node, rmse_oracle = np.sqrt(np.mean(np.square(err_node))), np.sqrt(np.mean(np.square(err_oracle)))
        assert rmse_node <= 2.0 * rmse_oracle, (node, rmse_node, rmse_oracle)
    assert m["label_agreement"]["agreement"] >= 0.95, m["label_agreement"]
    (rv,) = m["rendezvous"]
    assert all(v["distinct_share"] >= 0.8 for v in rv["nodes"].values()), rv
    # the counts add up
    tr = m["traffic"]
    assert tr["sent"] + tr["duplicated"] == tr["delivered"] + tr["dropped"] + tr["in_flight"]
    assert sum(v["bundles_received"] for v in m["nodes"].values()) + tr["rejected"] == tr["delivered"]
    assert res.world.readings > 0 and m["world"]["people"] == 2 and m["world"]["robots"] == 1


def test_dfusion_simulate_runs_a_multi_target_scenario_and_writes_json(tmp_path, capsys):
    path = write(tmp_path, MULTI)
    out = tmp_path / "mt.json"
    assert main(["simulate", str(path), "--duration", "3", "-q", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "GOSPA [m]" in text and "label agr." in text and "central" in text
    data = json.loads(out.read_text())
    assert data["kind"] == "multi_target" and set(data["nodes"]) == {"cam_e", "cam_w", "wsn"}
    assert data["steps"] == 30 and len(data["series"]["cam_w"]) == 30
    assert main(["simulate", str(path), "--duration", "1", "-q", "--csv", str(tmp_path / "x.csv")]) == 2


def test_replay_of_a_pose_array_bag_into_the_scenario_gives_what_simulate_gives(tmp_path, capsys):
    """The cameras' detections of a simulated world written as PoseArray messages (one topic per
    camera) and the truth as PoseStamped per target: ``dfusion replay SCENARIO BAG`` tracks them as
    ``simulate`` does with the same detections (the tag readings, which are not in the bag, left out)."""
    from dataclasses import replace

    from tests.helpers.bags import ns, pose_msg, write_bag

    from dfusion.sim.target_world import simulate_targets

    origin = 1_700_000_000_000_000_000
    text = MULTI.replace("duration = 12.0", "duration = 6.0").replace('meets = "ann"\n', "")
    sc = load_scenario(write(tmp_path, text))
    world = simulate_targets(sc)
    recs = []
    for f in world.frames:
        if f.scan is None:
            continue
        pts = f.scan.detections.copy()
        recs.append((f"/{f.node}/people", "geometry_msgs/msg/PoseArray", ns(f.t, origin),
                     lambda T, h, pts=pts: T.geometry_msgs__msg__PoseArray(
                         header=h, poses=[pose_msg(T, x, y, 0.0) for x, y in pts])))
    for name, (ts, xy) in world.truth.paths.items():
        recs += [(f"/truth/{name}", "geometry_msgs/msg/PoseStamped", ns(t, origin),
                  lambda T, h, p=p: T.geometry_msgs__msg__PoseStamped(header=h, pose=pose_msg(T, p[0], p[1], 0.0)))
                 for t, p in zip(ts, xy)]
    bag = write_bag(tmp_path / "people", "mcap", recs)
    out = tmp_path / "replay.json"
    argv = ["replay", str(tmp_path / "s.scenario.toml"), str(bag), "--topic", "/cam_w/people=cam_w",
            "--topic", "/cam_e/people=cam_e", "-q", "--json", str(out)]
    argv += [a for name in world.truth.paths for a in ("--truth", f"/truth/{name}")]
    assert main(argv) == 0
    assert "read 122 scans" in capsys.readouterr().out
    replayed = json.loads(out.read_text())
    # the same world without the tag readings, simulated
    cameras_only = replace(world, frames=[f for f in world.frames if f.scan is not None],
                           truth=type(world.truth)({f"/truth/{n}": p for n, p in world.truth.paths.items()}))
    simulated = run_tracking_scenario(sc, world=cameras_only).metrics
    for node in ("cam_w", "cam_e", "wsn", CENTRAL):
        a = replayed["nodes"].get(node, replayed["central"] if node == CENTRAL else None)
        b = simulated["nodes"].get(node, simulated["central"] if node == CENTRAL else None)
        assert abs(a["gospa"]["mean"] - b["gospa"]["mean"]) <= 1e-6 and a["idf1"] == b["idf1"], (node, a, b)
        assert a["switches"] == b["switches"] and a.get("births") == b.get("births"), (node, a, b)
    assert replayed["nodes"]["cam_w"]["gospa"]["mean"] < 1.5
    assert main(argv[:-2 * len(world.truth.paths)]) == 2          # no --truth: refused in one line
    assert "needs --truth" in capsys.readouterr().err


def test_dfusion_run_refuses_a_multi_target_scenario_in_one_line(tmp_path, capsys):
    assert main(["run", str(write(tmp_path, MULTI)), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "dfusion run does not take multi-target scenarios" in err, err
