r"""Front end of an observer's position fixes of a target, with robust updates and lock-out recovery.

An observer robot sees a target (another robot) by range and bearing; converted to a
position fix of the target (:meth:`dfusion.models.TargetRangeBearing.position_fix`, a
:class:`~dfusion.models.PositionFix` with the observer's pose uncertainty in its
covariance ``R_eff``), it is linear in the target's state.
:class:`TargetTrackingFrontEnd` fuses such fixes into the target's fusion node through
an :class:`~dfusion.estimation.innovation.InnovationMonitor`: gate and Huber weight
against the node's *fused* estimate, and lock-out recovery by process noise added at the
node (:meth:`~dfusion.fusion.FusionNode.add_process_noise`), which no message carries,
so the recovery double counts nothing (``docs/robots.md``). A lock-out is declared only
over a span that every neighbour has reported on (:meth:`FusionNode.reported_until`) and
that no neighbour's information backed (:func:`network_support`).
"""
from __future__ import annotations

import numpy as np

from dfusion.estimation.innovation import Assessment, InnovationMonitor, monitored_update
from dfusion.frontends.base import FrontEnd, FrontEndStats
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array, symmetrize
from dfusion.models.measurement import PositionFix

__all__ = ["TargetTrackingFrontEnd", "network_support", "ROUNDING_INFO"]

#: Received information whose trace is below this (relative) is rounding, not support.
ROUNDING_INFO = 1e-9


class TargetTrackingFrontEnd(FrontEnd):
    """An observer's position fixes of a target, fused into the target's fusion node with
    robust updates and lock-out recovery (:mod:`dfusion.estimation.innovation`).

    Each fix (a :class:`PositionFix`) at a window state ``t`` of the node is tested
    against the node's **fused** estimate at ``t`` (which already holds the neighbours'
    information): ``nu = p - m_xy``, ``S = P_xy + R_eff``, the inflatable part
    ``A = P_xy``. Accepted fixes are fused with ``R_eff / w`` (Huber weight ``w``). When
    the monitor detects a divergence (a run of rejected fixes that agree on where the
    target is, judged once every neighbour has reported on their span and only if no
    neighbour's information backed the node's belief over it; or a persistent bias of
    the innovations), the node's belief of the target's position at ``t`` is
    re-initialized from the fixes: :meth:`FusionNode.add_process_noise` with the jump's
    second moment ``delta delta^T + F^+`` on the position block (its mean stays, its
    covariance covers the jump); the rejected fix is then tested again and the next fixes
    take over. Process noise is not exchanged information, so the recovery double counts
    nothing (``docs/robots.md``).

    Attributes
    ----------
    monitor : InnovationMonitor
    fused : list of (t, PositionFix)
        The fixes fused, with the noise they were fused with (for references).
    last : Assessment or None
        The decision on the last fix.
    """

    def __init__(self, monitor: InnovationMonitor) -> None:
        self.monitor = monitor
        self.fused: list[tuple[float, PositionFix]] = []
        self.last: Assessment | None = None
        self.stats = FrontEndStats()

    def process(self, node: FusionNode, t: float, z: PositionFix) -> bool:
        """Fuse the fix ``z`` (a :class:`PositionFix`) at ``t``; whether it was fused (:meth:`assess`)."""
        return self.assess(node, t, z).accept

    def assess(self, node: FusionNode, t: float, fix: PositionFix) -> Assessment:
        """Test ``fix`` at the node's window state ``t``, fuse it if accepted, recover
        from a divergence (see the class docstring). Returns the final assessment."""
        d = fix.dim_z
        R = fix.R

        def innovation() -> tuple[Array, Array, Array, Array]:
            m, P = node.estimate(t)
            return fix.z - m[:d], symmetrize(P[:d, :d]) + R, np.eye(d), symmetrize(P[:d, :d])

        def fuse(w: float) -> None:
            sensor = fix if w == 1.0 else PositionFix(fix.z, R / w)
            node.update(t, fix.z, sensor)
            self.fused.append((float(t), sensor))

        def inflate(Q_b: Array) -> None:
            Q = np.zeros((node.filter.n, node.filter.n))
            Q[:d, :d] = Q_b
            node.add_process_noise(t, Q)

        def supported(t0: float, t1: float) -> bool:
            return network_support(node, t0, t1, d)

        a = monitored_update(self.monitor, t, innovation, fuse, inflate, supported=supported,
                             horizon=node.reported_until)
        self.last = a
        self.stats.processed += 1
        self.stats.contributed += int(a.accept)
        self.stats.rejected += int(not a.accept)
        return a

    def status(self) -> str:
        """``"lost"`` while the current run of rejected fixes spans as many looks as the lock-out test's."""
        return "lost" if self.monitor.looks >= self.monitor.run_length else "ok"

    def health(self) -> dict[str, float]:
        """The counters, with the monitor's: mean NIS, largest windowed mean NIS, fixes
        down-weighted, lock-outs and drifts detected, recoveries."""
        st = self.monitor.stats
        return {**self.stats.as_dict(), "nis_mean": st.nis_sum / max(1, st.tested),
                "window_nis_max": st.window_nis_max, "downweighted": st.downweighted,
                "lockouts": st.lockouts, "drifts": st.drifts, "recoveries": st.recoveries}


def network_support(node: FusionNode, t0: float, t1: float, d: int = 2) -> bool:
    """Whether ``node`` holds measurement information from its neighbours on the position
    (the first ``d`` entries) of its states in ``[t0, t1]``: then its belief over that
    span rests on other sensors too, and a run of its own rejected fixes, which all share
    its observer's pose error, is no evidence that the *fused* belief is wrong
    (:class:`TargetTrackingFrontEnd`, which only judges spans that every neighbour has
    reported on, :meth:`FusionNode.reported_until`). What a quarantine withdrew
    (:mod:`dfusion.fusion.guard`) is no support."""
    for _, L, _ in node.received_information(t0, t1):
        if float(np.trace(L[:d, :d])) > ROUNDING_INFO * max(1.0, float(np.abs(L).max(initial=0.0))):
            return True
    return False
