"""Perturbed copies of an MRCLAM dataset (dfusion.datasets.perturb_mrclam) on the 180 s slice
in tests/data/mrclam, against brute-force recomputation: only the target's sightings change,
inside the span of all measurements; the densest window found by trying every start; the
odometry of the busiest observer scaled; the input left untouched."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfusion.datasets import perturb_mrclam, read_mrclam
from dfusion.errors import ValidationError

SLICE = Path(__file__).resolve().parents[1] / "data" / "mrclam"


@pytest.fixture(scope="module")
def ds():
    return read_mrclam(SLICE)


def sightings(d, target=1, observers=(2, 3, 4, 5)):
    return {o: d.robots[o].observations_of(target) for o in observers}


def test_perturbed_copies_are_what_they_claim(ds):
    base = sightings(ds)
    k_all = sum(v.size for v in base.values())
    orig = {o: (r.meas_range.copy(), r.meas_bearing.copy(), r.odom.copy()) for o, r in ds.robots.items()}
    # outliers: round(0.1 K) sightings replaced, inside the span of all measurements
    out = perturb_mrclam(ds, "outliers", seed=3)
    changed = 0
    r_all = np.concatenate([r.meas_range for r in ds.robots.values()])
    b_all = np.concatenate([r.meas_bearing for r in ds.robots.values()])
    for o, idx in base.items():
        a, b = ds.robots[o], out.robots[o]
        diff = np.flatnonzero((a.meas_range != b.meas_range) | (a.meas_bearing != b.meas_bearing))
        assert set(diff) <= set(idx.tolist())          # only sightings of robot 1 change
        changed += diff.size
        assert np.all((b.meas_range[diff] >= r_all.min()) & (b.meas_range[diff] <= r_all.max()))
        assert np.all((b.meas_bearing[diff] >= b_all.min()) & (b.meas_bearing[diff] <= b_all.max()))
    assert changed == round(0.1 * k_all)
    # gap: the densest 60 s of sightings (brute force over every start) removed, nothing else
    times = np.sort(np.concatenate([ds.robots[o].meas_t[i] for o, i in base.items()]))
    counts = [np.count_nonzero((times >= s) & (times < s + 60.0)) for s in times]
    start = times[int(np.argmax(counts))]
    gap = perturb_mrclam(ds, "gap")
    for o, idx in base.items():
        a, g = ds.robots[o], gap.robots[o]
        t1 = g.meas_t[g.observations_of(1)]
        assert not np.any((t1 >= start) & (t1 < start + 60.0))
        removed = np.count_nonzero((a.meas_t[idx] >= start) & (a.meas_t[idx] < start + 60.0))
        assert a.meas_t.size - g.meas_t.size == removed
    assert sum(ds.robots[o].meas_t.size - gap.robots[o].meas_t.size for o in base) == max(counts)
    # odometry scale: the observer with the most sightings, (v, omega) x 1.05
    sc = perturb_mrclam(ds, "odometry-scale")
    busiest = max(base, key=lambda o: base[o].size)
    for o in ds.robots:
        np.testing.assert_array_equal(sc.robots[o].odom, ds.robots[o].odom * (1.05 if o == busiest else 1.0))
    both = perturb_mrclam(ds, "combined", seed=3)
    assert both.robots[busiest].odom[5, 0] == pytest.approx(1.05 * ds.robots[busiest].odom[5, 0])
    assert sum(both.robots[o].observations_of(1).size for o in base) == k_all - max(counts)
    # the input is untouched
    for o, (rr, bb, od) in orig.items():
        np.testing.assert_array_equal(ds.robots[o].meas_range, rr)
        np.testing.assert_array_equal(ds.robots[o].meas_bearing, bb)
        np.testing.assert_array_equal(ds.robots[o].odom, od)
    with pytest.raises(ValidationError):
        perturb_mrclam(ds, "earthquake")
