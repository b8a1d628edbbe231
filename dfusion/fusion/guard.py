r"""Consistency test of a neighbour's information, and quarantine of a neighbour that keeps failing it.

**The test.** With per-time replacement (:mod:`dfusion.fusion.channel`) a message
changes, per state time ``t``, what the receiver holds from the sender: its filter gets
the block ``(Lambda, y) = new - old`` (the channel's plan), what the message adds. That
block is a pseudo-measurement of the state: with ``Lambda = V diag(l) V^T`` (``r``
positive eigenvalues), ``z = Lambda^+ y`` is a measurement of ``V^T x(t)`` with noise
``diag(l)^-1``. Against the receiver's belief *without* the message, its innovation
``nu = V^T (z - mu0)`` has covariance ``V^T (P0 + Lambda^+) V`` and ``nu^T S^-1 nu ~
chi2_r`` when both sides' models hold (Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, sec. 5.4: the normalized innovation
squared). All blocks of one message are tested jointly: their pseudo-measurements are
stacked against the joint belief over the trajectory, which gives one statistic with
``sum r`` degrees of freedom. It is computed without forming the joint covariance, from
the smoothed means at the blocks' times before (``mu0``) and after (``mu1``) adding them
(:meth:`~dfusion.estimation.delayed_state.DelayedStateEIF.add_information_moments`)::

    D^2 = sum_t (z_t - mu0_t)^T Lambda_t (z_t - mu1_t)        ~ chi2_{sum r_t}

(the identity ``nu^T S^-1 nu = (z - H mu0)^T R^-1 (z - H mu1)`` of a Kalman update,
applied to the stacked pseudo-measurement; ``mu1 - mu0`` is the joint update of the
trajectory, so the correlations between the blocks' times are accounted for). The
smoothed covariances before, ``P0``, enter only the two threshold tests below (a
direction negligible, a value out of range): they are decided from bounds
``P_k - G_k P^-_{k+1} G_k^T <= P0 <= P_k`` that the smoother's cached terms give without
its covariance pass, and the exact ``P0`` is computed only when the bounds do not decide
(:func:`_thresholds_from_bounds`: the same verdicts). The
message *fails* when ``D^2 > chi2^-1_{sum r}(1 - alpha)``; ``alpha`` (default 1e-3)
is the false-alarm probability *per message*, whatever the number of blocks.

Only what is new is tested, and it is tested against a belief that already holds
everything else the receiver knows, so under the model the statistics of successive
messages are independent (the innovations of a filter are white): a healthy
neighbour fails ``k`` of ``m`` consecutive messages with probability about
``C(m, k) alpha^k`` (1.2e-7 for the defaults ``k = 3``, ``m = 10``). Blocks that
remove information (a negative eigenvalue: the sender dropped or replaced something)
are added first and not tested; blocks for state times newer than the receiver's
newest state wait in the node and are not tested; directions whose information is
negligible for the receiver (``l_i v_i^T P0 v_i <= 1e-9``) are left out. A block whose
``y`` leaves the range of ``Lambda`` (no measurement can produce it) by more than
rounding (``y_out^T P0 y_out > 1e-6``: the mean would move by a thousandth of a
standard deviation without any information) fails at once.

**In the receive transaction.** :meth:`dfusion.fusion.node.FusionNode.receive` plans a
message (decoding, validation, the channel's plan) without changing anything, then
applies the plan inside one transaction: the test runs as the plan's additions are
added to the filter, the verdict is recorded, and a verdict that completes a quarantine
withdraws the link in the same transaction. An exception anywhere undoes all of it, the
link's record included: a message is tested, fused and judged completely or not at all.
A steady-state message takes the node's critical path (:meth:`FusionNode.settle
<dfusion.fusion.node.FusionNode.settle>`): it is fused at once and its bookkeeping is done
later, with the same statistic, counters and decisions. Its test is done later too when it is
one block at the newest state and even a failure would not complete a quarantine
(:meth:`NeighbourGuard.may_quarantine`: the verdict then changes only the link's counters);
otherwise it is tested and judged as it is fused, and a verdict that would complete a
quarantine (:meth:`NeighbourGuard.would_quarantine`) sends the message to the general
transaction instead.

**Quarantine.** A failed message is still fused (one failure is the expected false
alarm of a healthy network, and refusing it would not make the fused result exact: the
sender's next messages carry the same times again). A neighbour whose last ``m`` tested
messages hold ``k`` failures is quarantined: the receiver *withdraws* everything that
came over that link. With per-time replacement that means treating the channel's stored
values ``M_ij(t)`` as removed: they are subtracted from the filter (every state time
still in the window) and from what the node shares, ``T_i``, and those times are marked
changed on every other link, so the next partial messages carry the smaller values ``V =
T - M`` (or clear the time) and the rest of the tree withdraws the same information.
Removing information is never over-confident; the cost is that what the quarantined
neighbour relayed from further away is lost too. Blocks older than the receiver's window
are already marginalized into its base and stay. While the link is quarantined the node
keeps storing the neighbour's messages in the channel (what it would contribute; they
are acknowledged as usual), fuses none of them, marks nothing changed for them, and sends
the neighbour its whole belief ``V = T`` (nothing of the neighbour's is in it, so the
value for that link did not change when the quarantine began). Each message received
then is a *probation* test: the neighbour's whole current contribution (every stored
block in the window) against the receiver's belief, jointly as above, in a trial (undone
at once). After ``release`` consecutive passing probation tests the link leaves
quarantine and the neighbour's current contribution is added back to the filter and to
``T``, its times marked changed on the other links (exactly what normal operation would
hold). Probation statistics of successive messages share most of their blocks, so they
are strongly correlated: requiring ``release`` passes in a row mainly requires the
neighbour's picture to agree with the receiver's for ``release`` send periods; a
neighbour that restarted (a new incarnation) replaces its old blocks and can pass.

**Health** (:meth:`NeighbourGuard.health`): ``"lost"`` when every neighbour of a
node is quarantined (it no longer trusts anyone: either it or all of them are
wrong), ``"degraded"`` when some neighbour is quarantined or a link has failed
at least 2 of its last ``m`` tests (half way to quarantine with the defaults),
``"ok"`` otherwise.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.delayed_state import CovarianceBounds
from dfusion.linalg import Array, chi2_isf

log = logging.getLogger(__name__)

__all__ = ["GuardConfig", "LinkRecord", "NeighbourGuard", "block_eigen", "information_statistic", "split_blocks",
           "split_blocks_eigen", "HEALTH_STATES"]

HEALTH_STATES = ("ok", "degraded", "lost")

#: Eigenvalues of a block below this fraction of its largest are zero (rounding).
EIG_RTOL = 1e-9
#: A direction whose information changes the receiver's variance by less than this fraction is left out.
NEGLIGIBLE = 1e-9
#: The part of ``y`` outside the range of ``Lambda`` may shift the receiver's mean by this many
#: standard deviations (squared) at most: more is information no measurement can produce.
RANGE_TOL = 1e-6
#: Bounds on the covariances decide a threshold test only when they clear it by this fraction of
#: ``|x|^2 tr(upper)``, ``x`` the quadratic form's vector (:func:`_thresholds_from_bounds`).
BOUND_RTOL = 1e-8


#: ``chi2_isf`` values by ``(alpha, dof)``, shared by the guards of a process (the nodes of a host).
_THRESHOLDS: dict[tuple[float, int], float] = {}


@dataclass(frozen=True)
class GuardConfig:
    """Parameters of the consistency test and the quarantine (module docstring).

    Attributes
    ----------
    false_alarm : float
        ``alpha``: probability that a healthy neighbour's message fails the test.
    failures, window : int
        Quarantine after ``failures`` failed messages among the last ``window`` tested ones.
    release : int
        Consecutive passing probation tests that end a quarantine.
    """

    false_alarm: float = 1e-3
    failures: int = 3
    window: int = 10
    release: int = 10

    def __post_init__(self) -> None:
        if not (0.0 < self.false_alarm < 1.0):
            raise ValidationError(f"false_alarm must be in (0, 1), got {self.false_alarm!r}")
        for name in ("failures", "window", "release"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValidationError(f"{name} must be a positive integer, got {v!r}")
        if self.failures > self.window:
            raise ValidationError(f"failures ({self.failures}) must not exceed window ({self.window})")


@dataclass
class LinkRecord:
    """What a node's guard knows about one neighbour."""

    window: int
    tests: int = 0                  # messages tested (normal operation)
    failures: int = 0               # of which failed
    stat_sum: float = 0.0           # sum of the statistics of the tested messages
    dof_sum: int = 0                # and of their degrees of freedom
    untested_blocks: int = 0        # blocks not tested (removals, ahead of the newest state)
    quarantined: bool = False
    quarantines: int = 0            # times the link was quarantined
    releases: int = 0               # times it left quarantine
    probation_tests: int = 0
    passes: int = 0                 # consecutive passing probation tests
    recent: deque = field(default_factory=deque)

    def __post_init__(self) -> None:
        self.recent = deque(self.recent, maxlen=self.window)

    @property
    def recent_failures(self) -> int:
        return int(sum(self.recent))


