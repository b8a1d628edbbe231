"""Output policies: what a fusion node reports, given its candidate sources.

A node holds a fused estimate (its information filter, which already includes
every neighbour's information) and possibly several *sources* of the same
quantity (its own localizers, say). A :class:`Policy` decides the node's output
from them. :class:`InformationFusionPolicy`, the default, outputs the fused
estimate. Switching policies (the switching paper's greedy rule with a
punishment, hysteresis on a similarity rate, blending) implement the same
interface (``docs/background.md#6-policies-switching-alongside-fusion``).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

from dfusion.linalg import Array


@dataclass(frozen=True)
class SourceEstimate:
    """One candidate estimate of a node's quantity.

    Attributes
    ----------
    name : str
        The source (``"fused"`` for the node's information filter).
    t : float
        Time of the estimate.
    mean, cov : ndarray
        The Gaussian estimate.
    reliability : float
        In ``[0, 1]``; 1 for the fused estimate unless a model says otherwise.
    healthy : bool
        False while the source is in an error state (then counts as reliability 0).
    """

    name: str
    t: float
    mean: Array
    cov: Array
    reliability: float = 1.0
    healthy: bool = True


class Policy(ABC):
    """Decides a node's output from its fused estimate and its candidate sources."""

    name: str = "policy"

    @abstractmethod
    def decide(self, fused: SourceEstimate, sources: Sequence[SourceEstimate]) -> SourceEstimate:
        """Return the node's output."""


class InformationFusionPolicy(Policy):
    """Output the information-filter fusion of all sources (the default)."""

    name = "fusion"

    def decide(self, fused: SourceEstimate, sources: Sequence[SourceEstimate]) -> SourceEstimate:
        return fused
