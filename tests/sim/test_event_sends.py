"""Event-triggered sends (dfusion.fusion.sending): news crosses a chain within its latency, the
minimum interval per link holds, the periodic heartbeat stays; checked against filterpy's Kalman
filter as the independent reference."""
from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from dfusion.errors import ScenarioError, ValidationError
from dfusion.fusion import FusionNode
from dfusion.fusion.sending import MIN_SEND_INTERVAL, SendSchedule
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.scenario import load_scenario
from dfusion.sim import run_scenario, runner

ROOT = Path(__file__).resolve().parents[2]


def chain(**over) -> dict:
    """a - b - c, wired (10 ms); only ``a`` measures (every step); b and c relay and listen."""
    d = {
        "duration": 6.0, "dt": 0.1, "seed": 3, "window": 200,
        "target": {"motion": "constant_velocity", "q": 0.5, "initial_mean": [0, 0, 1, 0],
                   "initial_cov_diag": [4, 4, 1, 1]},
        "nodes": [
            {"name": "a", "sensor": "position", "std": 0.3, "rate": 10.0, "send_period": 0.5},
            {"name": "b", "sensor": "none", "send_period": 0.5},
            {"name": "c", "sensor": "none", "send_period": 0.5},
        ],
        "links": [{"between": ["a", "b"], "latency": 0.01}, {"between": ["b", "c"], "latency": 0.01}],
    }
    d.update(over)
    return d


def kalman_reference(sc, meas, times) -> list:
    """filterpy's Kalman filter over ``meas`` (time order) at every time of ``times``: returns a
    function ``k, upto -> (mean, cov)``: the filter of the measurements with ``arrival <= upto``,
    predicted to ``times[k]``."""
    motion = sc.target.motion
    sensor = sc.nodes["a"].sensor

    def at(k: int, upto: float):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.x = np.array(sc.target.initial_mean, dtype=float).reshape(4, 1)
        kf.P = np.array(sc.target.initial_cov, dtype=float)
        kf.H = sensor.H(np.zeros(4))
        kf.R = sensor.R
        t_prev = 0.0
        for t in times[1:k + 1]:
            kf.F, kf.Q = motion.F(t - t_prev), motion.Q(t - t_prev)
            kf.predict()
            for m in meas:
                if abs(m.t - t) < 1e-9 and m.arrival <= upto + 1e-9:
                    kf.update(np.asarray(m.z).reshape(2, 1))
            t_prev = t
        # a measurement at t = 0 (before the first prediction) is fused at the first step
        return kf.x.ravel(), kf.P

    return at


def test_event_sends_bring_the_end_of_a_chain_to_the_centralized_estimate_within_the_latency():
    ev = run_scenario(load_scenario(chain(), sends="event"))
    pe = run_scenario(load_scenario(chain(), sends="periodic"))
    sc = ev.scenario
    meas = [m for m in ev.world.measurements if m.node == "a"]
    assert all(abs(m.t - round(m.t / sc.dt) * sc.dt) < 1e-9 and m.t > 0 for m in meas) and len(meas) > 50
    ref = kalman_reference(sc, meas, ev.times)
    gaps_ev, gaps_pe = [], []
    for k in range(2, len(ev.times)):
        t = float(ev.times[k])
        # a has its own measurements up to now; c has a's up to the previous step: a's message of
        # step k-1 crossed both hops (2 x 10 ms) before step k
        mean_a, cov_a = ref(k, t)
        np.testing.assert_allclose(ev.node_mean["a"][k], mean_a, rtol=0, atol=1e-8)
        np.testing.assert_allclose(ev.node_cov["a"][k], cov_a, rtol=1e-7, atol=1e-10)
        mean_c, cov_c = ref(k, float(ev.times[k - 1]))
        np.testing.assert_allclose(ev.node_mean["c"][k], mean_c, rtol=0, atol=1e-8)
        np.testing.assert_allclose(ev.node_cov["c"][k], cov_c, rtol=1e-7, atol=1e-10)
        gaps_ev.append(np.linalg.norm(ev.node_mean["c"][k][:2] - mean_c[:2]))
        gaps_pe.append(np.linalg.norm(pe.node_mean["c"][k][:2] - mean_c[:2]))
    # periodic sends lag: c is behind the one-step reference at most steps, and further from
    # the centralized EKF (which has every measurement at once) on average
    assert np.mean(np.array(gaps_pe) > 1e-6) > 0.8
    central = ev.central_mean[2:, :2]
    err_ev = np.linalg.norm(ev.node_mean["c"][2:, :2] - central, axis=1).mean()
    err_pe = np.linalg.norm(pe.node_mean["c"][2:, :2] - central, axis=1).mean()
    assert err_pe > 2 * err_ev > 0
    # and the centralized reference of the run is the same Kalman filter on everything so far
    mean_all, _ = ref(len(ev.times) - 1, math.inf)
    np.testing.assert_allclose(ev.central_mean[-1], mean_all, atol=1e-8)


