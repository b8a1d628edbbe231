"""The plaza world (dfusion.sim.plaza): deterministic by seed, people inside the plaza, detections with the
configured noise, detection probability and clutter, cameras that see only their views."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.errors import ValidationError
from dfusion.sim.plaza import CameraView, PlazaConfig, plaza_cameras, simulate_plaza


@pytest.fixture(scope="module")
def world():
    return simulate_plaza(PlazaConfig(n_people=8, duration=30.0, seed=2, cameras=plaza_cameras(3)))


def test_same_seed_same_world_other_seed_other_world():
    cfg = PlazaConfig(n_people=4, duration=3.0, seed=9)
    a, b = simulate_plaza(cfg), simulate_plaza(cfg)
    assert all(np.array_equal(fa.z, fb.z) for ka, kb in zip(a.frames, b.frames) for fa, fb in zip(ka, kb))
    c = simulate_plaza(PlazaConfig(n_people=4, duration=3.0, seed=10))
    assert not np.array_equal(a.frames[0][0].z, c.frames[0][0].z)


def test_people_stay_inside_are_born_at_the_edges_and_cross(world):
    c = world.config
    seen: dict[int, list] = {}
    for truth in world.truth:
        for pid, x in truth.items():
            assert 0 <= x[0] <= c.width and 0 <= x[1] <= c.height
            seen.setdefault(pid, []).append(x)
    born = [pid for pid in seen if pid >= c.n_people]
    assert born, "nobody was born in 30 s"
    for pid in born:
        p = seen[pid][0][:2]
        assert min(p[0], c.width - p[0], p[1], c.height - p[1]) < 0.3          # enters at the border
    counts = [len(t) for t in world.truth]
    assert 4 <= np.mean(counts) <= 10


def test_detections_have_the_configured_statistics(world):
    c = world.config
    errors, clutter, detected, visible = [], [], 0, 0
    for truth, frame in zip(world.truth, world.frames):
        for view, f in zip(c.cameras, frame):
            assert all(view.contains(z) for z in f.z[f.person < 0])            # clutter in the view
            assert all(view.contains(truth[pid]) for pid in f.person[f.person >= 0])   # people in the view
            inside = [pid for pid, x in truth.items() if view.contains(x)]
            visible += len(inside)
            detected += int(np.sum(f.person >= 0))
            errors += [z - truth[pid][:2] for z, pid in zip(f.z, f.person) if pid >= 0]
            clutter.append((int(np.sum(f.person < 0)), view.area))
    e = np.array(errors)
    assert np.allclose(e.std(axis=0), c.std, rtol=0.05) and np.allclose(e.mean(axis=0), 0.0, atol=0.02)
    assert detected / visible == pytest.approx(c.detection, abs=0.02)
    per_m2 = sum(k for k, _ in clutter) / sum(a for _, a in clutter)
    assert per_m2 == pytest.approx(c.clutter_density, rel=0.1)


def test_scans_carry_each_cameras_view_and_settings(world):
    scans = world.scans(0)
    assert [s.source for s in scans] == ["cam1", "cam2", "cam3"]
    assert scans[0].sees([15.3, 3.0]) and not scans[0].sees([15.4, 3.0])           # cam1 ends at 15.33 m
    cov = np.diag([0.04, 0.04, 1.0, 1.0])
    assert scans[0].visibility(np.array([15.33333333, 3.0, 0, 0]), cov) == pytest.approx(0.5)
    assert scans[0].visibility(np.array([15.33333333 - 0.2, 3.0, 0, 0]), cov) == pytest.approx(0.8413, abs=1e-4)
    assert scans[0].visibility(np.array([7.0, 15.0, 0, 0]), cov) == pytest.approx(1.0)
    assert scans[0].clutter_density == world.config.clutter_density


def test_bad_settings_are_refused():
    with pytest.raises(ValidationError, match="std"):
        PlazaConfig(std=0.0)
    with pytest.raises(ValidationError, match="x1 > x0"):
        CameraView("c", 1.0, 0.0, 0.0, 1.0)
    with pytest.raises(ValidationError, match="cameras"):
        plaza_cameras(5)
