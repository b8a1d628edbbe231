"""WSN-RSSI nodes: the particle-filter front end, its information contributions, no double
counting, late measurements, maps, scenario keys, and Monte Carlo consistency with cameras."""
from __future__ import annotations

import copy
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from dfusion.errors import OutsideWindowError, ScenarioError
from dfusion.estimation import DelayedStateEIF
from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, RSSISensor
from dfusion.localization import WSNTracker
from dfusion.frontends import WSNFrontEnd
from dfusion.metrics import nees
from dfusion.scenario import build_front_ends
from dfusion.sim import run_scenario
from dfusion.scenario import load_scenario
from dfusion.sim import simulate_world

DATA = Path(__file__).resolve().parents[1] / "data"
RECEIVERS = [[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [0.0, 12.0], [10.0, 12.0], [20.0, 12.0]]


def wsn_scenario(duration=15.0, seed=1, cameras=True, **wsn) -> dict:
    node = {"name": "wsn", "sensor": "wsn_rssi", "receivers": RECEIVERS, "p0": -45.0, "exponent": 2.5,
            "std": 3.0, "tag_height": 1.0, "particles": 1500, "rate": 2.0, "send_period": 0.5}
    node.update(wsn)
    nodes = [node, {"name": "relay", "send_period": 0.5}]
    links = [{"between": ["relay", "wsn"], "latency": 0.05, "drop": 0.1}]
    if cameras:
        nodes.append({"name": "cam", "sensor": "camera", "position": [10.0, -3.0, 5.0], "look_at": [10.0, 5.0],
                      "fx": 600.0, "pixel_std": 3.0, "rate": 5.0, "detection": 0.9, "send_period": 0.5})
        links.append({"between": ["relay", "cam"], "latency": 0.05, "drop": 0.1})
    return {
        "duration": duration, "dt": 0.1, "seed": seed, "window": 80,
        "target": {"motion": "constant_velocity", "q": 0.005, "initial_mean": [3.0, 6.0, 1.0, 0.0],
                   "initial_cov_diag": [0.5, 0.5, 0.02, 0.02]},
        "nodes": nodes, "links": links,
    }


def _drive(sc, front: WSNFrontEnd, node: FusionNode, until: float | None = None) -> None:
    for m in sorted(simulate_world(sc).measurements, key=lambda m: (m.arrival, m.t)):
        if m.node != "wsn" or (until is not None and m.t > until):
            continue
        node.predict(m.t)
        front.process(node, m.t, m.z)


def _wsn_node(sc, neighbors=()) -> FusionNode:
    return FusionNode("wsn", list(neighbors), sc.target.motion, window=sc.window,
                      prior=(0.0, sc.target.initial_mean, sc.target.initial_cov))


# ----------------------------------------------------------------------------- the particle filter
def test_particle_filter_converges_on_a_known_field():
    # a broad prior: the truth starts about 2 m from its mean
    d = wsn_scenario(duration=12.0, seed=3, cameras=False, particles=3000)
    d["target"]["initial_cov_diag"] = [4.0, 4.0, 0.1, 0.1]
    sc = load_scenario(d)
    w = simulate_world(sc)
    front = build_front_ends(sc)["wsn"]
    assert isinstance(front, WSNFrontEnd)
    node = _wsn_node(sc)
    start_err = np.hypot(*(sc.target.initial_mean[:2] - w.states[0, :2]))
    errs, node_errs = [], []
    for m in sorted(w.measurements, key=lambda m: (m.arrival, m.t)):
        node.predict(m.t)
        front.process(node, m.t, m.z)
        errs.append(np.hypot(*(front.estimate()[0] - w.truth(m.t)[:2])))
        node_errs.append(np.hypot(*(node.estimate()[0][:2] - w.truth(m.t)[:2])))
    assert start_err > 1.0
    assert np.mean(errs[-10:]) < 0.8, errs[-10:]          # about 1 m or better, as in URUS
    assert np.mean(node_errs[-10:]) < 0.8, node_errs[-10:]
    assert front.stats.measurements == len(errs) == front.stats.contributions
    assert front.stats.readings == 6 * len(errs)
    # the node's Gaussian and the particle filter's own fit agree (same readings, same prior)
    pf_mean, pf_cov = front.estimate()
    mean, cov = node.estimate()
    assert np.hypot(*(pf_mean - mean[:2])) < 0.3
    assert np.allclose(np.sqrt(np.diag(cov)[:2]), np.sqrt(np.diag(pf_cov)), rtol=0.5)


def test_contributions_are_position_information_embedded_in_the_state():
    sc = load_scenario(wsn_scenario(cameras=False, duration=5.0))
    front = build_front_ends(sc)["wsn"]
    node = _wsn_node(sc)
    _drive(sc, front, node)
    own = node.own_information()
    assert len(own) == front.stats.contributions > 5
    for t, Lam, y in own:
        assert np.all(Lam[2:, :] == 0) and np.all(Lam[:, 2:] == 0) and np.all(y[2:] == 0)
        assert np.linalg.eigvalsh(Lam[:2, :2]).min() >= -1e-12
        assert np.trace(Lam) > 0


def test_wsn_information_reaches_the_network_once():
    """The relay ends up with exactly the WSN's own information: not lost, not counted twice."""
    sc = load_scenario(wsn_scenario(cameras=False, duration=6.0))
    front = build_front_ends(sc)["wsn"]
    wsn = _wsn_node(sc, ["relay"])
    relay = FusionNode("relay", ["wsn"], sc.target.motion, window=sc.window,
                       prior=(0.0, sc.target.initial_mean, sc.target.initial_cov))
    T = 6.0
    for m in sorted(simulate_world(sc).measurements, key=lambda m: (m.arrival, m.t)):
        wsn.predict(m.t)
        relay.predict(m.t)
        front.process(wsn, m.t, m.z)
        if round(m.t * 2) % 2 == 0:          # exchange every second, both ways
            relay.receive(wsn.message_to("relay"))
            wsn.receive(relay.message_to("wsn"))
    wsn.predict(T)
    relay.predict(T)
    for _ in range(3):                       # repeated messages change nothing
        relay.receive(wsn.message_to("relay"))
        wsn.receive(relay.message_to("wsn"))
    # an independent filter given the WSN's contributions once
    ref = DelayedStateEIF(sc.target.motion, 1000)
    ref.initialize(0.0, sc.target.initial_mean, sc.target.initial_cov)
    for t in sorted({float(t) for t, _, _ in wsn.own_information()} | {T}):
        ref.predict(t)
    for t, Lam, y in wsn.own_information():
        ref.add_information(t, Lam, y)
    for node in (wsn, relay):
        mean, cov = node.estimate()
        rm, rc = ref.estimate()
        assert np.allclose(mean, rm, atol=1e-8) and np.allclose(cov, rc, atol=1e-8)


def test_late_measurements_are_skipped_and_counted():
    sc = load_scenario(wsn_scenario(cameras=False, duration=5.0))
    front = build_front_ends(sc)["wsn"]
    node = _wsn_node(sc)
    w = simulate_world(sc)
    ms = [m for m in w.measurements if m.node == "wsn"]
    node.predict(ms[3].t)
    assert front.process(node, ms[3].t, ms[3].z)
    assert not front.process(node, ms[1].t, ms[1].z)      # older than the particles
    assert front.stats.late == 1 and front.stats.contributions == 1
    assert front.time == ms[3].t
    for k in range(1, 101):                                # 80-state window: now [2.1, 10]
        node.predict(ms[3].t + 0.1 * k)
    with pytest.raises(OutsideWindowError):
        front.process(node, ms[0].t, ms[0].z)
    assert front.stats.refused == 1


def test_large_particle_sets_match_direct_computations():
    """20,000 particles, 12 receivers: the row-blocked products (single-threaded BLAS) and the ESS
    against plain per-particle formulas."""
    rng = np.random.default_rng(5)
    rec = np.column_stack([rng.uniform(0, 20, 12), rng.uniform(0, 15, 12), rng.uniform(1, 3, 12)])
    sensors = [RSSISensor(rec[j], -50.0 - j, 1.8 + 0.1 * j, 3.0 + 0.2 * j, height=1.5) for j in range(12)]
    t = WSNTracker(sensors, 20000, motion="constant_velocity", q=0.05, seed=3)
    t.initialize(mean=[10.0, 7.0], cov=np.diag([16.0, 9.0]))
    n = t.particles.shape[0]
    assert n == 20000
    # CV prediction: x + dt v + w with w = L e, e the tracker's own standard normal draws
    x0 = t.particles.copy()
    draws = copy.deepcopy(t.pf.rng).standard_normal((n, 4))
    dt = 0.4
    t.predict(t.time + dt)
    L = np.linalg.cholesky(ConstantVelocity(2, 0.05).Q(dt))
    want = x0 + np.hstack([dt * x0[:, 2:], np.zeros((n, 2))]) + np.einsum("ij,nj->ni", L, draws)
    np.testing.assert_allclose(t.particles, want, rtol=1e-12, atol=1e-12)
    # likelihood of 12 readings (two missing) against RSSISensor.h, particle by particle
    z = -70.0 + 8.0 * rng.standard_normal(12)
    z[[3, 8]] = np.nan
    ll = t.log_likelihood(z)
    ok = np.isfinite(z)
    for i in rng.choice(n, 200, replace=False).tolist() + [0, n - 1]:
        mu = np.array([s.h(t.particles[i])[0] for s in sensors])
        std = np.array([s.std[0] for s in sensors])
        assert ll[i] == pytest.approx(-0.5 * np.sum(((z[ok] - mu[ok]) / std[ok]) ** 2), rel=1e-9)
    # ESS = 1 / sum w^2, summed exactly
    t.update(t.time, z)
    w = np.exp(t.pf.log_weights)
    assert t.pf.ess == pytest.approx(1.0 / math.fsum((w / math.fsum(w)) ** 2), rel=1e-9)


# ----------------------------------------------------------------------------- maps
def test_obstacle_map_keeps_particles_out_of_obstacles():
    box = [8.0, 8.0, 12.0, 11.0]
    sc = load_scenario(wsn_scenario(cameras=False, duration=6.0, obstacles=[box],
                                    map_bounds=[-2.0, -2.0, 22.0, 14.0], map_cell=0.25))
    front = build_front_ends(sc)["wsn"]
    grid = front.tracker.grid
    assert grid is not None and grid.is_occupied(np.array([10.0, 9.5])) and not grid.is_occupied(np.array([3.0, 6.0]))
    node = _wsn_node(sc)
    _drive(sc, front, node)
    p = front.tracker.particles
    inside = (p[:, 0] > box[0]) & (p[:, 0] < box[2]) & (p[:, 1] > box[1]) & (p[:, 1] < box[3])
    assert not inside.any()
    assert front.stats.contributions > 5


def test_occ_map_file_relative_to_the_scenario(tmp_path):
    shutil.copy(DATA / "ble_rssi" / "occ" / "tetam_0.2.occ", tmp_path / "area.occ")
    d = wsn_scenario(cameras=False, duration=1.0, map="area.occ")
    path = tmp_path / "s.scenario.toml"
    path.write_text(_toml(d))
    sc = load_scenario(path)
    grid = build_front_ends(sc)["wsn"].tracker.grid
    assert grid is not None and grid.cell == pytest.approx(0.2)
    d["nodes"][0]["map"] = "missing.occ"
    path.write_text(_toml(d))
    with pytest.raises(ScenarioError, match="map"):
        load_scenario(path)


def _toml(d: dict) -> str:
    def val(v):
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)

    lines = [f"{k} = {val(v)}" for k, v in d.items() if not isinstance(v, (dict, list))]
    lines.append("[target]")
    lines += [f"{k} = {val(v)}" for k, v in d["target"].items()]
    for section in ("nodes", "links"):
        for tbl in d[section]:
            lines.append(f"[[{section}]]")
            lines += [f"{k} = {val(v)}" for k, v in tbl.items()]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("change, words", [
    ({"receivers": [[0, 0, 0, 0]]}, "receivers"),
    ({"receivers": [[0, 0], [1, 1, 1]]}, "receivers"),
    ({"std": [3.0, 3.0]}, "std"),
    ({"exponent": 0}, "exponent"),
    ({"particles": 1}, "particles"),
    ({"pf_motion": "teleport"}, "pf_motion"),
    ({"pf_information": "exact"}, "pf_information"),
    ({"obstacles": [[0, 0, 1, 1]]}, "map_bounds"),
    ({"map_cell": 0.5}, "map_cell"),
    ({"antenna": "yagi"}, "antenna"),
])
def test_bad_wsn_keys_raise_scenario_errors(change, words):
    with pytest.raises(ScenarioError) as info:
        load_scenario(wsn_scenario(**change))
    assert words in str(info.value) and "wsn" in str(info.value)


