"""dfusion.bags.tf: static transforms looked up along the tree of frames, against homogeneous
3x3 matrices composed by hand (the reference), with the graph of frames built once per change."""
from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np
import pytest

from dfusion.bags.tf import StaticTransforms


def _matrix(pose) -> np.ndarray:
    x, y, a = pose
    return np.array([[math.cos(a), -math.sin(a), x], [math.sin(a), math.cos(a), y], [0.0, 0.0, 1.0]])


def _pose(M: np.ndarray) -> np.ndarray:
    return np.array([M[0, 2], M[1, 2], math.atan2(M[1, 0], M[0, 0])])


def _reference(parents: dict, target: str, source: str) -> np.ndarray | None:
    """The pose of ``source`` in ``target``: each frame's matrix in the root of its tree, then
    ``inv(M_target) @ M_source``."""
    def in_root(f):
        M = np.eye(3)
        while f in parents:
            p, pose = parents[f]
            M = _matrix(pose) @ M
            f = p
        return f, M
    rt, Mt = in_root(target)
    rs, Ms = in_root(source)
    return _pose(np.linalg.solve(Mt, Ms)) if rt == rs else None


def _check_all(tf: StaticTransforms, parents: dict, frames: list[str]) -> None:
    for t in frames:
        for s in frames:
            got, want = tf.lookup(t, s), _reference(parents, t, s)
            if want is None:
                assert got is None, (t, s)
            else:
                assert got is not None, (t, s)
                assert got[:2] == pytest.approx(want[:2], abs=1e-12), (t, s)
                assert math.remainder(got[2] - want[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-12), (t, s)


def test_lookups_match_composed_matrices_and_build_the_graph_once_per_change(monkeypatch):
    builds = []
    build = StaticTransforms._neighbours
    monkeypatch.setattr(StaticTransforms, "_neighbours", lambda self: builds.append(1) or build(self))
    rng = np.random.default_rng(3)
    parents = {"odom": ("map", rng.normal(size=3)), "base_link": ("odom", rng.normal(size=3)),
               "laser": ("base_link", rng.normal(size=3)), "camera": ("base_link", rng.normal(size=3)),
               "gps": ("odom", rng.normal(size=3)), "other": ("elsewhere", rng.normal(size=3))}
    tf = StaticTransforms()
    for child, (parent, pose) in parents.items():
        tf.add(parent, "/" + child, pose)
    frames = sorted(set(parents) | {p for p, _ in parents.values()})
    _check_all(tf, parents, frames)
    for _ in range(200):   # a live input: the same lookup for every message
        tf.lookup("map", "laser")
    assert len(builds) == 1
    # a new transform and a replaced one: the graph is rebuilt once, and lookups see both
    parents["elsewhere"] = ("map", rng.normal(size=3))
    parents["laser"] = ("base_link", rng.normal(size=3))
    tf.add("map", "elsewhere", parents["elsewhere"][1])
    tf.add("base_link", "laser", parents["laser"][1])
    _check_all(tf, parents, frames)
    assert len(builds) == 2
    assert isinstance(tf.parents, MappingProxyType) and set(tf.parents) == set(parents)
