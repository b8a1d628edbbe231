r"""Front ends of a phone's indoor localization network: the PDR + magnetic particle filter and radio fingerprints.

The network is a tree of :class:`~dfusion.fusion.FusionNode` s over a position state (the first two
entries; a constant-velocity model, like the WSN network's): the **phone** node runs a
:class:`~dfusion.localization.magnetic_pf.MagneticLocalizer`, a **WiFi** node and a **beacon** node
each run a :class:`~dfusion.localization.fingerprint.FingerprintLocalizer`. Channel filters on the
links count every contribution once.

* :class:`FingerprintFrontEnd` turns a scan into the pseudo-measurement ``z = p_hat`` with the
  fingerprint's calibrated covariance (:func:`~dfusion.frontends.base.position_information`).
* :class:`MagneticFrontEnd` moves its particles with every step and weights them by the step's
  magnetic reading; at each exchange it (1) contributes what its magnetic readings added since the
  previous exchange (:meth:`MagneticLocalizer.information_contribution`: zero while the particle set
  is spread over several corridors, so a multi-modal set never sends a narrow Gaussian around a
  point between its modes), and (2) re-weights its particles by the information its neighbours sent
  (:meth:`FusionNode.received_information`: the node's total minus its own share, so its own
  contribution never comes back to it), scaled by ``radio_weight``. Radio fixes of one walk have
  errors correlated in time (the same shops' access points, the same bias for seconds), which the
  network, treating them as independent, would over-count; ``radio_weight < 1`` tempers them in the
  particle filter, the WSN tracker's ``std_scale`` for correlated readings.

The phone node's output is its particle filter's Gaussian fit: PDR and magnetic readings in the
particles, the radio information from the network in the weights.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfusion.errors import OutsideWindowError
from dfusion.frontends.base import FrontEnd, FrontEndStats, embed_position_information, position_information
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array
from dfusion.localization.fingerprint import FingerprintLocalizer
from dfusion.localization.magnetic_pf import MagneticLocalizer

__all__ = ["FingerprintFrontEnd", "MagneticFrontEnd", "MagneticStats"]


class FingerprintFrontEnd(FrontEnd):
    """A radio fingerprint node's front end: each scan's fix as a position pseudo-measurement."""

    def __init__(self, localizer: FingerprintLocalizer) -> None:
        self.localizer = localizer
        self.stats = FrontEndStats()
        self.last: tuple[float, Array, Array] | None = None

    def process(self, node: FusionNode, t: float, z: dict[str, float]) -> bool:
        """Locate the scan ``z`` (transmitter -> RSSI) taken at ``t`` and fuse it; False if nothing known was heard."""
        self.stats.processed += 1
        fix = self.localizer.locate(z)
        if fix is None:
            self.stats.rejected += 1
            return False
        Lam, y = position_information(fix.mean, fix.cov, node.filter.n)
        node.add_local_information(t, Lam, y)
        self.last = (t, fix.mean, fix.cov)
        self.stats.contributed += 1
        return True


@dataclass
class MagneticStats(FrontEndStats):
    """Counters of a magnetic front end: ``steps`` moved, ``withheld`` exchanges without a contribution
    (multi-modal set), ``absorbed`` exchanges whose received information re-weighted the particles."""

    steps: int = 0
    withheld: int = 0
    absorbed: int = 0


class MagneticFrontEnd(FrontEnd):
    """The phone node's front end (module docstring)."""

    def __init__(self, localizer: MagneticLocalizer, radio_weight: float = 0.5, max_std: float = 3.0,
                 inject: float = 0.0, floor: float = 0.0) -> None:
        self.localizer = localizer
        self.radio_weight = float(radio_weight)
        self.max_std = float(max_std)
        self.inject = float(inject)
        self.floor = float(floor)
        self.stats = MagneticStats()
        self._absorbed_until = -np.inf

    def step(self, t: float, w: float, psi: float, field: Array | None) -> None:
        """One detected step (see :meth:`MagneticLocalizer.step`)."""
        self.localizer.step(t, w, psi, field)
        self.stats.steps += 1

    def process(self, node: FusionNode, t: float, z: None = None) -> bool:
        """Contribute the magnetic information since the last call at ``t``; True if some was fused."""
        f = node.filter
        if t < f.oldest_time - f.time_tol:   # refused before the localizer's reference moves (nothing lost)
            raise OutsideWindowError(f"magnetic contribution at t={t} is older than the window start {f.oldest_time}")
        self.stats.processed += 1
        info = self.localizer.information_contribution(self.max_std)
        if not np.any(info.Omega):
            self.stats.withheld += 1
            return False
        Lam, y = embed_position_information(info.Omega, info.eta, node.filter.n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        return True

    def absorb(self, node: FusionNode, t: float) -> bool:
        """Re-weight the particles by the neighbours' information at states after the last absorption, up to ``t``."""
        got = [(tt, L, y) for tt, L, y in node.received_information(self._absorbed_until, t)
               if tt > self._absorbed_until + node.filter.time_tol]
        if not got:
            self._absorbed_until = max(self._absorbed_until, float(t))
            return False
        Om = sum(L[:2, :2] for _, L, _ in got)
        eta = sum(y[:2] for _, _, y in got)
        if np.any(Om):   # (moved past only once the re-weighting went through: a raise loses nothing)
            self.localizer.reweight_information(self.radio_weight * eta, self.radio_weight * Om, self.inject,
                                                 self.floor)
        self._absorbed_until = max(self._absorbed_until, float(t))
        if not np.any(Om):
            return False
        self.stats.absorbed += 1
        return True

    def estimate(self) -> tuple[Array, Array]:
        """The particle filter's Gaussian fit of ``(x, y)``."""
        return self.localizer.estimate()