def block_eigen(L: Array) -> tuple[list[float], Array]:
    """The eigendecomposition ``Lambda = V diag(l) V^T`` of one block (symmetrized), ``(l as
    floats, ascending; V)``: computed once for a one-block message and handed to both
    :func:`split_blocks` and :func:`information_statistic`."""
    w, V = np.linalg.eigh(0.5 * (L + L.T))
    return w.tolist(), V


def split_blocks(entries: list[tuple[float, Array, Array]],
                 eigen: tuple[list[float], Array] | None = None) -> tuple[list, list]:
    """``(additions, others)``: blocks whose information matrix is positive semi-definite
    (up to rounding: eigenvalues above ``-EIG_RTOL`` times the largest), and the rest.
    The eigenvalues of all blocks come from one stacked ``eigvalsh`` call (the same LAPACK
    routine per block as one call per block, without its per-call overhead); ``eigen``: of
    the one block of ``entries``, :func:`block_eigen` (a steady-state message), tested on
    Python floats."""
    if not entries:
        return [], []
    if eigen is not None and len(entries) == 1:
        e = entries[0]
        w = eigen[0]
        sc = max(abs(w[0]), abs(w[-1]))   # (ascending: the largest magnitude is at an end)
        if sc > 0.0:
            return ([e], []) if w[0] >= -EIG_RTOL * sc else ([], [e])
        if sc == 0.0:
            return ([e], []) if any(e[2].tolist()) else ([], [])
    w = np.linalg.eigvalsh(np.array([e[1] for e in entries]))
    a, o = _split_rows(entries, w)
    return [entries[i] for i in a], [entries[i] for i in o]


