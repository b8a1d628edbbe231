"""Switching policies: greedy with a punishment, hysteresis, blending, fusion above a floor,
selection by configuration, and the reliability models they use."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dfusion.fusion import FusionNode
from dfusion.policies import InformationFusionPolicy
from dfusion.estimation import Estimate
from dfusion.errors import ValidationError
from dfusion.models import ConstantVelocity
from dfusion.reliability import (
    covariance_error,
    covariance_reliability,
    error_from_reliability,
    isotonic_decreasing,
    NDTMap,
    reliability_from_error,
    ScoreErrorTable,
)
from dfusion.policies import (
    BlendedTransitionPolicy,
    FusionFloorPolicy,
    GreedySwitchingPolicy,
    HysteresisSwitchingPolicy,
    information_fusion,
    select_punishment,
)

FUSED = Estimate("fused", 0.0, np.zeros(2), np.eye(2) * 100.0)


def src(name, r, t=0.0, healthy=True, mean=None, cov=None):
    m = np.full(2, float(ord(name[0]))) if mean is None else np.asarray(mean, float)
    return Estimate(name, t, m, np.eye(2) * 0.01 if cov is None else np.asarray(cov, float), r, healthy)


# ------------------------------------------------------------------------------ greedy
def test_greedy_first_choice_is_the_most_reliable_and_is_not_a_switch():
    p = GreedySwitchingPolicy(0.15)
    out = p.decide(FUSED, [src("a", 0.5), src("b", 0.8), src("c", 0.7)])
    assert out.name == "b" and p.current == "b" and p.switches == []


def test_greedy_no_switch_inside_the_punishment_band():
    p = GreedySwitchingPolicy(0.15)
    p.decide(FUSED, [src("a", 0.8), src("b", 0.5)])
    assert p.current == "a"
    # b climbs to a + P exactly, then just inside: still no switch (needs R_b - P > R_a)
    for k, rb in enumerate([0.7, 0.9, 0.95, 0.949]):
        out = p.decide(FUSED, [src("a", 0.8, t=k), src("b", rb, t=k)])
        assert out.name == "a", rb
    assert p.switches == []
    out = p.decide(FUSED, [src("a", 0.8, t=9), src("b", 0.96, t=9)])
    assert out.name == "b" and p.switches == [(9.0, "a", "b")]
    # and back only when a beats b by more than P
    assert p.decide(FUSED, [src("a", 1.0, t=10), src("b", 0.9, t=10)]).name == "b"
    assert p.decide(FUSED, [src("a", 1.0, t=11), src("b", 0.8, t=11)]).name == "a"
    assert [s.to for s in p.switches] == ["b", "a"]


def test_greedy_with_zero_punishment_is_plain_greedy_and_chatters():
    p0, p = GreedySwitchingPolicy(0.0), GreedySwitchingPolicy(0.15)
    rng = np.random.default_rng(0)
    for k in range(200):
        s = [src("a", 0.7 + 0.05 * rng.standard_normal(), t=k), src("b", 0.7 + 0.05 * rng.standard_normal(), t=k)]
        p0.decide(FUSED, s)
        p.decide(FUSED, s)
    assert len(p0.switches) > 50 and len(p.switches) <= 5


def test_greedy_error_forces_a_switch_whatever_the_punishment():
    p = GreedySwitchingPolicy(0.5)
    p.decide(FUSED, [src("a", 0.9), src("b", 0.3)])
    out = p.decide(FUSED, [src("a", 0.9, t=1, healthy=False), src("b", 0.3, t=1)])
    assert out.name == "b" and p.switches[-1] == (1.0, "a", "b") and p.forced == 1
    # a recovers: it counts again, with the punishment (0.95 - 0.5 > 0.3)
    assert p.decide(FUSED, [src("a", 0.95, t=2), src("b", 0.3, t=2)]).name == "a"
    # a source that stops reporting is treated like one in error
    assert p.decide(FUSED, [src("b", 0.3, t=3)]).name == "b"


def test_greedy_no_healthy_source_falls_back():
    p = GreedySwitchingPolicy()
    p.decide(FUSED, [src("a", 0.9)])
    assert p.decide(FUSED, [src("a", 0.9, healthy=False)]) is FUSED
    hold = GreedySwitchingPolicy(fallback="hold")
    hold.decide(FUSED, [src("a", 0.9)])
    out = hold.decide(FUSED, [src("a", 0.9, healthy=False)])
    assert out.name == "a" and not out.healthy
    with pytest.raises(ValidationError):
        GreedySwitchingPolicy(-0.1)


def test_select_punishment_largest_P_within_tolerance():
    P = [0.0, 0.05, 0.1, 0.15, 0.2, 0.3]
    err = [0.10, 0.10, 0.104, 0.108, 0.13, 0.2]
    assert select_punishment(P, err, 0.1) == 0.15
    assert select_punishment(P, err, 0.0) == 0.05
    assert select_punishment(P, err, 0.1, lost=[3, 1, 1, 2, 1, 5]) == 0.1


# ------------------------------------------------------------------------------ hysteresis
def test_hysteresis_no_chattering_inside_the_band():
    p = HysteresisSwitchingPolicy("precise", "coarse", upper=0.75, lower=0.65, signal="similarity")
    srcs = lambda t, rho: [src("coarse", 0.5, t), src("precise", 0.9, t), src("similarity", rho, t)]  # noqa: E731
    assert p.decide(FUSED, srcs(0, 0.5)).name == "coarse"
    for k in range(1, 200):                       # oscillates between 0.66 and 0.74
        rho = 0.66 if k % 2 else 0.74
        assert p.decide(FUSED, srcs(k, rho)).name == "coarse"
    assert p.switches == [] and p.stage == "low"
    assert p.decide(FUSED, srcs(200, 0.76)).name == "precise"
    for k in range(201, 400):
        assert p.decide(FUSED, srcs(k, 0.66 if k % 2 else 0.74)).name == "precise"
    assert p.decide(FUSED, srcs(400, 0.64)).name == "coarse"
    assert [(s.from_, s.to) for s in p.switches] == [("coarse", "precise"), ("precise", "coarse")]


def test_hysteresis_signal_pushed_or_callable_and_moving_average():
    p = HysteresisSwitchingPolicy("p", "c", window=3)
    s = [src("c", 0.5), src("p", 0.9)]
    for v in (0.8, 0.8, 0.8):
        p.set_signal(v)
        p.decide(FUSED, s)
    assert p.current == "p"
    p.set_signal(0.3)                              # mean (0.8, 0.8, 0.3) = 0.63 < 0.65
    assert p.decide(FUSED, s).name == "c"
    q = HysteresisSwitchingPolicy("p", "c", signal=lambda fused, sources: 0.9)
    assert q.decide(FUSED, s).name == "p"
    # the selected source in error: the other one is output
    assert q.decide(FUSED, [src("c", 0.5), src("p", 0.9, healthy=False)]).name == "c"
    with pytest.raises(ValidationError):
        HysteresisSwitchingPolicy(upper=0.6, lower=0.7)


# ------------------------------------------------------------------------------ blending
def test_blend_spreads_the_jump_over_the_transition():
    inner = HysteresisSwitchingPolicy("p", "c", signal="rho")
    p = BlendedTransitionPolicy(inner, duration=1.0)
    c = lambda t: src("c", 0.5, t, mean=[0.0, 0.0], cov=np.eye(2) * 0.04)  # noqa: E731
    q = lambda t: src("p", 0.9, t, mean=[1.0, 0.0], cov=np.eye(2) * 0.0001)  # noqa: E731
    r = lambda t, v: src("rho", v, t)  # noqa: E731
    assert p.decide(FUSED, [c(0.0), q(0.0), r(0.0, 0.5)]).name == "c"
    xs = []
    for t in np.arange(0.5, 2.01, 0.25):
        out = p.decide(FUSED, [c(t), q(t), r(t, 0.9)])
        xs.append(out.mean[0])
    # switch at t = 0.5, blending until 1.5: 0, .25, .5, .75, then 1
    np.testing.assert_allclose(xs, [0.0, 0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    assert p.switches[0] == (0.5, "c", "p") and p.current == "p"
    # mixture covariance during the transition covers both estimates and the jump
    p2 = BlendedTransitionPolicy(HysteresisSwitchingPolicy("p", "c", signal="rho"), duration=1.0)
    p2.decide(FUSED, [c(0.0), q(0.0), r(0.0, 0.5)])
    p2.decide(FUSED, [c(1.0), q(1.0), r(1.0, 0.9)])
    out = p2.decide(FUSED, [c(1.5), q(1.5), r(1.5, 0.9)])
    w = 0.5
    assert out.name == "c->p"
    np.testing.assert_allclose(out.cov[0, 0], (1 - w) * 0.04 + w * 0.0001 + w * (1 - w) * 1.0)


def test_blend_switching_again_mid_transition_never_jumps():
    p = BlendedTransitionPolicy(HysteresisSwitchingPolicy("p", "c", signal="rho"), duration=1.0)
    c = lambda t: src("c", 0.5, t, mean=[0.0, 0.0])  # noqa: E731
    q = lambda t: src("p", 0.9, t, mean=[1.0, 0.0])  # noqa: E731
    r = lambda t, v: src("rho", v, t)  # noqa: E731
    p.decide(FUSED, [c(0.0), q(0.0), r(0.0, 0.5)])
    p.decide(FUSED, [c(1.0), q(1.0), r(1.0, 0.9)])               # c -> p starts
    mid = p.decide(FUSED, [c(1.5), q(1.5), r(1.5, 0.9)]).mean[0]  # 0.5
    back = p.decide(FUSED, [c(1.6), q(1.6), r(1.6, 0.1)])          # p -> c while blending
    assert mid == pytest.approx(0.5) and back.mean[0] == pytest.approx(0.5)   # starts from the last output
    assert p.decide(FUSED, [c(2.1), q(2.1), r(2.1, 0.1)]).mean[0] == pytest.approx(0.25)
    assert p.decide(FUSED, [c(2.7), q(2.7), r(2.7, 0.1)]).name == "c"
    assert [(s.from_, s.to) for s in p.switches] == [("c", "p"), ("p", "c")]


def test_blend_wraps_angles():
    p = BlendedTransitionPolicy(HysteresisSwitchingPolicy("p", "c", signal="rho"), duration=1.0, angle_indices=[2])
    a = lambda t: Estimate("c", t, np.array([0, 0, math.pi - 0.1]), np.eye(3), 0.5)  # noqa: E731
    b = lambda t: Estimate("p", t, np.array([0, 0, -math.pi + 0.1]), np.eye(3), 0.9)  # noqa: E731
    r = lambda t, v: Estimate("rho", t, np.zeros(3), np.eye(3), v)  # noqa: E731
    p.decide(FUSED, [a(0), b(0), r(0, 0.1)])
    p.decide(FUSED, [a(1), b(1), r(1, 0.9)])
    out = p.decide(FUSED, [a(1.5), b(1.5), r(1.5, 0.9)])
    assert abs(abs(out.mean[2]) - math.pi) < 1e-9      # half way along the short arc: pi


# ------------------------------------------------------------------------------ fusion floor
def test_fusion_floor_matches_a_hand_computed_information_fusion():
    a = Estimate("a", 1.0, np.array([1.0, 2.0]), np.array([[0.04, 0.01], [0.01, 0.09]]), 0.8)
    b = Estimate("b", 1.0, np.array([1.3, 1.8]), np.array([[0.25, 0.0], [0.0, 0.01]]), 0.7)
    c = Estimate("c", 1.0, np.array([9.0, 9.0]), np.eye(2) * 0.01, 0.3)          # below the floor
    d = Estimate("d", 1.0, np.array([-9.0, 9.0]), np.eye(2) * 0.01, 0.95, False)  # in error
    p = FusionFloorPolicy(floor=0.5)
    out = p.decide(FUSED, [a, b, c, d])
    # by hand: Y = A^-1 + B^-1, y = A^-1 a + B^-1 b
    Ai = np.linalg.inv(a.cov)
    Bi = np.array([[4.0, 0.0], [0.0, 100.0]])
    Y = Ai + Bi
    y = Ai @ a.mean + Bi @ b.mean
    np.testing.assert_allclose(out.cov, np.linalg.inv(Y), rtol=1e-12)
    np.testing.assert_allclose(out.mean, np.linalg.solve(Y, y), rtol=1e-12)
    assert out.name == "a+b" and p.current == ("a", "b")
    assert out.reliability == pytest.approx(1 / (math.sqrt(out.cov[0, 0] + out.cov[1, 1]) + 1))
    # the set changes when c rises above the floor: recorded as a switch
    c2 = Estimate("c", 2.0, c.mean, c.cov, 0.6)
    assert p.decide(FUSED, [a, b, c2]).name == "a+b+c"
    assert p.switches == [(2.0, ("a", "b"), ("a", "b", "c"))]
    # nothing above the floor: the most reliable healthy source
    assert FusionFloorPolicy(0.9).decide(FUSED, [a, b, c]).name == "a"
    assert FusionFloorPolicy(0.9, fallback="fused").decide(FUSED, [a, b]) is FUSED


def test_information_fusion_of_angles_wraps():
    a = Estimate("a", 0, np.array([0.0, math.pi - 0.1]), np.eye(2), 1)
    b = Estimate("b", 0, np.array([0.0, -math.pi + 0.1]), np.eye(2), 1)
    mean, _ = information_fusion([a, b], angle_indices=[1])
    assert abs(abs(mean[1]) - math.pi) < 1e-9


# ------------------------------------------------------------------------------ configuration
def _scenario(policy_a, policy_b="fusion"):
    return {
        "duration": 2.0, "dt": 0.1, "seed": 1, "window": 20,
        "target": {"motion": "constant_velocity", "q": 0.1, "initial_mean": [0, 0, 1, 0],
                   "initial_cov_diag": [1, 1, 1, 1]},
        "nodes": [{"name": "a", "sensor": "position", "std": 0.5, "policy": policy_a},
                  {"name": "b", "sensor": "position", "std": 0.5, "policy": policy_b}],
        "links": [{"between": ["a", "b"]}],
    }


def test_fusion_and_switching_selected_by_configuration():
    from dfusion.scenario import build_nodes
    from dfusion.scenario import load_scenario

    built = build_nodes(load_scenario(_scenario("greedy")))
    assert isinstance(built["a"].policy, GreedySwitchingPolicy)
    assert isinstance(built["b"].policy, InformationFusionPolicy)
    lidar = Estimate("lidar", 0.0, np.array([5.0, 5.0, 0, 0]), np.eye(4) * 0.01, 0.9)
    camera = Estimate("camera", 0.0, np.array([-5.0, 5.0, 0, 0]), np.eye(4) * 0.01, 0.6)
    for node in built.values():
        node.report_source(lidar)
        node.report_source(camera)
    out_a, out_b = built["a"].output(), built["b"].output()
    assert out_a.name == "lidar" and out_b.name == "fused"
    np.testing.assert_array_equal(out_a.mean, lidar.mean)
    np.testing.assert_array_equal(out_b.mean, built["b"].estimate()[0])
    assert not np.allclose(out_a.mean, out_b.mean)
    # the same node switched to fusion by configuration only
    again = build_nodes(load_scenario(_scenario("fusion")))["a"]
    again.report_source(lidar)
    assert again.output().name == "fused"
    # tables with parameters, including blend around hysteresis and the floor
    sc = load_scenario(_scenario({"kind": "greedy", "punishment": 0.12},
                                 {"kind": "blend", "inner": "hysteresis", "duration": 0.5, "signal": "rho"}))
    nodes = build_nodes(sc)
    assert nodes["a"].policy.punishment == 0.12
    assert isinstance(nodes["b"].policy, BlendedTransitionPolicy) and nodes["b"].policy.duration == 0.5
    assert isinstance(nodes["b"].policy.inner, HysteresisSwitchingPolicy)
    assert isinstance(build_nodes(load_scenario(_scenario({"kind": "fusion_floor", "floor": 0.4})))["a"].policy,
                      FusionFloorPolicy)
    # one policy object per node (they are stateful)
    sc2 = load_scenario(_scenario("greedy", "greedy"))
    n2 = build_nodes(sc2)
    assert n2["a"].policy is not n2["b"].policy


def test_bad_policy_parameters_name_the_key():
    from dfusion.errors import ScenarioError
    from dfusion.scenario import load_scenario

    with pytest.raises(ScenarioError, match=r"nodes\[0\].*policy.*punishment"):
        load_scenario(_scenario({"kind": "greedy", "punishment": -1}))
    with pytest.raises(ScenarioError, match="policy"):
        load_scenario(_scenario({"kind": "greedy", "volume": 11}))


def test_switching_policy_inside_a_node_sees_the_node_sources():
    node = FusionNode("n", [], ConstantVelocity(2, 0.1), window=5, prior=(0.0, np.zeros(4), np.eye(4)),
                      policy=GreedySwitchingPolicy(0.1))
    node.report_source(Estimate("x", 0.0, np.ones(4), np.eye(4), 0.7))
    node.report_source(Estimate("y", 0.0, np.ones(4) * 2, np.eye(4), 0.75))
    assert node.output().name == "y"
    node.report_source(Estimate("x", 0.1, np.ones(4), np.eye(4), 0.84))
    assert node.output().name == "y"                 # 0.84 - 0.1 = 0.74 < 0.75: stay
    node.report_source(Estimate("x", 0.2, np.ones(4), np.eye(4), 0.9))
    assert node.output().name == "x"                 # 0.9 - 0.1 = 0.8 > 0.75: switch
    assert node.policy.switches == [(0.2, "y", "x")]


# ------------------------------------------------------------------------------ reliability models
def test_covariance_model_eq_11_12():
    C = np.diag([0.09, 0.16, 5.0])
    assert covariance_error(C) == pytest.approx(0.5)
    assert covariance_reliability(C) == pytest.approx(1 / 1.5)
    assert covariance_reliability(C) == pytest.approx(1 / (math.sqrt(C[0, 0] + C[1, 1]) + 1))
    assert reliability_from_error(0.0) == 1.0
    assert error_from_reliability(reliability_from_error(0.37)) == pytest.approx(0.37)
    with pytest.raises(ValidationError):
        reliability_from_error(-1.0)


def test_score_table_is_monotone_and_clamped():
    rng = np.random.default_rng(3)
    err = rng.uniform(0.01, 1.0, 2000)
    score = 5000 * np.exp(-3 * err) * rng.lognormal(0, 0.15, err.size)     # score falls with the error
    tab = ScoreErrorTable.from_samples(score, err, bins=15)
    s = np.linspace(score.min() - 100, score.max() + 100, 500)
    e = tab.error(s)
    assert np.all(np.diff(e) <= 1e-12)                                    # monotone
    assert e[0] == pytest.approx(tab.errors[0]) and e[-1] == pytest.approx(tab.errors[-1])
    # recovers the calibration curve E = -ln(score / 5000) / 3 in the middle of the range
    mid = np.array([1000.0, 2000.0, 3000.0])
    np.testing.assert_allclose(tab.error(mid), -np.log(mid / 5000) / 3, atol=0.06)
    r = tab.reliability(mid)
    np.testing.assert_allclose(r, 1 / (tab.error(mid) + 1))
    assert np.all(np.diff(r) > 0)
    np.testing.assert_allclose(isotonic_decreasing([3, 1, 2, 0]), [3, 1.5, 1.5, 0])
    with pytest.raises(ValidationError):
        ScoreErrorTable([1.0, 2.0], [0.1, 0.2])


def test_ndt_score_is_highest_at_the_true_pose():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 400)
    walls = np.vstack([np.column_stack([t, np.zeros_like(t)]), np.column_stack([np.zeros_like(t), t]),
                       np.column_stack([t, 10 - 0.5 * t])])
    ndt = NDTMap(walls + rng.normal(0, 0.01, walls.shape), cell=0.5)
    scan = walls[::4] + rng.normal(0, 0.01, walls[::4].shape)
    s0 = ndt.score(scan)
    shifted = [ndt.score(scan, (dx, 0.0, 0.0)) for dx in (0.1, 0.2, 0.4)]
    assert s0 > shifted[0] > shifted[2]
    assert ndt.score(scan, (0.0, 0.0, 0.05)) < s0
