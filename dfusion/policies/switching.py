r"""Switching policies beside fusion: greedy with a punishment, hysteresis, blending, a floor.

Every class here is a :class:`dfusion.policies.base.Policy`: given the node's fused
estimate and its candidate sources (:class:`Estimate`), it returns the node's
output. A source with ``healthy=False`` (in error, see :mod:`dfusion.policies.lifecycle`)
counts as reliability 0. Each policy keeps

* ``current``: its current choice (a source name; for :class:`FusionFloorPolicy` the
  tuple of fused source names), ``None`` before the first decision;
* ``switches``: a list of :class:`Switch` ``(t, from, to)``, one per change of the
  choice after the first one (the first choice is a connection, not a switch).

The time of a decision is the newest time stamp among the fused estimate and the
sources.

Policies (registered for scenario files as ``"greedy"``, ``"hysteresis"``, ``"blend"``,
``"fusion_floor"`` by :mod:`dfusion.scenario.kinds`):

:class:`GreedySwitchingPolicy`
    The switching paper's algorithm (Hu et al., sec. 4; ``docs/background.md#references``): with
    ``R_c`` the current source's reliability and ``R_max`` the largest, switch only if
    ``R_max - P > R_c``. A source in error counts as ``R = 0``; an error of the current
    source forces a switch to the best healthy one whatever ``P`` (the supervisor's
    first task: "once the execution error occurs, the current configuration will be
    changed").

    *About "changing punishment".* The paper's "changing punishment P" is the
    punishment *for changing* (switching) component, not a P that changes over time: it
    is a constant of the rule, chosen once by two principles, "as large as possible to
    avoid the oscillation between localization methods" and "as small as possible to
    avoid robot lost situation", from a sweep of P over recorded data (their Fig. 8),
    which led them to ``P in [0.1, 0.17]``. There is no run-time rule for changing P in
    the paper. :func:`select_punishment` is that selection, written as a rule: the
    largest P whose mean error stays within ``(1 + tolerance)`` (default 5 %) of the
    smallest mean error of the sweep (optionally also with the fewest lost situations).
    The default ``P = 0.15`` is inside the paper's range.

:class:`HysteresisSwitchingPolicy`
    The docking paper's decision (Yilmaz and Temeltas, *Robotica* 2024, sec. 3.5, Algorithm 1):
    a signal ``rho`` (the correntropy similarity rate) above ``upper`` (0.75) selects
    the precise source, below ``lower`` (0.65) the coarse one, in between the previous
    stage is kept, so a signal wandering inside the band never switches.

:class:`BlendedTransitionPolicy`
    Wraps a switching policy. When it switches from ``A`` to ``B`` at ``t0``, the output
    over ``[t0, t0 + duration]`` is the weighted average ``(1 - w) A + w B`` with ``w``
    going from 0 to 1 (linear, or smoothstep): the docking paper's second remedy for the
    jump at a switch (sec. 4.5.2, "a weighted average of the estimated poses"). The
    covariance is that of the two-component mixture, ``(1 - w) P_A + w P_B + w (1 - w)
    (x_A - x_B)(x_A - x_B)^T``, which covers both estimates and the jump between them.

:class:`FusionFloorPolicy`
    Information-form fusion of the healthy sources whose reliability is above a floor:
    ``Y = sum_i P_i^-1``, ``y = sum_i P_i^-1 x_i``, output ``(Y^-1 y, Y^-1)``. **This sum
    assumes the sources' errors are independent.** Sources that share information (two
    localizers using the same odometry, or estimates that already contain each other)
    are counted twice and the result is over-confident; use the node's channel-filtered
    fusion (:class:`~dfusion.policies.base.InformationFusionPolicy`) for those, or
    covariance intersection.

Angles: estimates with heading components (``angle_indices``) are blended and fused
with wrapped differences to the first source and the result is wrapped to ``[-pi, pi)``.
"""
from __future__ import annotations

import math
from typing import Callable, Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array
from dfusion.policies.base import Policy
from dfusion.reliability import covariance_reliability

__all__ = [
    "Switch",
    "SwitchingPolicy",
    "GreedySwitchingPolicy",
    "HysteresisSwitchingPolicy",
    "BlendedTransitionPolicy",
    "FusionFloorPolicy",
    "effective_reliability",
    "select_punishment",
    "information_fusion",
]


class Switch(NamedTuple):
    """One change of a policy's choice."""

    t: float
    from_: object
    to: object


