"""Multi-target scenario files ([[targets]], [tracking]): a good file, and every mistake refused in one line."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfusion.scenario import load_scenario
from tests.scenario.test_loader import GOOD as SINGLE_TARGET
from tests.scenario.test_loader import error_of, write

ROOT = Path(__file__).resolve().parents[2]

#: Two people crossing, a robot that waits where one of them passes, two cameras with
#: overlapping views, a tag reader, a link outage (also run by tests/sim/test_tracking_runner.py).
MULTI = """\
duration = 12.0
dt = 0.1
seed = 3
window = 60

[tracking]
associator = "jpda"
q = 0.05
region = [0.0, 20.0, 0.0, 10.0]

[tracking.initiator]
confirm = [3, 5]
velocity_std = 1.5

[tracking.deleter]
max_age = 4.0
max_misses = 5

[tracking.merge]
confirm = 3

[[targets]]
name = "ann"
path = [[0.0, 3.0], [20.0, 3.0]]
speed = 1.2

[[targets]]
name = "bob"
path = [[20.0, 7.0], [0.0, 7.0]]
speed = 1.0
appear = 1.0

[[targets]]
name = "rob"
kind = "robot"
path = [[10.0, 0.0], [10.0, 2.5]]
speed = 0.5
leave = 12.0
meets = "ann"

[[nodes]]
name = "cam_w"
sensor = "detections"
view = [0.0, 11.0, 0.0, 10.0]
clutter = 0.3
detection = 0.9
rate = 10.0
send_period = 0.2

[[nodes]]
name = "cam_e"
sensor = "detections"
view = [9.0, 20.0, 0.0, 10.0]
clutter = 0.3
detection = 0.9
rate = 10.0
send_period = 0.2

[[nodes]]
name = "wsn"
sensor = "tags"
targets = ["bob"]
std = 1.0
rate = 2.0
send_period = 0.2

[[links]]
between = ["cam_w", "cam_e"]
latency = 0.05