def test_the_minimum_interval_per_link_holds_in_a_storm_of_news(monkeypatch):
    """Both ends measure at 100 Hz (dt = 10 ms): news every step; no link carries two messages of a
    node less than the minimum interval apart, and the heartbeat goes on."""
    sent: dict[tuple[str, str], list[float]] = {}
    real_send = runner.SimulatedNetwork.send

    def spy(self, src, dst, data, t):
        sent.setdefault((src, dst), []).append(float(t))
        return real_send(self, src, dst, data, t)

    monkeypatch.setattr(runner.SimulatedNetwork, "send", spy)
    d = chain(duration=3.0, dt=0.01, window=400, min_send_interval=0.07)
    d["nodes"][0]["rate"] = 100.0
    d["nodes"][2] = {"name": "c", "sensor": "position", "std": 0.3, "rate": 100.0, "send_period": 0.5}
    res = run_scenario(load_scenario(d, sends="event"))
    assert set(sent) == {("a", "b"), ("b", "a"), ("b", "c"), ("c", "b")}
    for link, times in sent.items():
        gaps = np.diff(times)
        assert gaps.min() >= 0.07 - 1e-9, link
        assert len(times) <= 3.0 / 0.07 + 1, link
        assert len(times) >= 3.0 / 0.07 - 3, link   # news all the time: the limit is what holds it back
    # every node ends on the centralized estimate (the final lossless rounds), consistent
    for nm, v in res.metrics["nodes"].items():
        assert v["final_gap"] < 1e-6, nm
    assert res.metrics["sends"]["event_messages"] > 0
    # both directions, each at most duration / interval + 1 messages over the 3 s
    assert res.metrics["sends"]["messages_per_link_per_s"]["max"] <= 2 * (3.0 / 0.07 + 1) / 3.0 + 1e-9


def test_schedule_heartbeat_interval_and_news_on_one_node():
    motion = ConstantVelocity(2, 0.1)
    sensor = PositionSensor(2, 0.5)
    node = FusionNode("a", ["b", "c"], motion, window=100, prior=(0.0, np.zeros(4), np.eye(4)))
    sched = SendSchedule(0.5, 0.2, "event")
    assert sched.ack_lag == 2 * math.ceil(0.5 / 0.2)
    log: list[tuple[float, str]] = []
    rng = np.random.default_rng(0)
    for k in range(1, 31):
        t = round(0.1 * k, 9)
        node.predict(t)
        if k <= 10:   # news for both links every 0.1 s in the first second, none after
            node.update(t, rng.normal(size=2), sensor)
        log += [(t, j) for j, _ in sched.due(node, t)]
    assert node.ack_lag == sched.ack_lag
    for j in ("b", "c"):
        times = [t for t, nb in log if nb == j]
        assert min(np.diff(times)) >= 0.2 - 1e-9
        # the first second: news at most every 0.2 s (the heartbeats at 0.5 and 1.0 fall inside an
        # interval: a message went less than 0.2 s before); the news of t = 1.0 goes when its
        # interval ends (1.1); then only the heartbeat, every 0.5 s
        assert [t for t in times if t <= 1.0] == [0.1, 0.3, 0.5, 0.7, 0.9]
        assert [t for t in times if t > 1.0] == [1.1, 1.5, 2.0, 2.5, 3.0]
    # news waiting for the interval is due at its end
    node.predict(3.1)
    node.update(3.1, rng.normal(size=2), sensor)
    assert sched.due(node, 3.1) == []
    assert sched.next_event(node) == pytest.approx(3.2)
    assert [j for j, _ in sched.due(node, 3.2)] == ["b", "c"]
    assert sched.next_event(node) == math.inf
    # periodic: no news sends
    per = SendSchedule(0.5, 0.2, "periodic", first=3.5)
    node.predict(3.3)
    node.update(3.3, rng.normal(size=2), sensor)
    assert per.due(node, 3.3) == [] and per.next_event(node) == math.inf
    assert [j for j, _ in per.due(node, 3.5)] == ["b", "c"]   # the period


@pytest.mark.parametrize("args", [(0.0, 0.05, "event"), (0.5, -0.1, "event"), (0.5, 0.05, "sometimes"),
                                  (math.inf, 0.05, "event")])
def test_schedule_refuses_bad_settings(args):
    with pytest.raises(ValidationError):
        SendSchedule(*args)


def test_scenario_keys_and_defaults():
    sc = load_scenario(chain())
    assert (sc.sends, sc.min_send_interval) == ("periodic", MIN_SEND_INTERVAL)
    sc = load_scenario(chain(sends="event", min_send_interval=0.2))
    assert (sc.sends, sc.min_send_interval) == ("event", 0.2)
    assert load_scenario(chain(sends="event"), sends="periodic", min_send_interval=0.0).sends == "periodic"
    urus = load_scenario(ROOT / "topologies" / "urus-mobile.scenario.toml")
    assert (urus.sends, urus.min_send_interval) == ("event", MIN_SEND_INTERVAL)
    with pytest.raises(ScenarioError, match="sends"):
        load_scenario(chain(sends="often"))
    with pytest.raises(ScenarioError, match="min_send_interval"):
        load_scenario(chain(min_send_interval=-1))


