"""Output policies: what a fusion node reports, given its candidate sources.

A node holds a fused estimate (its information filter, which already includes
every neighbour's information) and possibly several *sources* of the same
quantity (its own localizers, say), each an :class:`~dfusion.estimation.Estimate`. A
:class:`Policy` decides the node's output
from them. :class:`InformationFusionPolicy`, the default, outputs the fused
estimate. Switching policies (the switching paper's greedy rule with a
punishment, hysteresis on a similarity rate, blending) implement the same
interface (``docs/background.md#6-policies-switching-alongside-fusion``).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Sequence

from dfusion.estimation.estimate import Estimate


class Policy(ABC):
    """Decides a node's output from its fused estimate and its candidate sources."""

    name: str = "policy"

    @abstractmethod
    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        """Return the node's output."""


class InformationFusionPolicy(Policy):
    """Output the information-filter fusion of all sources (the default)."""

    name = "fusion"

    def decide(self, fused: Estimate, sources: Sequence[Estimate]) -> Estimate:
        return fused


def records_output(policy: Policy) -> bool:
    """Whether a node with ``policy`` has an output of its own to record: its policy is not
    plain information fusion (whose output is the fused estimate)."""
    return type(policy) is not InformationFusionPolicy