def effective_reliability(s: Estimate) -> float:
    """A source's reliability for switching: 0 while it is in error (not healthy)."""
    if not s.healthy:
        return 0.0
    r = float(s.reliability)
    return r if math.isfinite(r) else 0.0


def _now(fused: Estimate | None, sources: Sequence[Estimate]) -> float:
    ts = [float(s.t) for s in sources]
    if fused is not None:
        ts.append(float(fused.t))
    return max(ts) if ts else 0.0




class SwitchingPolicy(Policy):
    """Base of the policies that select among sources: ``current``, ``switches``, ``decisions``."""

    name = "switching"

    def __init__(self) -> None:
        self.current: object = None
        self.switches: list[Switch] = []
        self.decisions = 0

    def reset(self) -> None:
        """Forget the current choice and the recorded switches."""
        self.current = None
        self.switches = []
        self.decisions = 0

    def _choose(self, t: float, choice: object) -> None:
        if choice != self.current:
            if self.current is not None and choice is not None:
                self.switches.append(Switch(t, self.current, choice))
            if choice is not None:
                self.current = choice

    @property
    def n_switches(self) -> int:
        return len(self.switches)


# ---------------------------------------------------------------------------------- greedy
class GreedySwitchingPolicy(SwitchingPolicy):
    """Switch to the most reliable source when it beats the current one by more than ``P``.

    Parameters
    ----------
    punishment : float
        ``P >= 0``: switch only if ``R_max - P > R_c`` (paper: ``P in [0.1, 0.17]``).
    fallback : {"fused", "hold"}
        Output when no source is healthy: the node's fused estimate (default), or the
        current source's last estimate as it is (``healthy=False`` shows its state).

    A source missing from ``sources`` (not reported any more) is treated like one in
    error. Ties go to the source whose name sorts first (deterministic).
    """

    name = "greedy"

    def __init__(self, punishment: float = 0.15, fallback: str = "fused") -> None:
        super().__init__()
        P = float(punishment)
        if not (math.isfinite(P) and P >= 0):
            raise ValidationError(f"punishment P must be a non-negative number, got {punishment!r}")
        if fallback not in ("fused", "hold"):
            raise ValidationError(f"fallback must be 'fused' or 'hold', got {fallback!r}")
        self.punishment = P
        self.fallback = fallback
        self.forced = 0

    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        self.decisions += 1
        t = _now(fused, sources)
        by_name = {s.name: s for s in sources}
        healthy = sorted((s for s in sources if s.healthy), key=lambda s: s.name)
        if not healthy:
            cur = by_name.get(self.current)
            if self.fallback == "hold" and cur is not None:
                return cur
            return fused
        best = max(healthy, key=effective_reliability)     # first of the maxima in name order
        cur = by_name.get(self.current)
        if cur is None or not cur.healthy:
            if self.current is not None:
                self.forced += 1
            self._choose(t, best.name)
            return best
        if effective_reliability(best) - self.punishment > effective_reliability(cur):
            self._choose(t, best.name)
            return best
        return cur


def select_punishment(punishments: Sequence[float], mean_errors: Sequence[float], tolerance: float = 0.05,
                      lost: Sequence[float] | None = None) -> float:
    """The paper's selection of ``P`` from a sweep (sec. 4, Fig. 8), written as a rule.

    "P is chosen to be as large as possible to avoid the oscillation" (fewer switches)
    and "as small as possible to avoid robot lost situation" (accuracy): the largest
    ``P`` whose mean error is at most ``(1 + tolerance)`` times the smallest mean error
    of the sweep and, if ``lost`` (lost situations per ``P``) is given, whose number of
    lost situations is the sweep's smallest.
    """
    P = np.asarray(punishments, dtype=float)
    e = np.asarray(mean_errors, dtype=float)
    if P.shape != e.shape or P.size == 0:
        raise ValidationError("need one mean error per punishment")
    ok = e <= (1.0 + tolerance) * np.nanmin(e)
    if lost is not None:
        n = np.asarray(lost, dtype=float)
        if n.shape != P.shape:
            raise ValidationError("need one count of lost situations per punishment")
        ok &= n <= np.nanmin(n[ok]) if ok.any() else n <= np.nanmin(n)
    return float(P[ok].max())


