"""Moving nodes and links that change in scenarios: waypoint paths, a camera on a robot, links
by radio range, scripted [[events]] and their one-line errors."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.spatial.distance import pdist, squareform

from dfusion.errors import ScenarioError, ValidationError
from dfusion.geometry import WaypointPath
from dfusion.models.camera import MountedCamera
from dfusion.scenario import load_scenario
from dfusion.topology import radio_links


# ---------------------------------------------------------------- WaypointPath
def test_a_waypoint_path_is_driven_at_constant_speed_along_its_segments():
    p = WaypointPath([[0, 0], [4, 0], [4, 3]], speed=2.0, start=1.0)
    assert p.length == 7.0
    np.testing.assert_allclose(p.position(0.0), [0, 0])        # waits at the first waypoint
    np.testing.assert_allclose(p.position(2.0), [2, 0])        # 2 m along the first segment
    np.testing.assert_allclose(p.position(3.5), [4, 1])        # 5 m: 1 m up the second
    np.testing.assert_allclose(p.position(100.0), [4, 3])      # stops at the last one
    assert p.heading(2.0) == 0.0 and math.isclose(p.heading(3.5), math.pi / 2)
    np.testing.assert_allclose(p.pose(3.5), [4, 1, math.pi / 2])


def test_a_looping_path_goes_round_its_closed_polygon():
    p = WaypointPath([[0, 0], [2, 0], [2, 2], [0, 2]], speed=1.0, loop=True)
    assert p.length == 8.0
    for t, want in ((1.0, [1, 0]), (3.0, [2, 1]), (7.0, [0, 1]), (9.0, [1, 0]), (8.0 * 5 + 5.0, [1, 2])):
        np.testing.assert_allclose(p.position(t), want, atol=1e-12)
    assert math.isclose(p.heading(7.0), -math.pi / 2)     # the closing segment, back down to the start


@pytest.mark.parametrize("args", [([[0, 0]], 1.0), ([[0, 0], [0, 0]], 1.0), ([[0, 0], [1, 1]], 0.0),
                                  ([[0, 0], [1, float("nan")]], 1.0), ([[0, 0], [1, 1]], True)])
def test_bad_paths_are_refused(args):
    with pytest.raises(ValidationError):
        WaypointPath(*args)


# ---------------------------------------------------------------- a camera on a robot
def test_a_mounted_camera_looks_along_the_heading_and_projects_its_optical_axis_to_the_principal_point():
    """The ground point where the optical axis meets the floor, ``h / tan(pitch)`` ahead of the
    robot (closed form), projects to ``(cx, cy)``; a point to the robot's left appears left."""
    path = WaypointPath([[0, 0], [10, 10]], speed=1.0)
    h, pitch = 1.2, math.radians(12.0)
    cam = MountedCamera(path.pose, mount_height=h, pitch=pitch, fx=500.0, fy=500.0, cx=320.0, cy=240.0,
                        width=640, height=480)
    for t in (0.0, 3.0, 7.5):
        x, y, th = path.pose(t)
        d = h / math.tan(pitch)
        ahead = np.array([x + d * math.cos(th), y + d * math.sin(th), 0.0, 0.0])
        np.testing.assert_allclose(cam.at(t).h(ahead), [320.0, 240.0], atol=1e-9)
        left = ahead + np.array([-math.sin(th), math.cos(th), 0.0, 0.0])
        assert cam.at(t).h(left)[0] < 320.0
        behind = np.array([x - d * math.cos(th), y - d * math.sin(th), 0.0, 0.0])
        assert not cam.at(t).in_view(behind)


# ---------------------------------------------------------------- links by radio range
@pytest.mark.parametrize("seed", range(5))
def test_radio_links_are_the_pairs_within_both_ranges(seed):
    rng = np.random.default_rng(seed)
    names = [f"n{i}" for i in range(12)]
    xy = rng.uniform(0, 30, size=(12, 2))
    ranges = dict(zip(names, rng.uniform(3, 15, size=12)))
    ranges.pop("n3")                      # a node without a range takes no part
    dist = squareform(pdist(xy))
    want = {tuple(sorted((a, b))) for (i, a), (j, b) in itertools.combinations(enumerate(names), 2)
            if a in ranges and b in ranges and dist[i, j] <= min(ranges[a], ranges[b])}
    got = radio_links({n: p for n, p in zip(names, xy)}, ranges)
    assert got == want