# ----------------------------------------------------------------------------- consistency
RUNS = 8


def test_cameras_and_wsn_fused_consistently_monte_carlo():
    """Average NEES of every node over RUNS seeds inside the chi-square 95% interval (no double counting)."""
    base = wsn_scenario(duration=15.0)
    per: dict[str, list[np.ndarray]] = {}
    seen = 0
    for r in range(RUNS):
        sc = load_scenario(copy.deepcopy(base), seed=200 + r)
        res = run_scenario(sc)
        seen += sum(1 for m in res.world.measurements if m.node == "cam")
        for name in res.node_mean:
            per.setdefault(name, []).append(nees(res.node_mean[name], res.node_cov[name], res.truth)[1:])
        for v in res.metrics["nodes"].values():
            # PF contributions vs the plain EKF on every true detection (the oracle reference: no clutter
            # here): 0.038 at most (seeds 200-207); naive fusion (double counting) gives 0.07-0.12 at
            # seeds 200-202 while its ANEES stays inside the interval below. (The fair reference gates
            # like the camera node, on its own filtered estimate: at seed 200 it gates one detection
            # with d^2 = 9.22 that the node, gating on its smoothed estimate, fuses; gap 0.095.)
            assert v["final_gap_oracle"] < 0.06
    assert seen > 50                              # the camera saw the target in these runs
    lo, hi = chi2.ppf(0.025, 4 * RUNS) / RUNS, chi2.ppf(0.975, 4 * RUNS) / RUNS
    for name, v in per.items():
        anees = float(np.mean(v))
        assert lo <= anees <= hi, (name, anees, (lo, hi))