# ---------------------------------------------------------------------------------- hysteresis
class HysteresisSwitchingPolicy(SwitchingPolicy):
    """Two-stage switching on a signal with hysteresis (docking paper, Algorithm 1).

    Parameters
    ----------
    high, low : str
        Source names selected above ``upper`` (the precise source) and below ``lower``
        (the coarse one).
    upper, lower : float
        Thresholds, ``lower <= upper`` (paper: 0.75 and 0.65).
    signal : str, callable or None
        Where the signal comes from: the *name of a source* whose ``reliability`` field
        carries it (e.g. a ``"similarity"`` pseudo-source reported by the similarity-rate
        estimator: configuration only); a callable ``f(fused, sources) -> float | None``;
        or ``None``, in which case the latest value given to :meth:`set_signal` is used.
    window : int
        Moving average over the last ``window`` signal values before the comparison
        (the paper's ROS node has such a filter, ``/windowSize``); 1 = none.
    initial : {"low", "high"}
        Starting stage (paper: the delivery stage, i.e. ``"low"``).

    If the selected source is missing or in error and the other one is healthy, the
    other one is output (and recorded as a switch); the stage itself follows the signal
    only.
    """

    name = "hysteresis"

    def __init__(
        self,
        high: str = "precise",
        low: str = "coarse",
        upper: float = 0.75,
        lower: float = 0.65,
        signal: str | Callable[[Estimate, Sequence[Estimate]], float | None] | None = None,
        window: int = 1,
        initial: str = "low",
    ) -> None:
        super().__init__()
        if not (math.isfinite(upper) and math.isfinite(lower) and lower <= upper):
            raise ValidationError(f"need finite thresholds with lower <= upper, got {lower}, {upper}")
        if initial not in ("low", "high"):
            raise ValidationError("initial must be 'low' or 'high'")
        if high == low:
            raise ValidationError("high and low must name different sources")
        if int(window) < 1:
            raise ValidationError("window must be >= 1")
        self.high, self.low = str(high), str(low)
        self.upper, self.lower = float(upper), float(lower)
        self.signal = signal
        self.window = int(window)
        self.initial = initial
        self.stage = initial
        self._values: list[float] = []
        self._pushed: float | None = None
        self.last_signal: float | None = None
        self.stage_changes: list[Switch] = []

    def reset(self) -> None:
        super().reset()
        self.stage = self.initial
        self._values = []
        self._pushed = None
        self.last_signal = None
        self.stage_changes = []

    def set_signal(self, value: float) -> None:
        """Give the next signal value (when ``signal`` is ``None``)."""
        self._pushed = float(value)

    def _read_signal(self, fused, sources) -> float | None:
        if self.signal is None:
            v, self._pushed = self._pushed, None
            return v
        if isinstance(self.signal, str):
            for s in sources:
                if s.name == self.signal:
                    return float(s.reliability) if s.healthy else None
            return None
        v = self.signal(fused, sources)
        return None if v is None else float(v)

    def next_stage(self, value: float | None) -> str:
        """The stage that :meth:`update_stage` would give for ``value``, without changing anything.

        Lets a caller run only the localizer that the decision will need (the docking
        paper activates one localizer at a time).
        """
        if value is None or not math.isfinite(value):
            return self.stage
        vals = (self._values + [float(value)])[-self.window:]
        rho = float(np.mean(vals))
        return "high" if rho > self.upper else "low" if rho < self.lower else self.stage

    def update_stage(self, value: float | None, t: float = 0.0) -> str:
        """Feed one signal value through the moving average and the hysteresis; the stage."""
        if value is not None and math.isfinite(value):
            self._values.append(float(value))
            if len(self._values) > self.window:
                del self._values[: len(self._values) - self.window]
            rho = float(np.mean(self._values))
            self.last_signal = rho
            new = "high" if rho > self.upper else "low" if rho < self.lower else self.stage
            if new != self.stage:
                self.stage_changes.append(Switch(t, self.stage, new))
                self.stage = new
        return self.stage

    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        self.decisions += 1
        t = _now(fused, sources)
        stage = self.update_stage(self._read_signal(fused, sources), t)
        by_name = {s.name: s for s in sources}
        want, other = (self.high, self.low) if stage == "high" else (self.low, self.high)
        s = by_name.get(want)
        if s is None or not s.healthy:
            o = by_name.get(other)
            if o is not None and o.healthy:
                s, want = o, other
        if s is None:
            return fused
        self._choose(t, want)
        return s