def _split_rows(entries: list[tuple[float, Array, Array]], w: Array) -> tuple[list[int], list[int]]:
    """:func:`split_blocks` by rows, from the stacked eigenvalues ``w`` (ascending) of the blocks."""
    scale = np.max(np.abs(w), axis=1)
    psd = w[:, 0] >= -EIG_RTOL * scale
    add, other = [], []
    for i, (sc, ok) in enumerate(zip(scale.tolist(), psd.tolist())):
        if sc > 0.0:
            (add if ok else other).append(i)
        elif any(entries[i][2].tolist()):
            add.append(i)   # y without Lambda: tested (rounding passes, more fails: out of range)
    return add, other


def split_blocks_eigen(entries: list[tuple[float, Array, Array]]) -> tuple[list, list, tuple[Array, Array] | None]:
    """:func:`split_blocks` of several blocks with one stacked eigendecomposition for the split and
    the statistic: ``(additions, others, (l, V))``, ``l, V`` the stacked eigenvalues and vectors
    of the additions (``Lambda_t = V_t diag(l_t) V_t^T``, of ``(Lambda + Lambda^T) / 2``: the
    decomposition :func:`information_statistic` computes), for its ``stacked`` argument. The
    eigenvalues of ``numpy.linalg.eigh`` instead of ``eigvalsh`` decide the split: the same
    LAPACK routine (``syevd``) with the vectors, which can move an eigenvalue by a rounding
    error, against a threshold of ``EIG_RTOL = 1e-9`` of the largest."""
    if not entries:
        return [], [], None
    L = np.array([e[1] for e in entries])
    w, V = np.linalg.eigh(0.5 * (L + L.transpose(0, 2, 1)))
    a, o = _split_rows(entries, w)
    return [entries[i] for i in a], [entries[i] for i in o], ((w[a], V[a]) if a else None)


