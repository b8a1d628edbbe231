"""The fusion state of one target: its delayed-state filter, its information stores, its per-link channels.

:class:`TargetFusion` is the part of :class:`dfusion.fusion.node.FusionNode` that knows one
target's estimate and nothing of the network around it. Its state (set up by the node):

* ``filter``: the :class:`~dfusion.estimation.delayed_state.DelayedStateEIF` (common prior
  and motion, plus the single-state information of every state time in the window);
* ``_own``, ``_total``, ``_held``: the :class:`~dfusion.fusion.stores.InformationBlocks` of
  own, shared-total and held-back information (:mod:`dfusion.fusion.stores`);
* ``channels``: one :class:`~dfusion.fusion.channel.ChannelFilter` per fusion link, with what
  that link delivered per state time (``M_j(t)``) and what changed for it (``dirty``);
* ``_tree_held``: per state time, what a change of the tree took from the channels and the
  estimate keeps a while (:mod:`dfusion.fusion.following`);
* ``_pruned_at``, ``_naive_sent``: the prune mark; naive fusion's record of what it sent.

Its methods: local information in (:meth:`FusionNode.predict`, :meth:`FusionNode.update`,
:meth:`FusionNode.add_local_information`, sharing and withdrawing it), the estimate, the stores read
out (:meth:`FusionNode.information_blocks`, :meth:`FusionNode.received_information`), the value for one link
(``V_j(t) = T(t) - M_j(t)``, :meth:`FusionNode._values_for`), what a link delivered
(:meth:`FusionNode._link_blocks`), and pruning what left the window. The node's other parts (receiving,
the steady path, the guard, the tree rule, sending) call these and reach the target's state
through them or directly within one receive transaction. What this part asks of the node:
``_settle`` (the bookkeeping left for later is done before the state is read or changed),
``is_quarantined`` (a quarantined link's value is ``T(t)``) and ``_release_tree_held`` (held
times expire as the trajectory moves on).

Multi-target tracking (``docs/architecture.md``, "Tracks") turns this part into one object
per track, each with these attributes; today the node is its single instance.
"""
from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import OutsideWindowError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.fusion.channel import any_of, nonzero_blocks, ChannelFilter, time_key
from dfusion.fusion.stats import node_log as log
from dfusion.fusion.stores import InformationBlocks, clean_difference
from dfusion.linalg import Array, as_matrix, as_time, as_vector, check_psd, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel

__all__ = ["TargetFusion"]