# ---------------------------------------------------------------------------------- blending
def _blend(a: Estimate, b: Estimate, w: float, angles: Sequence[int], name: str, t: float) -> Estimate:
    xa = np.asarray(a.mean, dtype=float)
    xb = np.asarray(b.mean, dtype=float)
    d = xb - xa
    if angles:
        d[list(angles)] = wrap_angle(d[list(angles)])
    mean = xa + w * d
    if angles:
        mean[list(angles)] = wrap_angle(mean[list(angles)])
    cov = (1.0 - w) * np.asarray(a.cov, float) + w * np.asarray(b.cov, float) + w * (1.0 - w) * np.outer(d, d)
    rel = (1.0 - w) * effective_reliability(a) + w * effective_reliability(b)
    return Estimate(name, t, mean, 0.5 * (cov + cov.T), rel, a.healthy or b.healthy)


class BlendedTransitionPolicy(SwitchingPolicy):
    """A switching policy whose switches are spread over ``duration`` seconds.

    Parameters
    ----------
    inner : SwitchingPolicy
        Decides which source is wanted (greedy or hysteresis).
    duration : float
        Length of the transition (s) in the estimates' time; 0 = plain switching.
    shape : {"linear", "smoothstep"}
        Weight of the new source over the transition: ``u`` or ``3u^2 - 2u^3`` with
        ``u = (t - t0) / duration``.
    angle_indices : sequence of int
        Components that are angles (blended along the shorter arc).

    During a transition the output is named ``"A->B"``. If the old source disappears or
    fails during the transition, the new one is output at once; if the inner policy
    switches again during a transition, the new transition starts from the *current
    blended output* (kept as a frozen estimate), so the output never jumps.
    """

    name = "blend"

    def __init__(self, inner: SwitchingPolicy, duration: float = 1.0, shape: str = "linear",
                 angle_indices: Iterable[int] = ()) -> None:
        super().__init__()
        if not isinstance(inner, SwitchingPolicy):
            raise ValidationError("inner must be a SwitchingPolicy")
        if not (math.isfinite(duration) and duration >= 0):
            raise ValidationError("duration must be >= 0")
        if shape not in ("linear", "smoothstep"):
            raise ValidationError("shape must be 'linear' or 'smoothstep'")
        self.inner = inner
        self.duration = float(duration)
        self.shape = shape
        self.angle_indices = tuple(int(i) for i in angle_indices)
        self._t0: float | None = None
        self._from: Estimate | str | None = None
        self._to: str | None = None
        self._last_out: Estimate | None = None

    def reset(self) -> None:
        super().reset()
        self.inner.reset()
        self._t0 = self._from = self._to = self._last_out = None

    @property
    def blending(self) -> bool:
        return self._t0 is not None

    def _weight(self, t: float) -> float:
        if self.duration <= 0:
            return 1.0
        u = min(max((t - self._t0) / self.duration, 0.0), 1.0)
        return u if self.shape == "linear" else u * u * (3.0 - 2.0 * u)

    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        self.decisions += 1
        n_before = len(self.inner.switches)
        target = self.inner.decide(fused, sources)
        t = _now(fused, sources)
        if len(self.inner.switches) > n_before and self.duration > 0:
            sw = self.inner.switches[-1]
            # blend from what was output last (a frozen estimate if we were mid-transition)
            self._from = self._last_out if self.blending and self._last_out is not None else sw.from_
            self._t0 = t
            self._to = sw.to
        self._choose(t, self.inner.current)
        out = target
        if self.blending:
            by_name = {s.name: s for s in sources}
            old = self._from if isinstance(self._from, Estimate) else by_name.get(self._from)
            w = self._weight(t)
            if w >= 1.0 or old is None or not old.healthy or target.name != self._to:
                self._t0 = self._from = self._to = None
            else:
                label = f"{old.name}->{target.name}"
                out = _blend(old, target, w, self.angle_indices, label, t)
        self._last_out = out
        return out


# ---------------------------------------------------------------------------------- fusion floor
def information_fusion(estimates: Sequence[Estimate], angle_indices: Sequence[int] = ()) -> tuple[Array, Array]:
    """``(mean, cov)`` of the information-form sum of independent Gaussian estimates.

    ``Y = sum P_i^-1``, ``y = sum P_i^-1 x_i``; mean ``Y^-1 y``, covariance ``Y^-1``.
    Angle components are expressed relative to the first estimate (wrapped) first.
    """
    if not estimates:
        raise ValidationError("nothing to fuse")
    ref = np.asarray(estimates[0].mean, dtype=float)
    n = ref.size
    Y = np.zeros((n, n))
    y = np.zeros(n)
    idx = list(angle_indices)
    for s in estimates:
        x = np.asarray(s.mean, dtype=float).copy()
        if idx:
            x[idx] = ref[idx] + wrap_angle(x[idx] - ref[idx])
        Lam = np.linalg.inv(np.asarray(s.cov, dtype=float))
        Lam = 0.5 * (Lam + Lam.T)
        Y += Lam
        y += Lam @ x
    cov = np.linalg.inv(Y)
    cov = 0.5 * (cov + cov.T)
    mean = cov @ y
    if idx:
        mean[idx] = wrap_angle(mean[idx])
    return mean, cov