def information_statistic(entries: list[tuple[float, Array, Array]], mu0: list[Array],
                          P0: list[Array] | CovarianceBounds, mu1: list[Array],
                          eigen: tuple[list[float], Array] | None = None,
                          stacked: tuple[Array, Array] | None = None) -> tuple[float, int]:
    """``(D^2, dof)`` of the blocks ``entries`` as joint pseudo-measurements (module docstring).

    ``mu0, P0``: the belief's smoothed means and covariances at the blocks' times before
    they are added; ``mu1``: the means after. ``P0`` enters only two threshold tests (a
    direction negligible, ``y`` out of range), so it may be given as
    :class:`~dfusion.estimation.delayed_state.CovarianceBounds`: the tests are then decided from
    the bounds, and the exact covariances computed only when the bounds do not decide them
    (:func:`_thresholds_from_bounds`; the same verdicts). Returns ``(inf, dof)`` if some ``y`` is not
    in the range of its ``Lambda``. All blocks at once: one stacked eigendecomposition
    ``Lambda_t = V_t diag(l_t) V_t^T`` and masks for the directions kept (positive, and not
    negligible), which gives per block exactly the terms of a loop over the blocks. One block
    is computed on 4 x 4 matrices and Python floats instead (``eigen``: its
    :func:`block_eigen`, if known). ``stacked``: the stacked decomposition of ``entries``, if
    known (:func:`split_blocks_eigen`).
    """
    if not entries:
        return 0.0, 0
    if len(entries) == 1 and not isinstance(P0, CovarianceBounds):
        return _statistic_one(entries[0], mu0[0], P0[0], mu1[0], eigen)
    return _statistic_stacked(entries, mu0, P0, mu1, stacked)


def _statistic_one(entry: tuple[float, Array, Array], mu0: Array, P0: Array, mu1: Array,
                   eigen: tuple[list[float], Array] | None = None) -> tuple[float, int]:
    """:func:`information_statistic` of one block (a steady-state message), the same terms as
    :func:`_statistic_stacked` on 4 x 4 matrices and Python floats: a numpy call on a stack of one
    block, and above all a numpy reduction, costs several times the arithmetic it does."""
    _, L, y = entry
    wl, V = block_eigen(L) if eigen is None else eigen
    sc = max(abs(wl[0]), abs(wl[-1]))   # (ascending)
    if not math.isfinite(sc):
        return _statistic_stacked([entry], [mu0], [P0], [mu1])
    pos = [x > EIG_RTOL * sc for x in wl] if sc > 0 else [False] * len(wl)
    Vt = V.T
    Vy = (Vt @ y).tolist()                                       # V^T y
    out = y - V @ np.array([v if p else 0.0 for v, p in zip(Vy, pos)])   # the part of y outside the range
    if float(out @ P0 @ out) > RANGE_TOL:
        return math.inf, sum(pos)
    vPv = np.diagonal(Vt @ P0 @ V).tolist()                      # v_i^T P0 v_i
    a0, a1 = (Vt @ mu0).tolist(), (Vt @ mu1).tolist()
    stat, dof = 0.0, 0
    for lam, p, s, vy, m0, m1 in zip(wl, pos, vPv, Vy, a0, a1):
        if p and lam * s > NEGLIGIBLE:
            zc = vy / lam                                        # v^T z in a kept direction
            stat += (zc - m0) * lam * (zc - m1)
            dof += 1
    return stat, dof


