r"""Straight-line Python kernels of the forward pass for small states (the scalar path).

The forward pass of :class:`dfusion.estimation.trajectory.TrajectoryInformation` on one state is
a chain of some fifteen numpy calls on ``n x n`` blocks; on a 4 x 4 block each call costs
1-3 us of overhead for well under 1 us of arithmetic. For a small state (``n <= MAX_N``, 4)
the same arithmetic is done here on Python floats, in code generated once per ``n`` with
every loop unrolled (no numpy call inside; measured on 4 states: 14.6 against 42 us for
the fold with the conversions to and from arrays, ``benchmarks/hop_cpu.py``).

Two kernels, each the algorithm of the numpy path, so that the results differ by rounding
only (LAPACK orders its sums differently and may use fused multiply-adds):

* :func:`predict_kernel`: ``mu^- = F mu + c``, ``P^- = F P F^T + Q`` (the prediction of the
  next state; Thrun et al. 2005, Table 3.1). Only the upper triangle of ``F P F^T + Q`` is
  computed and mirrored: the result is exactly symmetric, as ``symmetrize`` makes the
  numpy path's.
* :func:`fold_kernel`: the information ``(L, y)`` of a state folded into its prediction
  ``N(mu^-, P^-)`` (``TrajectoryInformation._filtered``)::

      P  = (I + P^- L)^-1 P^-,   mu = (I + P^- L)^-1 (mu^- + P^- y)

  by Gaussian elimination with partial pivoting of ``[I + P^- L | P^- | mu^- + P^- y]``
  (the pivot of column ``k`` is the first largest ``|a_ik|``, ``i >= k``, as LAPACK's
  ``dgetrf``) and back substitution; then ``P`` is symmetrized, ``(P + P^T) / 2``, and
  tested by a Cholesky factorization (each pivot ``> 0``, as LAPACK's ``dpotrf``; NaN
  fails). Golub & Van Loan, *Matrix Computations* (4th ed.), algorithms 3.4.1 and 4.2.1.

A kernel returns ``None`` instead of raising when the result is not usable (a zero pivot,
a value that is not finite, a covariance that is not positive definite): the caller then
takes the numpy path, which decides and words the error exactly as before. Inputs are
nested lists (``ndarray.tolist()``); results are lists.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable

#: Largest state dimension given the scalar path. Measured (micro-benchmark, three runs on a
#: shared 2-core VM; the fold with its conversions, us): 2 states 4-7 against 25-41 in numpy,
#: 4 states 15-19 against 24-51, 5 states 22-26 against 25-40, 6 states 24-40 against 25-40:
#: from 5 states on the gain is within the noise (``docs/zenoh.md``).
MAX_N = 4

_GLOBALS = {"_sqrt": math.sqrt, "_isfinite": math.isfinite}


def _unpack(name: str, n: int, var: str) -> str:
    rows = ", ".join("(" + ", ".join(f"{var}{i}_{j}" for j in range(n)) + ",)" for i in range(n))
    return f"    ({rows},) = {name}"


def predict_source(n: int) -> str:
    """Source of ``predict(F, Q, c, m, P) -> (mean, cov)`` for an ``n``-state (see the module)."""
    N = range(n)
    out = ["def predict(F, Q, c, m, P):", _unpack("F", n, "f"), _unpack("Q", n, "q"), _unpack("P", n, "p"),
           f"    ({', '.join(f'c{i}' for i in N)},) = c", f"    ({', '.join(f'm{i}' for i in N)},) = m"]
    e = out.append
    for i in N:   # T = F P
        for j in N:
            e(f"    t{i}_{j} = " + " + ".join(f"f{i}_{k} * p{k}_{j}" for k in N))
    for i in N:   # the upper triangle of T F^T + Q
        for j in range(i, n):
            e(f"    s{i}_{j} = (" + " + ".join(f"t{i}_{k} * f{j}_{k}" for k in N) + f") + q{i}_{j}")
    mean = ", ".join("(" + " + ".join(f"f{i}_{k} * m{k}" for k in N) + f") + c{i}" for i in N)
    cov = ", ".join("[" + ", ".join(f"s{min(i, j)}_{max(i, j)}" for j in N) + "]" for i in N)
    e(f"    return [{mean}], [{cov}]")
    return "\n".join(out)


def fold_source(n: int) -> str:
    """Source of ``fold(P, L, m, y) -> (mean, cov) | None`` for an ``n``-state (see the module)."""
    N = range(n)
    w = 2 * n + 1   # the columns of [I + P L | P | m + P y]
    out = ["def fold(P, L, m, y):", _unpack("P", n, "p"), _unpack("L", n, "l"),
           f"    ({', '.join(f'm{i}' for i in N)},) = m", f"    ({', '.join(f'y{i}' for i in N)},) = y"]
    e = out.append
    for i in N:
        for j in N:
            e(f"    a{i}_{j} = " + " + ".join(f"p{i}_{k} * l{k}_{j}" for k in N) + (" + 1.0" if i == j else ""))
        for j in N:
            e(f"    a{i}_{n + j} = p{i}_{j}")
        e(f"    a{i}_{2 * n} = m{i} + (" + " + ".join(f"p{i}_{k} * y{k}" for k in N) + ")")
    for k in N:   # elimination, the first largest pivot of the column (swapped rows: tuples)
        for i in range(k + 1, n):
            rk = ", ".join(f"a{k}_{j}" for j in range(k, w))
            ri = ", ".join(f"a{i}_{j}" for j in range(k, w))
            e(f"    if abs(a{i}_{k}) > abs(a{k}_{k}):")
            e(f"        {rk}, {ri} = {ri}, {rk}")
        e(f"    if not a{k}_{k}:")   # (NaN is truthy: it shows as a non-finite result below)
        e("        return None")
        for i in range(k + 1, n):
            e(f"    g = a{i}_{k} / a{k}_{k}")
            for j in range(k + 1, w):
                e(f"    a{i}_{j} -= g * a{k}_{j}")
    for j in range(n, w):   # back substitution, one right-hand side at a time
        for i in reversed(N):
            s = f"a{i}_{j}" + "".join(f" - a{i}_{k} * x{k}_{j}" for k in range(i + 1, n))
            e(f"    x{i}_{j} = ({s}) / a{i}_{i}")

    def cov(i: int, j: int) -> str:
        return f"x{i}_{n + i}" if i == j else f"s{min(i, j)}_{max(i, j)}"

    for i in N:   # symmetrized
        for j in range(i + 1, n):
            e(f"    s{i}_{j} = 0.5 * (x{i}_{n + j} + x{j}_{n + i})")
    values = [f"x{i}_{2 * n}" for i in N] + [cov(i, j) for i in N for j in range(i, n)]
    e(f"    if not _isfinite(({' + '.join(values)}) * 0.0):")   # inf or NaN anywhere gives NaN
    e("        return None")
    for j in N:   # the Cholesky test
        for i in range(j, n):
            acc = cov(i, j) + "".join(f" - h{i}_{k} * h{j}_{k}" for k in range(j))
            if i == j:
                e(f"    d = {acc}")
                e("    if not d > 0.0:")
                e("        return None")
                e(f"    h{j}_{j} = _sqrt(d)")
            else:
                e(f"    h{i}_{j} = ({acc}) / h{j}_{j}")
    rows = ", ".join("[" + ", ".join(cov(i, j) for j in N) + "]" for i in N)
    e(f"    return [{', '.join(f'x{i}_{2 * n}' for i in N)}], [{rows}]")
    return "\n".join(out)


def _compile(name: str, n: int) -> Callable:
    """The function ``name`` (``"predict"`` or ``"fold"``) for an ``n``-state, compiled from its
    generated source; ``1 <= n <= MAX_N``."""
    if not 1 <= n <= MAX_N:
        raise ValueError(f"the scalar path takes 1 to {MAX_N} states, not {n}")
    source = predict_source(n) if name == "predict" else fold_source(n)
    space = dict(_GLOBALS)
    exec(compile(source, f"<dfusion.estimation.scalar.{name}{n}>", "exec"), space)   # noqa: S102 - generated above
    return space[name]


@functools.cache
def predict_kernel(n: int) -> Callable:
    """The compiled :func:`predict_source` for ``1 <= n <= MAX_N`` (compiled once, then cached)."""
    return _compile("predict", n)


@functools.cache
def fold_kernel(n: int) -> Callable:
    """The compiled :func:`fold_source` for ``1 <= n <= MAX_N`` (compiled once, then cached)."""
    return _compile("fold", n)