def _waypoint_position(points: list[list[float]], speed: float, loop: bool, t: float) -> tuple[float, float]:
    """Where a robot is at ``t`` on its waypoint path, by hand (a reference for ``LinkSchedule``)."""
    pts = [tuple(p) for p in points] + ([tuple(points[0])] if loop else [])
    lengths = [math.dist(a, b) for a, b in pairwise(pts)]
    s = speed * t
    if loop:
        s %= sum(lengths)
    for (a, b), seg in zip(pairwise(pts), lengths):
        if s <= seg:
            u = s / seg
            return (a[0] + u * (b[0] - a[0]), a[1] + u * (b[1] - a[1]))
        s -= seg
    return pts[-1]


def test_urus_mobile_covers_the_robots_routes_so_they_hand_over_and_are_never_alone():
    """The URUS-style scenario's radio coverage (docs/dynamic-topology.md, "Why it is shaped so"):
    from the TOML alone (positions, paths, ranges; the link rule "distance at most the smaller
    range"), every robot has a radio link at every step of the run and the robots' links change
    at least ten times (handovers), and the scenario's LinkSchedule gives the same links."""
    import tomllib

    from dfusion.scenario.links import LinkSchedule

    path = ROOT / "topologies" / "urus-mobile.scenario.toml"
    raw = tomllib.loads(path.read_text())
    kind_range = raw["radio"]["ranges"]
    nodes = {n["name"]: n for n in raw["nodes"]}
    ranges = {name: n.get("radio_range", kind_range.get(n.get("sensor"))) for name, n in nodes.items()}
    ranges = {k: v for k, v in ranges.items() if v is not None}
    robots = [name for name, n in nodes.items() if "path" in n]
    assert sorted(robots) == ["robot1", "robot2"]

    def positions(t):
        out = {}
        for name, n in nodes.items():
            if "path" in n:
                out[name] = _waypoint_position(n["path"], n["speed"], n.get("loop", False), t)
            elif "position" in n:
                out[name] = tuple(n["position"][:2])
        return out

    sched = LinkSchedule(load_scenario(path))
    wired = {tuple(sorted(x["between"])) for x in raw["links"]}
    prev, downs = None, 0
    for k in range(round(raw["duration"] / raw["dt"]) + 1):
        t = round(k * raw["dt"], 9)
        pos = positions(t)
        radio = {tuple(sorted((a, b))) for a in ranges for b in ranges
                 if a < b and math.dist(pos[a], pos[b]) <= min(ranges[a], ranges[b])}
        for r in robots:
            assert any(r in pair for pair in radio), f"{r} has no link at t={t}"
        assert sched.links(t) == radio | wired, t
        if prev is not None:
            downs += len(prev - radio)
        prev = radio
    assert downs >= 10


def test_urus_mobile_person_starts_in_a_fixed_cameras_view():
    """The URUS-style scenario starts the person inside the covered area (docs/dynamic-topology.md,
    "Margin on every seed"): the prior's mean and its whole 3-sigma circle project into cam_w's
    640 x 480 image. Checked by a pinhole projection written here from the TOML (camera axis
    towards look_at on the ground, image x to the right, image y down; Hartley & Zisserman),
    not by the scenario's camera model; robot1 starts 5.5 m behind the mean at its pace."""
    import tomllib

    raw = tomllib.loads((ROOT / "topologies" / "urus-mobile.scenario.toml").read_text())
    cam = next(n for n in raw["nodes"] if n["name"] == "cam_w")
    C = np.array(cam["position"], dtype=float)
    look = np.array([*cam["look_at"], 0.0])
    z = (look - C) / np.linalg.norm(look - C)            # optical axis
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)                               # image right (horizontal)
    y = np.cross(z, x)                                   # image down
    f, w, h = cam["fx"], cam.get("width", 640), cam.get("height", 480)

    def in_image(px: float, py: float) -> bool:
        d = np.array([px, py, 0.0]) - C
        pc = np.array([d @ x, d @ y, d @ z])
        if pc[2] <= 0:
            return False
        u, v = f * pc[0] / pc[2] + w / 2, f * pc[1] / pc[2] + h / 2
        return 0 <= u <= w and 0 <= v <= h

    mean = raw["target"]["initial_mean"]
    sd = np.sqrt(raw["target"]["initial_cov_diag"][:2])
    circle = [(mean[0] + 3 * sd[0] * math.cos(a), mean[1] + 3 * sd[1] * math.sin(a))
              for a in np.linspace(0, 2 * math.pi, 36, endpoint=False)]
    assert all(in_image(px, py) for px, py in [tuple(mean[:2])] + circle)
    # a point well outside the view is refused (the projection is not vacuous)
    assert not in_image(mean[0] - 6.0, mean[1])
    robot1 = next(n for n in raw["nodes"] if n["name"] == "robot1")
    assert math.dist(robot1["path"][0], mean[:2]) == pytest.approx(5.5)
    assert robot1["speed"] == pytest.approx(math.hypot(mean[2], mean[3]))