def _thresholds_from_bounds(w: Array, V: Array, out: Array, pos: Array,
                            bounds: CovarianceBounds) -> tuple[Array, Array] | None:
    """``(bad, use)`` of :func:`_statistic_stacked` decided from bounds ``lower <= P0 <= upper``
    on the covariances before, or None when the bounds do not decide every comparison.

    Both tests compare a quadratic form of ``P0`` with a threshold: ``out^T P0 out > RANGE_TOL``
    and ``l_i v_i^T P0 v_i > NEGLIGIBLE`` (``l_i > 0``). A quadratic form ``x^T P x`` is
    monotone in the Loewner order, so ``q(lower) <= q(P0) <= q(upper)``, and ``q(upper) <=
    |x|^2 tr(upper)`` (``upper`` is positive semi-definite): the bounds decide a comparison when
    both ends are on the same side. A margin of ``BOUND_RTOL |x|^2 tr(upper)`` (the covariances'
    size; the rounding of the smoother and of the bounds is about ``1e-16`` of it) keeps the
    decision the one that ``P0`` as the smoother computes it gives; a comparison inside the
    margin is left to the exact ``P0`` (:meth:`CovarianceBounds.exact`). The cheap forms are
    tried first: ``|out|^2 tr(upper)`` for the range (``out`` is rounding for a sound block),
    the lower bound alone for the directions kept."""
    lo, hi = bounds.lower, bounds.upper
    tr = np.trace(hi, axis1=1, axis2=2)                          # >= the largest eigenvalue
    oo = np.sum(out * out, axis=(1, 2))                          # |out|^2
    if float(np.max(oo * tr)) * (1.0 + BOUND_RTOL) <= RANGE_TOL:
        bad = np.zeros(len(tr), dtype=bool)                      # (q(upper) <= |out|^2 tr(upper))
    else:
        r_lo = (out.transpose(0, 2, 1) @ lo @ out).reshape(-1)
        r_hi = (out.transpose(0, 2, 1) @ hi @ out).reshape(-1)
        r_tol = BOUND_RTOL * oo * tr
        bad = r_lo - r_tol > RANGE_TOL
        if not np.all(bad | (r_hi + r_tol <= RANGE_TOL)):
            return None
    s_tol = BOUND_RTOL * tr[:, None] * np.abs(w)                 # (|v_i| = 1)
    use = pos & (w * np.sum(V * (lo @ V), axis=1) - s_tol > NEGLIGIBLE)
    if not np.all(use | ~pos):
        s_hi = w * np.sum(V * (hi @ V), axis=1)
        if not np.all(use | ~pos | (s_hi + s_tol <= NEGLIGIBLE)):
            return None
    return bad, use


def _statistic_stacked(entries: list[tuple[float, Array, Array]], mu0: list[Array],
                       P0: list[Array] | CovarianceBounds, mu1: list[Array],
                       stacked: tuple[Array, Array] | None = None) -> tuple[float, int]:
    """:func:`information_statistic` of any number of blocks, on stacked arrays."""
    y = np.array([e[2] for e in entries])[:, :, None]
    if stacked is None:
        L = np.array([e[1] for e in entries])
        w, V = np.linalg.eigh(0.5 * (L + L.transpose(0, 2, 1)))
    else:
        w, V = stacked
    Vt = V.transpose(0, 2, 1)
    scale = np.max(np.abs(w), axis=1, keepdims=True)
    pos = (w > EIG_RTOL * scale) & (scale > 0)
    Vy = (Vt @ y)[:, :, 0]                                       # V^T y
    out = y - V @ np.where(pos, Vy, 0.0)[:, :, None]             # the part of y outside the range
    decided = _thresholds_from_bounds(w, V, out, pos, P0) if isinstance(P0, CovarianceBounds) else None
    if decided is not None:
        bad, use = decided
    else:
        C0 = np.array(P0.exact() if isinstance(P0, CovarianceBounds) else P0)
        bad = (out.transpose(0, 2, 1) @ C0 @ out).reshape(-1) > RANGE_TOL
        signal = w * np.sum(V * (C0 @ V), axis=1)                # l_i v_i^T P0 v_i
        use = pos & (signal > NEGLIGIBLE)
    if bad.any():
        i = int(np.argmax(bad))
        return math.inf, int(use[:i].sum()) + int(pos[i].sum())
    lu = np.where(use, w, 1.0)
    zc = Vy / lu                                                 # V^T z in the kept directions
    a = zc - (Vt @ np.array(mu0)[:, :, None])[:, :, 0]
    b = zc - (Vt @ np.array(mu1)[:, :, None])[:, :, 0]
    return float(np.sum(np.where(use, a * lu * b, 0.0))), int(use.sum())


