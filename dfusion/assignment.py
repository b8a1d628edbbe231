r"""The gated assignment: rows to columns, only through allowed pairs, the most pairs at the least cost.

Data association (GNN, the pairing of initiation seeds with detections) and the multi-target
metrics (CLEAR MOT's matching, label agreement) all assign the rows of a cost matrix to its
columns where only some pairs are allowed (inside a gate, within a distance). Among the
assignments (each row at most one column, each column at most one row) the one wanted has
the most allowed pairs and, among those, the least total cost of its pairs.

It is solved by ``scipy.optimize.linear_sum_assignment`` (the Hungarian method in the
shortest augmenting path form of D. F. Crouse, "On implementing 2D rectangular assignment
algorithms", IEEE Trans. Aerospace and Electronic Systems 52(4), 2016) on the cost matrix with
every forbidden entry replaced by

.. math::

    M = 2 \sum_{(i, j)\ \mathrm{allowed}} |c_{ij}| + 1 .

``linear_sum_assignment`` assigns ``min(rows, columns)`` pairs. An assignment with ``f``
forbidden pairs costs ``A + f M`` with ``|A| <= S = sum |c_ij|`` (allowed); since ``M > 2S``,
one with fewer forbidden pairs always costs less, so the optimum has the most allowed pairs and,
among those, the least ``A``. Only its allowed pairs are returned.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["gated_assignment"]


def gated_assignment(cost: ArrayLike, allowed: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the allowed pairs of the assignment with the most allowed pairs and the least cost.

    Parameters
    ----------
    cost : (n, k) array
        The cost of each pair (any finite value where allowed; forbidden entries are not read).
    allowed : (n, k) bool array, optional
        The pairs that may be assigned; default: the finite entries of ``cost``.

    Returns
    -------
    rows, cols : int arrays of equal length, ``rows`` increasing: pair ``rows[i], cols[i]`` is assigned.
    """
    cost = np.asarray(cost, dtype=float)
    if cost.ndim != 2:
        raise ValueError(f"a cost matrix has two axes, got shape {cost.shape}")
    ok = np.isfinite(cost) if allowed is None else np.asarray(allowed, dtype=bool)
    if ok.shape != cost.shape:
        raise ValueError(f"allowed has shape {ok.shape}, the cost matrix {cost.shape}")
    ok = ok & np.isfinite(cost)
    if not ok.any():
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    from scipy.optimize import linear_sum_assignment   # noqa: PLC0415  (only where an assignment is made)

    big = 2.0 * float(np.abs(cost[ok]).sum()) + 1.0
    r, c = linear_sum_assignment(np.where(ok, cost, big))
    keep = ok[r, c]
    return r[keep].astype(int), c[keep].astype(int)
