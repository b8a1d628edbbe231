"""Component life cycle (switching paper, Fig. 6b) and the supervisor."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from dfusion.fusion import FusionNode
from dfusion.estimation import Estimate
from dfusion.models import ConstantVelocity
from dfusion.policies import Component, GreedySwitchingPolicy, InvalidTransition, State, Supervisor, TRANSITIONS


def est(name, t, r=0.8):
    return Estimate(name, t, np.array([t, 0.0]), np.eye(2) * 0.01, r)


def test_valid_life_cycle():
    c = Component("laser", clock=lambda: 0.0)
    assert c.state is State.CREATED
    c.initialize(0.0)
    assert c.state is State.READY
    assert c.activate(1.0) and c.state is State.ACTIVE
    c.deactivate(2.0)
    assert c.state is State.READY
    c.activate(3.0)
    c.fail("core algorithm diverged", 4.0)
    assert c.state is State.ERROR and c.error_reason == "core algorithm diverged" and c.failures == 1
    assert c.reset(5.0) and c.state is State.READY and c.restarts == 1
    path = [(e.from_.value, e.to.value) for e in c.history]
    assert path == [("created", "ready"), ("ready", "active"), ("active", "ready"), ("ready", "active"),
                    ("active", "error"), ("error", "reset"), ("reset", "ready")]


def test_every_transition_outside_the_table_raises():
    allowed = {(a, b) for a, tos in TRANSITIONS.items() for b in tos}
    assert allowed == {
        (State.CREATED, State.READY), (State.READY, State.ACTIVE), (State.READY, State.ERROR),
        (State.ACTIVE, State.READY), (State.ACTIVE, State.ERROR), (State.ERROR, State.RESET),
        (State.RESET, State.READY), (State.RESET, State.ERROR),
    }
    for a, b in itertools.product(State, State):
        c = Component("x", clock=lambda: 0.0)
        c.state = a
        if (a, b) in allowed:
            c.transition(b)
            assert c.state is b
        else:
            with pytest.raises(InvalidTransition):
                c.transition(b)
            assert c.state is a                       # unchanged


def test_operations_in_the_wrong_state_raise():
    c = Component("cam", clock=lambda: 0.0)
    with pytest.raises(InvalidTransition):
        c.activate()                                   # created -> active skips ready
    with pytest.raises(InvalidTransition):
        c.fail()                                       # created -> error
    c.initialize()
    with pytest.raises(InvalidTransition):
        c.reset()                                      # ready -> reset
    with pytest.raises(InvalidTransition):
        c.deactivate()
    with pytest.raises(InvalidTransition):
        c.initialize()


def test_hooks_failing_send_the_component_to_error():
    def boom():
        raise RuntimeError("no device")

    c = Component("kinect", on_activate=boom, clock=lambda: 0.0)
    c.initialize()
    assert not c.activate(1.0) and c.state is State.ERROR and "no device" in c.error_reason
    c.on_reset = boom
    assert not c.reset(2.0) and c.state is State.ERROR   # error -> reset -> error
    assert [e.to for e in c.history][-2:] == [State.RESET, State.ERROR]


def test_supervisor_restarts_a_failed_component_and_keeps_it_off_the_candidates():
    ok = {"laser": True}
    laser = Component("laser", health=lambda: ok["laser"])
    cam = Component("camera")
    sup = Supervisor([laser, cam], restart_delay=2.0)
    sup.start(0.0)
    assert laser.active and cam.active
    laser.report(est("laser", 0.0, 0.9), 0.0)
    cam.report(est("camera", 0.0, 0.6), 0.0)
    node = FusionNode("robot", [], ConstantVelocity(1, 0.1), window=5, prior=(0.0, np.zeros(2), np.eye(2)),
                      policy=GreedySwitchingPolicy(0.1))
    sup.report_to(node, 0.5)
    assert node.output().name == "laser"
    ok["laser"] = False                                # the core algorithm fails
    sup.report_to(node, 1.0)
    assert laser.state is State.ERROR
    assert node.sources["laser"].healthy is False
    assert node.output().name == "camera" and node.policy.forced == 1
    ok["laser"] = True
    sup.report_to(node, 2.0)                           # restart_delay not over: still in error
    assert laser.state is State.ERROR and node.output().name == "camera"
    sup.report_to(node, 3.0)                           # error -> reset -> ready -> active
    assert laser.state is State.ACTIVE and laser.restarts == 1
    # active again, but healthy only once it has reported a new estimate
    assert node.sources["laser"].healthy is False and node.output().name == "camera"
    laser.report(est("laser", 3.1, 0.9), 3.1)
    sup.report_to(node, 3.2)
    assert node.sources["laser"].healthy is True
    assert node.output().name == "laser"               # 0.9 - 0.1 > 0.6
    kinds = [(e.component, e.to.value) for e in sup.events if e.t >= 1.0]
    assert kinds == [("laser", "error"), ("laser", "reset"), ("laser", "ready"), ("laser", "active")]


def test_supervisor_heartbeat_timeout_and_max_restarts():
    c = Component("depth", heartbeat_timeout=0.5)
    sup = Supervisor([c], max_restarts=1)
    sup.start(0.0)
    c.heartbeat(0.4)
    sup.check(0.8)
    assert c.active                                    # 0.4 s since the last heartbeat
    sup.check(1.0)                                     # 0.6 s: failed, restarted at once (no delay)
    assert c.active and c.failures == 1 and c.restarts == 1
    sup.check(1.6)                                     # fails again; max_restarts reached
    assert c.state is State.ERROR and c.failures == 2
    sup.check(5.0)
    assert c.state is State.ERROR
    # a health callback that raises counts as a failure
    d = Component("cam", health=lambda: 1 / 0)
    s2 = Supervisor([d], restart=False)
    s2.start(0.0)
    s2.check(0.1)
    assert d.state is State.ERROR and "ZeroDivisionError" in d.error_reason


def test_reports_are_ignored_unless_active_and_renamed():
    c = Component("gps", clock=lambda: 0.0)
    c.report(est("gps", 0.0))
    assert c.source() is None
    c.initialize(0.0)
    c.activate(0.0)
    c.report(est("other-name", 1.0), 1.0)
    assert c.source().name == "gps" and c.source().healthy
