"""dfusion.assignment.gated_assignment against brute force: every partial assignment through
allowed pairs enumerated, the one with the most pairs and then the least cost."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from dfusion.assignment import gated_assignment


def _brute_force(cost: np.ndarray, ok: np.ndarray) -> tuple[int, float]:
    """(most allowed pairs, least cost with that many) over every injective map of rows to columns or none."""
    n, k = cost.shape
    best = (0, 0.0)
    for cols in itertools.product([None, *range(k)], repeat=n):
        used = [c for c in cols if c is not None]
        if len(used) != len(set(used)) or any(c is not None and not ok[r, c] for r, c in enumerate(cols)):
            continue
        pairs = len(used)
        total = sum(cost[r, c] for r, c in enumerate(cols) if c is not None)
        if pairs > best[0] or (pairs == best[0] and total < best[1] - 1e-12):
            best = (pairs, total)
    return best


@pytest.mark.parametrize("seed", range(40))
def test_most_pairs_then_least_cost_like_brute_force(seed):
    rng = np.random.default_rng(seed)
    n, k = rng.integers(1, 5), rng.integers(1, 5)
    cost = rng.normal(scale=rng.choice([0.1, 1.0, 100.0]), size=(n, k))   # negative costs too (GNN: -log g)
    ok = rng.random((n, k)) < rng.choice([0.2, 0.5, 0.9])
    with_mask = gated_assignment(cost, ok)
    with_inf = gated_assignment(np.where(ok, cost, np.inf))   # the default: the finite entries
    for r, c in (with_mask, with_inf):
        assert len(set(r.tolist())) == len(r) and len(set(c.tolist())) == len(c)
        assert ok[r, c].all()
        pairs, total = _brute_force(cost, ok)
        assert len(r) == pairs
        assert cost[r, c].sum() == pytest.approx(total, abs=1e-9)


def test_nothing_allowed_and_bad_shapes():
    r, c = gated_assignment(np.full((2, 3), np.inf))
    assert r.size == c.size == 0
    r, c = gated_assignment(np.zeros((0, 3)))
    assert r.size == c.size == 0
    with pytest.raises(ValueError, match="two axes"):
        gated_assignment(np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        gated_assignment(np.zeros((2, 2)), np.ones((2, 3), bool))