class TargetFusion:
    """The fusion state of one target (see the module docstring); a part of :class:`FusionNode`."""

    # the target's state (set by the node; declared here so that it is read in one place)
    filter: DelayedStateEIF
    channels: dict[str, ChannelFilter]
    _own: InformationBlocks
    _total: InformationBlocks
    _held: InformationBlocks
    _tree_held: dict[int, tuple[float, Array, Array, float]]
    _pruned_at: float
    _naive_sent: dict[str, dict[int, tuple[Array, Array]]]
    @property
    def motion(self) -> MotionModel:
        return self.filter.motion

    @property
    def latest_time(self) -> float:
        return self.filter.latest_time

    def predict(self, t: float, u: ArrayLike | None = None) -> None:
        """Advance the trajectory to ``t`` (or add a state at a past ``t`` in the window)."""
        self._settle()
        f = self.filter
        t = as_time(t)
        if t <= f.latest_time + f.time_tol:
            if t < f.oldest_time - f.time_tol:
                raise OutsideWindowError(f"time {t} is older than the window start {f.oldest_time}")
            f.ensure_state(t)
            self._prune()
            return
        pending = self._total.between(f.latest_time + f.time_tol, t + f.time_tol)
        if pending:
            with f.transaction():
                f.predict(t, u)
                f.add_information_batch(pending, validate=False)
        else:
            f.predict(t, u)
        self._prune()
        if self._tree_held:
            self._release_tree_held(t)

    def update(self, t: float, z: ArrayLike, sensor: MeasurementModel, *, share: bool = True) -> tuple[Array, Array]:
        """Fuse a local measurement taken at ``t`` (``t`` may be in the past, inside the window).

        Returns the single-state information ``(Lambda, y)`` it added. With ``share=False``
        it is fused here but held back from the neighbours until
        :meth:`share_local_information` (or removed by :meth:`withdraw_local_information`).
        """
        self._settle()
        f = self.filter
        t = self._window_time(t, "measurement")
        Lam, y = f.update(t, z, sensor)
        self._add_own(t, Lam, y, share)
        self._prune()
        return Lam, y

    def _window_time(self, t: float, what: str) -> float:
        """``t`` as a time, checked to be inside the window (``what``: the error's word for it)."""
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol or t > f.latest_time + f.time_tol:
            raise OutsideWindowError(f"{what} time {t} is outside the window [{f.oldest_time}, {f.latest_time}]")
        return t

    def add_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike, *,
                              share: bool = True) -> None:
        """Fuse information produced by a local estimator at time ``t``.

        For sensors whose measurements are not fused by the EIF itself, such as a
        particle filter (:mod:`dfusion.frontends.base`: the Gaussian fit of its posterior
        minus that of its prediction, in information form). The information counts as
        this node's own, exactly like a measurement: it is shared with the
        neighbours and never double counted. ``info_matrix`` must be symmetric
        positive semi-definite, of the state's dimension. With ``share=False`` it is
        fused here but held back from the neighbours (a tentative data association, for
        instance) until :meth:`share_local_information`, or removed by
        :meth:`withdraw_local_information`.
        """
        self._settle()
        f = self.filter
        t = self._window_time(t, "information")
        Lam = as_matrix(info_matrix, (f.n, f.n), "information matrix")
        check_psd(Lam, "information matrix")
        Lam = symmetrize(Lam)
        y = as_vector(info_vector, f.n, "information vector")
        with f.transaction():
            f.add_information_batch([(t, Lam, y)], validate=False)
            f.estimate()
        self._add_own(t, Lam, y, share)
        self._prune()

    def share_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike) -> bool:
        """Start sharing own information fused earlier with ``share=False``: it moves from the
        held-back store to what the node shares, and its time is marked changed on every link,
        so the next (partial) messages carry it. Returns False (nothing to share) when ``t`` has
        left the window."""
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol:
            return False
        Lam = np.asarray(info_matrix, dtype=float)
        y = np.asarray(info_vector, dtype=float)
        self._held.subtract([(t, Lam, y)])
        self._total.add(t, Lam, y)
        self._mark_dirty([time_key(t)])
        return True

    def withdraw_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike, *,
                                   shared: bool = True) -> bool:
        """Remove own information added earlier at ``t`` (a front end found it suspect).

        The filter and the node's own information lose ``(info_matrix, info_vector)``. If it
        was shared (``shared``), the time is marked changed on every link, so the next
        messages carry the smaller block (or clear the time): the neighbours replace what
        they stored and lose it too, and forward the change. Removing information is never
        over-confident. Returns False (and changes nothing) when ``t`` is outside the window:
        older information is marginalized into the window's base and stays.
        """
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol or t > f.latest_time + f.time_tol:
            return False
        Lam = np.asarray(info_matrix, dtype=float)
        y = np.asarray(info_vector, dtype=float)
        with f.transaction():
            f.add_information_batch([(t, -Lam, -y)], validate=False)
            f.estimate()
        self._own.subtract([(t, Lam, y)])
        if shared:
            self._total.subtract([(t, Lam, y)])
            self._mark_dirty([time_key(t)])
        else:
            self._held.subtract([(t, Lam, y)])
        return True

    def add_process_noise(self, t: float, Q_extra: ArrayLike) -> None:
        """Add process noise ``Q_extra`` to this node's motion step ending at the window
        state ``t`` (:meth:`DelayedStateEIF.add_process_noise`): a local re-initialization
        of a diverged belief (a recovery, :mod:`dfusion.estimation.innovation`).

        Nothing exchanged changes: messages and channel filters carry single-state
        (measurement) information per state time, and this changes a motion factor, which
        is never sent; the own, held-back and received stores and the channels are
        untouched, so no information is counted twice or lost, whether messages are full or
        partial. The node's belief becomes the posterior of all the measurement
        information it holds under its motion model with the extra noise, wider than
        before; its neighbours keep the nominal model until they recover too. With a
        guard (:mod:`dfusion.fusion.guard`) the wider belief only makes the neighbours'
        information pass its test more easily (``docs/robots.md``).
        """
        self._settle()
        self.filter.add_process_noise(t, Q_extra)
        log.info("%s: process noise added at t=%.3f (trace %.3g)", self.name, float(t),
                 float(np.trace(np.asarray(Q_extra, dtype=float))))

    def estimate(self, t: float | None = None) -> tuple[Array, Array]:
        """Fused ``(mean, cov)`` of the newest state, or of the window state at ``t``."""
        return self.filter.estimate(t)

    def received_information(self, t0: float, t1: float) -> list[tuple[float, Array, Array]]:
        """The measurement information this node fuses from its neighbours at the window
        states with ``t0 <= t <= t1``, oldest first: the total (own shared plus received;
        what a quarantine withdrew is not in it) minus the own shared part
        (``own - held``)."""
        self._settle()
        tol = self.filter.time_tol
        own = {time_key(t): (L, y) for t, L, y in self._own.between(t0 - tol, t1 + tol)}
        held = {time_key(t): (L, y) for t, L, y in self._held.between(t0 - tol, t1 + tol)}
        out = []
        for t, L, y in self._total.between(t0 - tol, t1 + tol):
            k = time_key(t)
            L, y = np.array(L, dtype=float), np.array(y, dtype=float)
            if k in own:
                L, y = L - own[k][0], y - own[k][1]
            if k in held:
                L, y = L + held[k][0], y + held[k][1]
            out.append((t, L, y))
        return out

    def information_blocks(self, own: bool = False) -> tuple[np.ndarray, Array, Array]:
        """The single-state information this node shares per state time: ``(time keys, info, vec)``
        (copies), its own and what it received (also blocks held back for times ahead of its
        newest state), or with ``own`` its own only; both without the own information it fused
        but does not share yet (``share=False``)."""
        self._settle()
        if not own:
            return self._total.keys.copy(), self._total.info.copy(), self._total.vec.copy()
        keys = self._own.keys.copy()
        held = self._held.values_at(keys)
        return keys, self._own.info - held[0], self._own.vec - held[1]

    def newest_information_time(self) -> float | None:
        """The newest state time in the window holding information (own, or received over a
        link), or ``None``: the filter then holds the common prior and motion only."""
        self._settle()
        times = self._total.times
        return float(times[-1]) if times.size else None

    def own_information(self) -> Sequence[tuple[float, Array, Array]]:
        """This node's own measurement information per state time, oldest first."""
        self._settle()
        return [(e.t, e.info, e.vec) for _, e in self._own.items()]

    def _add_own(self, t: float, Lam: Array, y: Array, share: bool = True) -> None:
        self._own.add(t, Lam, y)
        if share:
            self._total.add(t, Lam, y)
            self._mark_dirty([time_key(t)])
        else:
            self._held.add(t, Lam, y)

    def _mark_dirty(self, keys: Iterable[int], skip: str | None = None) -> None:
        """The value for every neighbour but ``skip`` changed at ``keys``: the next messages carry them."""
        keys = list(keys)
        if keys:
            for j, ch in self.channels.items():
                if j != skip:
                    ch.dirty.update(keys)

    def _values_for(self, ch: ChannelFilter, keys: np.ndarray) -> tuple[Array, Array]:
        """``V(t) = T(t) - M(t)`` for ``ch``'s neighbour at ``keys`` (rounding noise removed);
        ``T(t)`` for a quarantined neighbour, whose information ``T`` does not hold."""
        infos, vecs = self._total.values_at(keys)
        if self.is_quarantined(ch.remote):
            return infos, vecs
        if not len(ch) or not keys.size:
            return infos, vecs
        found, pos = ch.lookup(keys)
        if not any_of(found):   # the neighbour sent nothing for these times (a new block)
            return infos, vecs
        held = np.zeros(keys.size, dtype=bool)
        held[found] = nonzero_blocks(ch.info[pos[found]], ch.vec[pos[found]])
        if any_of(held):
            m_info, m_vec = ch.info[pos[held]], ch.vec[pos[held]]
            scale = np.abs(infos[held]).max(axis=(1, 2))
            infos[held] = clean_difference(infos[held] - m_info, scale)
            vecs[held] -= m_vec
        return infos, vecs

    def _link_blocks(self, ch: ChannelFilter, sign: float = 1.0) -> tuple[list, list]:
        """The channel's stored blocks in the window as ``(t, info, vec)`` times ``sign``:
        ``(those the filter holds, all)``; the others are newer than the newest state and wait
        in the total store for :meth:`FusionNode.predict`."""
        if not len(ch):
            return [], []
        f = self.filter
        latest = f.latest_time + f.time_tol
        live = nonzero_blocks(ch.info, ch.vec) & (ch.times >= f.oldest_time - f.time_tol)
        every = [(float(ch.times[i]), sign * ch.info[i], sign * ch.vec[i]) for i in np.flatnonzero(live).tolist()]
        return [e for e in every if e[0] <= latest], every

    def _received_at(self, keys: np.ndarray) -> tuple[Array, Array]:
        """``R(t) = T(t) - own(t) + H(t)`` at ``keys``: what the current channels delivered and the
        filter holds (``T`` is what the node shares: its shared own information and what came
        over links that are not quarantined; ``H`` its own information not shared yet)."""
        tot, own, held = self._total.values_at(keys), self._own.values_at(keys), self._held.values_at(keys)
        return tot[0] - own[0] + held[0], tot[1] - own[1] + held[1]

    def _add_to_filter(self, entries: list) -> None:
        f = self.filter
        with f.transaction():
            f.add_information_batch(entries, validate=False)
            f.estimate()   # prior, motion and own information stay: the belief stays proper

    def _prune(self) -> None:
        oldest = self.filter.oldest_time
        if oldest <= self._pruned_at:
            return
        self._pruned_at = oldest
        cutoff = time_key(oldest) - 1
        self._own.prune(cutoff)
        self._total.prune(cutoff)
        self._held.prune(cutoff)
        for k in [k for k in self._tree_held if k < cutoff]:
            del self._tree_held[k]
        for ch in self.channels.values():
            ch.prune(cutoff)