[[links]]
between = ["cam_e", "wsn"]
latency = 0.05
outages = [[5.0, 7.0]]
"""


def test_a_multi_target_scenario_loads_with_its_targets_tracker_and_rendezvous(tmp_path):
    sc = load_scenario(write(tmp_path, MULTI))
    assert sc.multi_target and [t.name for t in sc.targets] == ["ann", "bob", "rob"]
    ann, bob, rob = sc.targets
    assert (ann.kind, rob.kind) == ("person", "robot")
    assert ann.appear == 0.0 and ann.leave == 12.0                # 20 m at 1.2 m/s: still walking at the end
    assert bob.appear == 1.0 and bob.leave == pytest.approx(12.0)
    np.testing.assert_allclose(bob.position(6.0), [15.0, 7.0])     # 5 s after it appeared, at 1 m/s
    tr = sc.tracking
    assert (tr.associator, tr.confirm, tr.max_age, tr.max_misses, tr.merge_confirm) == ("jpda", (3, 5), 4.0, 5, 3)
    assert tr.region == (0.0, 20.0, 0.0, 10.0) and tr.inside(np.array([1.0, 1.0])) and not tr.inside([21.0, 1.0])
    # the rendezvous, computed by hand: rob waits at (10, 2.5) from t = 5 s; ann is at x = 10 at t = 8.33 s
    (rv,) = sc.rendezvous
    assert (rv.robot, rv.person) == ("rob", "ann") and abs(rv.t - 10.0 / 1.2) <= 0.05 and rv.distance == pytest.approx(0.5, abs=0.01)
    assert sc.nodes["cam_w"].sensor_kind == "detections" and sc.nodes["wsn"].params["targets"] == ["bob"]
    assert sc.outages() == [("cam_e", "wsn", 5.0, 7.0)]
    assert sc.target.motion.dim == 4       # every track: constant velocity in 2-D


def test_the_urus_people_scenario_has_what_issue_24_asks_for():
    sc = load_scenario(ROOT / "topologies" / "urus_people.toml")
    people = [t for t in sc.targets if t.kind == "person"]
    robots = [t for t in sc.targets if t.kind == "robot"]
    cameras = [n for n in sc.nodes.values() if n.sensor_kind == "detections"]
    assert len(people) >= 6 and len(robots) == 2 and len(cameras) >= 4
    assert sc.outages() and sc.rendezvous and all(n.params["clutter"] > 0 for n in cameras)
    views = [n.params["view"] for n in cameras]

    def overlap(a, b):
        return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]
    pairs = [overlap(a, b) for i, a in enumerate(views) for b in views[i + 1:]]
    assert any(pairs) and not all(pairs)                         # overlapping and separate views
    assert any(n.sensor_kind == "tags" and set(n.params["targets"]) & {p.name for p in people}
               for n in sc.nodes.values())                       # a tagged person read by the WSN


@pytest.mark.parametrize("old, new, expect", [
    ('speed = 1.2\n', 'sped = 1.2\n', "targets[0] (ann).sped: unknown key (did you mean 'speed'?)"),
    ('associator = "jpda"', 'asociator = "jpda"', "tracking.asociator: unknown key (did you mean 'associator'?)"),
    ('associator = "jpda"', 'associator = "jpdaa"', "tracking.associator: must be one of jpda, gnn"),
    ('max_misses = 5', 'max_mises = 5', "tracking.deleter.max_mises: unknown key (did you mean 'max_misses'?)"),
    ('[tracking.merge]\nconfirm = 3', '[tracking.merge]\nconfirm = 0', "tracking.merge.confirm must be an integer >= 1"),
    ('confirm = [3, 5]', 'confirm = [5, 3]', "tracking.initiator.confirm: must be [m, n]"),
    ('region = [0.0, 20.0, 0.0, 10.0]', 'region = [20.0, 0.0, 0.0, 10.0]', "tracking.region: must have x1 > x0"),
    ('kind = "robot"', 'kind = "drone"', "targets[2] (rob).kind: must be one of person, robot"),
    ('meets = "ann"', 'meets = "bob"', "rob comes no closer than"),
    ('meets = "ann"', 'meets = "anne"', "(did you mean 'ann'?)"),
    ('appear = 1.0', 'appear = 20.0', "targets[1] (bob).appear: 20 s is not before the end of the run"),
    ('leave = 12.0', 'leave = -1.0', "targets[2] (rob).leave must be non-negative"),
    ('targets = ["bob"]', 'targets = ["bobby"]', "targets names 'bobby', which has no [[targets]] table"),
    ('view = [0.0, 11.0, 0.0, 10.0]', 'view = [0.0, 11.0, 0.0]', "view must be [x0, x1, y0, y1]"),
    ('clutter = 0.3\ndetection = 0.9\nrate = 10.0\nsend_period = 0.2\n\n[[nodes]]\nname = "cam_e"',
     'clutter = -0.3\ndetection = 0.9\nrate = 10.0\nsend_period = 0.2\n\n[[nodes]]\nname = "cam_e"',
     "clutter must be non-negative"),
    ('sensor = "tags"', 'sensor = "position"', "a multi-target scenario's nodes have sensor = 'detections' or 'tags'"),
    ('rate = 2.0\n', 'rate = 2.0\ndelay = 0.1\n', "nodes[2] (wsn).delay: not used by a multi-target scenario"),
    ('name = "bob"', 'name = "wsn"', "target 'wsn' has the name of a node"),
    ('outages = [[5.0, 7.0]]', 'outages = [[5.0, 7.0]]\n\n[[events]]\nt = 3.0\nlink_down = ["cam_w", "cam_e"]',
     "[[events]] (links that change) is not supported in a multi-target scenario yet"),
    ('duration = 12.0', 'duration = 12.0\n[target]\nq = 0.1\n', "[target]: a multi-target scenario has [[targets]]"),
])
def test_mistakes_in_a_multi_target_scenario_are_one_line_errors(tmp_path, old, new, expect):
    assert old in MULTI, old
    msg = error_of(write(tmp_path, MULTI.replace(old, new, 1)))
    assert expect in msg, msg


def test_the_multi_target_sensor_kinds_belong_to_multi_target_scenarios(tmp_path):
    text = SINGLE_TARGET.replace('sensor = "position"\nstd = 0.5', 'sensor = "detections"\nview = [0.0, 1.0, 0.0, 1.0]', 1)
    msg = error_of(write(tmp_path, text))
    assert "sensor 'detections' belongs to a multi-target scenario" in msg, msg
    msg = error_of(write(tmp_path, MULTI.replace('[[targets]]\nname = "ann"', '[[targetz]]\nname = "ann"', 1)))
    assert "[[targetz]]: unknown table (did you mean" in msg, msg


def test_a_run_shortened_to_before_a_rendezvous_leaves_it_out_with_a_warning(tmp_path):
    sc = load_scenario(write(tmp_path, MULTI), duration=3.0)
    assert sc.rendezvous == [] and any("rob comes no closer than" in w and "left out" in w for w in sc.warnings)
    assert sc.targets[0].leave == 3.0