class NeighbourGuard:
    """Consistency records and quarantine decisions of one node (module docstring)."""

    def __init__(self, neighbors, config: GuardConfig | None = None) -> None:
        self.config = config or GuardConfig()
        self.links: dict[str, LinkRecord] = {j: LinkRecord(self.config.window) for j in neighbors}
        self._thresholds: dict[int, float] = {}

    def __repr__(self) -> str:
        q = sorted(self.quarantined)
        return f"NeighbourGuard({self.config}, quarantined={q})"

    def state(self, j: str) -> LinkRecord:
        """A copy of ``j``'s record (to undo a message's effect on it with :meth:`restore`)."""
        r = self.links[j]
        c = LinkRecord.__new__(LinkRecord)   # (its fields copied: dataclasses.replace costs 10x more per message)
        c.__dict__.update(r.__dict__)
        c.recent = deque(r.recent, maxlen=r.window)
        return c

    def restore(self, j: str, record: LinkRecord) -> None:
        """Put back ``j``'s record as :meth:`state` copied it."""
        self.links[j] = record

    def threshold(self, dof: int) -> float:
        """``chi2^-1_dof(1 - alpha)`` (:func:`dfusion.linalg.chi2_isf`: no scipy, whose import would stall a
        real-time node for seconds at the first message it tests; cached for every guard of the process)."""
        c = self._thresholds.get(dof)
        if c is None:
            key = (self.config.false_alarm, dof)
            c = _THRESHOLDS.get(key)
            if c is None:
                c = _THRESHOLDS[key] = chi2_isf(self.config.false_alarm, dof)
            self._thresholds[dof] = c
        return c

    @property
    def quarantined(self) -> set[str]:
        return {j for j, r in self.links.items() if r.quarantined}

    def is_quarantined(self, j: str) -> bool:
        r = self.links.get(j)
        return r is not None and r.quarantined

    def would_quarantine(self, j: str, stat: float, dof: int) -> bool:
        """Whether :meth:`judge` of this test would quarantine ``j``, without recording anything."""
        if dof <= 0:
            return False
        r = self.links[j]
        failed = not (stat <= self.threshold(dof))
        dropped = len(r.recent) == r.window and bool(r.recent[0])   # the oldest result leaves the last m
        return r.recent_failures + failed - dropped >= self.config.failures

    def may_quarantine(self, j: str) -> bool:
        """Whether a *failing* test of ``j`` now would quarantine it (:meth:`would_quarantine` of
        the worst verdict). When it would not, no verdict of the next test can change anything
        but ``j``'s counters: the node may record it later (:meth:`FusionNode.settle
        <dfusion.fusion.node.FusionNode.settle>`)."""
        r = self.links[j]
        dropped = len(r.recent) == r.window and bool(r.recent[0])
        return r.recent_failures + 1 - dropped >= self.config.failures

    def judge(self, j: str, stat: float, dof: int) -> bool:
        """Record one tested message of ``j``; returns True when ``j`` is to be quarantined now."""
        r = self.links[j]
        if dof <= 0:
            return False
        failed = not (stat <= self.threshold(dof))
        r.tests += 1
        r.failures += failed
        if math.isfinite(stat):
            r.stat_sum += stat
            r.dof_sum += dof
        r.recent.append(failed)
        if failed:
            log.debug("neighbour %s failed the consistency test: D^2 = %.3g > %.3g (%d dof)",
                     j, stat, self.threshold(dof), dof)
        if r.recent_failures >= self.config.failures:
            r.quarantined = True
            r.quarantines += 1
            r.passes = 0
            r.recent.clear()
            return True
        return False

    def probation(self, j: str, stat: float, dof: int) -> bool:
        """Record one probation test of quarantined ``j``; returns True when ``j`` is released now."""
        r = self.links[j]
        if dof <= 0:
            return False
        r.probation_tests += 1
        r.passes = r.passes + 1 if stat <= self.threshold(dof) else 0
        if r.passes >= self.config.release:
            r.quarantined = False
            r.releases += 1
            r.passes = 0
            return True
        return False

    def health(self) -> str:
        """``"ok"``, ``"degraded"`` or ``"lost"`` (module docstring)."""
        if not self.links:
            return "ok"
        q = self.quarantined
        if len(q) == len(self.links):
            return "lost"
        if q or any(r.recent_failures >= 2 for r in self.links.values()):
            return "degraded"
        return "ok"

    def summary(self) -> dict:
        """Totals over the links: tests, failures, normalized statistic, quarantines."""
        rs = self.links.values()
        dof = sum(r.dof_sum for r in rs)
        return {
            "tests": sum(r.tests for r in rs),
            "failures": sum(r.failures for r in rs),
            "nis_mean": (sum(r.stat_sum for r in rs) / dof) if dof else None,
            "quarantines": sum(r.quarantines for r in rs),
            "quarantined": sorted(self.quarantined),
            "untested_blocks": sum(r.untested_blocks for r in rs),
        }
