"""The consistency guard in the node: tests inside the receive transaction, quarantine and probation.

:class:`dfusion.fusion.guard.NeighbourGuard` keeps the records and makes the decisions (a
pure bookkeeping of verdicts per link); this part is where a node uses it: the blocks a
message adds are tested jointly against the node's belief as they are added
(:meth:`GuardedLinks._add_tested`, or later from saved moments on the steady path,
:meth:`GuardedLinks._deferred_test`), a neighbour that keeps failing is quarantined and
everything that came over its link is withdrawn from the filter and from what the node
shares (:meth:`GuardedLinks._withdraw`), a message over a quarantined link is a probation
test of the neighbour's whole contribution (:meth:`GuardedLinks._probation`), and a
released link's information is added back (:meth:`GuardedLinks._reinstate`).
"""
from __future__ import annotations

import math

from dfusion.errors import DfusionError
from dfusion.fusion.channel import ChannelFilter, time_keys
from dfusion.fusion.guard import block_eigen, information_statistic, split_blocks, split_blocks_eigen
from dfusion.linalg import Array

import numpy as np

__all__ = ["GuardedLinks"]


class GuardedLinks:
    """The guard's use in the node (see the module docstring); a part of :class:`FusionNode`."""
    def is_quarantined(self, neighbor: str) -> bool:
        """Whether the link to ``neighbor`` is quarantined (its information withdrawn)."""
        return self._guard is not None and self._guard.is_quarantined(neighbor)

    def health(self) -> str:
        """``"ok"``, ``"degraded"`` or ``"lost"`` (:meth:`NeighbourGuard.health`; always ok without a guard)."""
        if self._guard is None:
            return "ok"
        self._settle()   # (a verdict left for settle() counts)
        return self._guard.health()

    def _add_tested(self, entries: list[tuple[float, Array, Array]]) -> tuple[float, int, int]:
        """Add a message's blocks to the filter, testing the additions jointly (inside the
        caller's transaction). Returns ``(D^2, dof, blocks tested)``
        (:func:`dfusion.fusion.guard.information_statistic`)."""
        f = self.filter
        eigen = stacked = None   # (one decomposition for the split and the statistic)
        if len(entries) == 1:
            eigen = block_eigen(entries[0][1])
            add, other = split_blocks(entries, eigen)
        else:
            add, other, stacked = split_blocks_eigen(entries)
        if other:
            f.add_information_batch(other, validate=False)
        if not add:
            return 0.0, 0, 0
        mu0, P0, mu1 = f.add_information_moments(add, exact_covariances=False)   # (bounds: the statistic
        stat, dof = information_statistic(add, mu0, P0, mu1, eigen, stacked)    # asks for P0 if they do not decide)
        return stat, dof, len(add)

    def _deferred_test(self, block: tuple[float, Array, Array], mu0: Array, P0: Array, mu1: Array) -> tuple[float, int, int]:
        """:meth:`_add_tested`'s verdict of one block at the newest state, from the moments saved
        when it was added (the same values: :meth:`DelayedStateEIF.add_information_moments` reads
        the same filtered moments), for :meth:`FusionNode.settle`."""
        eigen = block_eigen(block[1])
        add, _ = split_blocks([block], eigen)
        if not add:
            return 0.0, 0, 0
        stat, dof = information_statistic(add, [mu0], [P0], [mu1], eigen)
        return stat, dof, 1

    def _record_verdict(self, src: str, n_blocks: int, verdict: tuple | None) -> bool:
        """Record a message of ``src`` with ``n_blocks`` blocks in its link's guard record: the
        blocks :meth:`_add_tested` did not test, and the test's verdict (``None``: nothing was
        tested). True when ``src`` is to be quarantined now (:meth:`NeighbourGuard.judge`)."""
        guard = self._guard
        guard.links[src].untested_blocks += n_blocks - (verdict[2] if verdict else 0)
        return verdict is not None and guard.judge(src, verdict[0], verdict[1])

    def _withdraw(self, neighbor: str) -> None:
        """Remove everything that came over the link to ``neighbor`` (quarantine): from the filter
        and from what the node shares; the other links are sent the changed times. Times held
        after a change of the tree are let go first (the filter then holds what its channels
        delivered, :meth:`FusionNode._release_tree_held`): what it subtracts is in the filter once."""
        self._release_tree_held(math.inf)
        now, every = self._link_blocks(self.channels[neighbor], -1.0)
        if now:
            self.filter.add_information_batch(now, validate=False)
            self.filter.estimate()
        changed = self._total.subtract([(t, -L, -y) for t, L, y in every])
        self._mark_dirty(changed.tolist(), skip=neighbor)

    def _reinstate(self, neighbor: str) -> None:
        """Add the neighbour's current contribution back (the link leaves quarantine); held
        times are let go first, as in :meth:`_withdraw`."""
        self._release_tree_held(math.inf)
        now, every = self._link_blocks(self.channels[neighbor])
        if now:
            self.filter.add_information_batch(now, validate=False)
            self.filter.estimate()
        if every:
            self._total.add_many(every)
            self._mark_dirty(time_keys(np.array([e[0] for e in every])).tolist(), skip=neighbor)

    def _probation(self, neighbor: str, ch: ChannelFilter) -> str | None:
        """A message over a quarantined link: test the neighbour's whole current contribution
        against this node's belief (a trial: nothing is kept); after ``release`` passes in a
        row, take it back. Returns ``"released"`` then."""
        now, _ = self._link_blocks(ch)
        add, _ = split_blocks(now)
        if not add:
            return None
        f = self.filter
        try:
            with f.trial():
                mu0, P0, mu1 = f.add_information_moments(add, exact_covariances=False)
                stat, dof = information_statistic(add, mu0, P0, mu1)
        except DfusionError:
            stat, dof = math.inf, 1
        if self._guard.probation(neighbor, stat, dof):
            self._reinstate(neighbor)
            return "released"
        return None