# ---------------------------------------------------------------- scenarios
BASE = """
duration = 10.0
[target]
motion = "constant_velocity"
q = 0.01
initial_mean = [0.0, 0.0, 0.0, 0.0]
initial_cov_diag = [1.0, 1.0, 0.1, 0.1]
[[nodes]]
name = "a"
sensor = "position"
std = 0.5
[[nodes]]
name = "b"
sensor = "position"
std = 0.5
[[nodes]]
name = "c"
sensor = "position"
std = 0.5
[[links]]
between = ["a", "b"]
[[links]]
between = ["b", "c"]
"""


def load(tmp_path, extra: str):
    f = tmp_path / "s.scenario.toml"
    f.write_text(BASE + extra)
    return load_scenario(f)


def test_events_are_read_in_time_order(tmp_path):
    sc = load(tmp_path, """
[[events]]
t = 5.0
link_down = ["a", "b"]
[[events]]
t = 2.0
link_up = ["c", "a"]
[[events]]
t = 3.0
join = "c"
""")
    assert sc.dynamic
    assert [(e.t, e.kind, e.nodes) for e in sc.events] == [(2.0, "link_up", ("a", "c")), (3.0, "join", ("c",)),
                                                          (5.0, "link_down", ("a", "b"))]
    assert sc.nodes["c"].joins == 3.0 and not sc.nodes["c"].is_present(2.9) and sc.nodes["c"].is_present(3.0)


@pytest.mark.parametrize("events, words", [
    ('t = 1.0\nlink_up = ["a", "b"]', "events[0].link_up: a - b is already up at t = 1 s"),
    ('t = 1.0\nlink_down = ["a", "c"]', "events[0].link_down: a - c is not up"),
    ('t = 1.0\nlink_up = ["a", "a"]', "must name two different nodes"),
    ('t = 1.0\nlink_up = ["a", "x"]', "names node 'x', which has no [[nodes]] table"),
    ('t = 11.0\nleave = "a"', "after the end of the run"),
    ('link_up = ["a", "c"]', "events[0].t: missing"),
    ('t = 1.0\nlink_up = ["a", "c"]\nleave = "b"', "needs exactly one of link_up, link_down, join, leave, got 2"),
    ('t = 1.0\nlinkup = ["a", "c"]', "linkup"),
    ('t = 0.0\njoin = "a"', "joins once, after the start"),
    ('t = -1.0\nleave = "a"', "events[0].t"),
    ('t = 1.0\nleave = 3', "must name a node"),
])
def test_bad_events_are_one_line_errors_naming_the_event(tmp_path, events, words):
    with pytest.raises(ScenarioError) as info:
        load(tmp_path, "[[events]]\n" + events + "\n")
    msg = str(info.value)
    assert words in msg and "\n" not in msg


def test_leaving_twice_and_joining_after_leaving_are_errors(tmp_path):
    with pytest.raises(ScenarioError, match="a leaves once"):
        load(tmp_path, '[[events]]\nt = 1.0\nleave = "a"\n[[events]]\nt = 2.0\nleave = "a"\n')
    with pytest.raises(ScenarioError, match="joins once"):
        load(tmp_path, '[[events]]\nt = 1.0\nleave = "a"\n[[events]]\nt = 2.0\njoin = "a"\n')


def test_radio_keys_are_checked(tmp_path):
    with pytest.raises(ScenarioError, match=r"radio.ranges.kamera: unknown sensor kind"):
        load(tmp_path, "[radio]\nranges = { kamera = 5.0 }\n")
    with pytest.raises(ScenarioError, match=r"radio.ranges.position"):
        load(tmp_path, "[radio]\nranges = { position = -5.0 }\n")
    with pytest.raises(ScenarioError, match=r"radio"):
        load(tmp_path, "[radio]\nrange = 5.0\n")
    f = tmp_path / "top.scenario.toml"
    f.write_text("spanning_tree = true\n" + BASE + '[[events]]\nt = 1.0\nlink_up = ["a", "c"]\n')
    with pytest.raises(ScenarioError, match="spanning_tree: has no meaning when links change"):
        load_scenario(f)


@pytest.mark.parametrize("keys, words", [
    ('speed = 1.0', "speed needs a path"),
    ('path = [[0.0, 0.0], [1.0, 0.0]]', "speed"),
    ('path = [[0.0, 0.0]]\nspeed = 1.0', "at least two [x, y] waypoints"),
    ('path = [[0.0, 0.0], [1.0, 0.0]]\nspeed = 1.0\nloop = 1', "loop must be true or false"),
])
def test_a_path_and_its_keys_are_checked(tmp_path, keys, words):
    text = BASE.replace('name = "c"\nsensor = "position"', 'name = "c"\nsensor = "position"\n' + keys)
    f = tmp_path / "p.scenario.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(f)
    assert words in str(info.value) and "nodes" in str(info.value)
