r"""Deleters: when a confirmed track ends.

* :class:`MissDeleter`: after ``max_misses`` consecutive scans in which the track was in
  view and took no detection (GNN: not assigned; JPDA: ``beta_t0 >= 1/2``). With
  detection probability ``P_D`` a target in view is missed ``K`` times in a row with
  probability ``(1 - P_D)^K`` (1e-5 for ``P_D = 0.9``, ``K = 5``).
* :class:`CovarianceDeleter`: when the trace of the position covariance exceeds
  ``max_trace`` (m^2): the track no longer says where the target is (e.g. it left every
  view, where it is never missed).
* :class:`StaleDeleter`: when the track's last hit is more than ``max_age`` seconds older
  than its state (it left every view, or every sensor stopped seeing it; Stone Soup's
  ``UpdateTimeDeleter`` rule).
* :class:`ObserverDeleter`: another deleter's rule for a network, where a node's tracks
  carry every node's information (:class:`~dfusion.fusion.tracking_node.TrackingNode`; a
  track's ``last_hit`` is the newest information from any node), applied only by a node whose
  own scans hit (or started) the track within ``within`` seconds (``track.seen_here``). The
  other nodes hear the same information later by the links' latency, so a rule on the age of
  the last hit (:class:`StaleDeleter`, the grace of :class:`RegionDeleter`) would give its
  verdict early there and, announced, end a track its observers still see; they leave the
  verdict to the observers and hear of the deletion. The node that saw a track last is an
  observer when its information stops (for rules whose verdict comes within ``within`` of the
  last hit), so every track is still ended by the rule, whatever the latency. In a
  centralized tracker every hit is the tracker's own: the rule is the inner deleter's.
* :class:`RegionDeleter`: when the track's estimated position has left the region where
  targets can be (the surveillance region, e.g. the union of a node's views) and its last
  scan in view was a miss: a target that walks out of a plaza is gone after one missed
  scan, where the rules above wait for several; a track whose estimate overshoots the
  border while its target, just inside, is still detected is kept.
* :class:`AnyDeleter`: when any of its deleters says so.
* :class:`NoDeleter`: never (a team of known size whose members never leave).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Callable

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.tracking.track import Track

__all__ = ["Deleter", "MissDeleter", "CovarianceDeleter", "StaleDeleter", "ObserverDeleter", "RegionDeleter",
           "AnyDeleter", "NoDeleter"]


class Deleter(ABC):
    """Component kind: whether a confirmed track should be deleted."""

    @abstractmethod
    def should_delete(self, track: Track) -> bool:
        """Whether ``track`` ends now."""


class MissDeleter(Deleter):
    """Delete after ``max_misses`` consecutive misses in view."""

    def __init__(self, max_misses: int = 5) -> None:
        if not (isinstance(max_misses, int) and max_misses >= 1):
            raise ValidationError(f"max_misses must be an integer >= 1, got {max_misses!r}")
        self.max_misses = max_misses

    def should_delete(self, track: Track) -> bool:
        return track.consecutive_misses >= self.max_misses


class CovarianceDeleter(Deleter):
    """Delete when ``trace(P_pos) > max_trace`` over the first ``axes`` state components."""

    def __init__(self, max_trace: float = 4.0, axes: int = 2) -> None:
        if not (math.isfinite(max_trace) and max_trace > 0):
            raise ValidationError(f"max_trace must be positive and finite, got {max_trace!r}")
        self.max_trace = float(max_trace)
        self.axes = int(axes)

    def should_delete(self, track: Track) -> bool:
        _, P = track.estimate()
        return float(np.trace(P[: self.axes, : self.axes])) > self.max_trace


class StaleDeleter(Deleter):
    """Delete when ``time - last_hit > max_age`` (seconds)."""

    def __init__(self, max_age: float = 1.0) -> None:
        if not (math.isfinite(max_age) and max_age > 0):
            raise ValidationError(f"max_age must be positive and finite, got {max_age!r}")
        self.max_age = float(max_age)

    def should_delete(self, track: Track) -> bool:
        last = track.born if track.last_hit is None else track.last_hit
        return track.time - last > self.max_age


class ObserverDeleter(Deleter):
    """Apply ``deleter`` only when this node's own scans hit (or started) the track within
    ``within`` seconds (``time - seen_here <= within``; module docstring). ``within`` must
    exceed the age of the last hit at which ``deleter`` ends a track (e.g. a ``StaleDeleter``'s
    ``max_age``), or the node that saw the track last no longer judges it then."""

    def __init__(self, deleter: Deleter, within: float = 1.0) -> None:
        if not isinstance(deleter, Deleter):
            raise ValidationError(f"ObserverDeleter needs a Deleter, got {deleter!r}")
        if not (math.isfinite(within) and within > 0):
            raise ValidationError(f"within must be positive and finite, got {within!r}")
        self.deleter, self.within = deleter, float(within)

    def should_delete(self, track: Track) -> bool:
        seen = getattr(track, "seen_here", None)
        if seen is None or track.time - seen > self.within + 1e-9:
            return False
        return self.deleter.should_delete(track)


class RegionDeleter(Deleter):
    """Delete when ``inside(mean)`` is false and the last hit is more than ``grace`` seconds old."""

    def __init__(self, inside: Callable[[Array], bool], grace: float = 0.15) -> None:
        if not callable(inside):
            raise ValidationError("RegionDeleter needs a callable inside(x) -> bool")
        if not (math.isfinite(grace) and grace >= 0):
            raise ValidationError(f"grace must be >= 0 and finite, got {grace!r}")
        self.inside = inside
        self.grace = float(grace)

    def should_delete(self, track: Track) -> bool:
        last = track.born if track.last_hit is None else track.last_hit
        if track.time - last <= self.grace + 1e-9:
            return False
        mean, _ = track.estimate()
        return not self.inside(mean)


class AnyDeleter(Deleter):
    """Delete when any of ``deleters`` says so."""

    def __init__(self, *deleters: Deleter) -> None:
        if not deleters:
            raise ValidationError("AnyDeleter needs at least one deleter")
        self.deleters = deleters

    def should_delete(self, track: Track) -> bool:
        return any(d.should_delete(track) for d in self.deleters)


class NoDeleter(Deleter):
    """Never delete: the targets are a team of known size that stays (e.g. the MRCLAM robots)."""

    def should_delete(self, track: Track) -> bool:
        return False