class FusionFloorPolicy(SwitchingPolicy):
    """Information fusion of the healthy sources with reliability above ``floor``.

    Parameters
    ----------
    floor : float
        Sources with ``reliability > floor`` (and healthy) are fused; ``0`` fuses every
        healthy source with a positive reliability.
    fallback : {"best", "fused"}
        When no source passes the floor: the most reliable healthy source (default), or
        the node's fused estimate.
    angle_indices : sequence of int

    Assumes independent source errors (see the module docstring). The output's name is
    the fused source names joined by ``"+"``; its reliability is eq. (11)-(12) of the
    switching paper applied to the fused covariance when it has at least two
    components (``1 / (sqrt(c_xx + c_yy) + 1)``), else the largest input reliability.
    ``current`` is the tuple of fused source names; a change of that set is recorded
    as a switch.
    """

    name = "fusion_floor"

    def __init__(self, floor: float = 0.5, fallback: str = "best", angle_indices: Iterable[int] = ()) -> None:
        super().__init__()
        if not (math.isfinite(floor) and 0.0 <= floor < 1.0):
            raise ValidationError(f"floor must be in [0, 1), got {floor!r}")
        if fallback not in ("best", "fused"):
            raise ValidationError("fallback must be 'best' or 'fused'")
        self.floor = float(floor)
        self.fallback = fallback
        self.angle_indices = tuple(int(i) for i in angle_indices)

    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        self.decisions += 1
        t = _now(fused, sources)
        chosen = sorted((s for s in sources if s.healthy and effective_reliability(s) > self.floor),
                        key=lambda s: s.name)
        if not chosen:
            healthy = [s for s in sources if s.healthy]
            if self.fallback == "fused" or not healthy:
                return fused
            best = max(sorted(healthy, key=lambda s: s.name), key=effective_reliability)
            self._choose(t, (best.name,))
            return best
        self._choose(t, tuple(s.name for s in chosen))
        if len(chosen) == 1:
            return chosen[0]
        mean, cov = information_fusion(chosen, self.angle_indices)
        if cov.shape[0] >= 2:
            rel = covariance_reliability(cov)
        else:
            rel = max(effective_reliability(s) for s in chosen)
        return Estimate("+".join(s.name for s in chosen), t, mean, cov, rel, True)


# ---------------------------------------------------------------------------------- factories
def _params(p: Mapping[str, object], allowed: set[str], kind: str) -> dict:
    unknown = set(p) - allowed
    if unknown:
        raise ValidationError(f"unknown parameters {sorted(unknown)} for policy {kind!r}; allowed {sorted(allowed)}")
    return dict(p)


def make_greedy(p: Mapping[str, object]) -> GreedySwitchingPolicy:
    return GreedySwitchingPolicy(**_params(p, {"punishment", "fallback"}, "greedy"))


def make_hysteresis(p: Mapping[str, object]) -> HysteresisSwitchingPolicy:
    return HysteresisSwitchingPolicy(**_params(p, {"high", "low", "upper", "lower", "signal", "window", "initial"},
                                               "hysteresis"))


def make_blend(p: Mapping[str, object]) -> BlendedTransitionPolicy:
    """``{kind = "blend", inner = "greedy" | "hysteresis", duration, shape, angle_indices, ...}``;
    the remaining keys go to the inner policy."""
    p = dict(p)
    inner = p.pop("inner", "greedy")
    own = {k: p.pop(k) for k in ("duration", "shape", "angle_indices") if k in p}
    if inner == "greedy":
        pol: SwitchingPolicy = make_greedy(p)
    elif inner == "hysteresis":
        pol = make_hysteresis(p)
    else:
        raise ValidationError(f"inner must be 'greedy' or 'hysteresis', got {inner!r}")
    return BlendedTransitionPolicy(pol, **own)


def make_fusion_floor(p: Mapping[str, object]) -> FusionFloorPolicy:
    return FusionFloorPolicy(**_params(p, {"floor", "fallback", "angle_indices"}, "fusion_floor"))
