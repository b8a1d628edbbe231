"""The stores of single-state information per state time: a node's own, total and held-back information.

:class:`InformationBlocks` keeps, per state time, one information block ``(Lambda(t), y(t))``
as arrays sorted by time key (:func:`dfusion.fusion.channel.time_key`), like
:class:`dfusion.fusion.channel.ChannelFilter`, so that a message is built with a few array
operations instead of one Python step per state time. A node (the fusion state of one
target, :class:`dfusion.fusion.target.TargetFusion`) holds three:

* ``own``: its own measurement information (shared or not);
* ``total``: what it shares, ``T(t) = own(t) - held(t) + sum_k M_k(t)`` (the channels of the
  links that are not quarantined); messages are made from it (``V_j(t) = T(t) - M_j(t)``);
  entries newer than the newest state wait there for :meth:`FusionNode.predict`;
* ``held``: own information fused here but not shared yet (``share=False``).

Differences of sums of blocks carry rounding noise; :func:`clean_difference` removes it
(the exact differences are positive semi-definite).

Stores support the receive transaction's undo without copies (:meth:`InformationBlocks.mark`,
copy on write) as well as with copies (:meth:`InformationBlocks.checkpoint`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dfusion.fusion.channel import all_of, find_keys, time_key, time_keys
from dfusion.linalg import Array

__all__ = ["Block", "InformationBlocks", "ROUNDING_RTOL", "clean_difference"]


@dataclass
class Block:
    """One state time's information block (:meth:`InformationBlocks.items`)."""

    t: float
    info: Array
    vec: Array


class InformationBlocks:
    """Single-state information per state time, as arrays sorted by time key.

    The node's own and total information (see the module docstring). Kept as
    arrays, like :class:`ChannelFilter`, so that a message is built with a few
    array operations instead of one Python step per state time. The entries live
    in ``[lo, hi)`` of buffers with spare room at the end: the usual changes
    (a new newest time, pruning the oldest) then copy nothing. The buffers are
    owned by the store and added to in place; what it hands out is a view to
    read at once (:attr:`keys` ...) or a copy.
    """

    def __init__(self, n: int) -> None:
        self._set(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, n, n)), np.zeros((0, n)))

    def _set(self, keys: np.ndarray, times: Array, info: Array, vec: Array) -> None:
        """Hold these entries (sorted by key) in new buffers with room to grow."""
        size = keys.shape[0]
        cap = max(8, 2 * size)
        self._keys = np.zeros(cap, dtype=np.int64)
        self._times = np.zeros(cap)
        self._info = np.zeros((cap,) + info.shape[1:])
        self._vec = np.zeros((cap,) + vec.shape[1:])
        self._keys[:size], self._times[:size], self._info[:size], self._vec[:size] = keys, times, info, vec
        self._lo, self._hi = 0, size
        self._shared = False   # a mark() holds these buffers: copy them before writing into them

    def _writable(self) -> None:
        """Copy the buffers if a :meth:`mark` still refers to them (copy on write)."""
        if self._shared:
            self._keys, self._times = self._keys.copy(), self._times.copy()
            self._info, self._vec = self._info.copy(), self._vec.copy()
            self._shared = False

    @property
    def keys(self) -> np.ndarray:
        return self._keys[self._lo:self._hi]

    @property
    def times(self) -> Array:
        return self._times[self._lo:self._hi]

    @property
    def info(self) -> Array:
        return self._info[self._lo:self._hi]

    @property
    def vec(self) -> Array:
        return self._vec[self._lo:self._hi]

    def __len__(self) -> int:
        return self._hi - self._lo

    def items(self) -> list[tuple[int, Block]]:
        """``(time key, Block)`` pairs, oldest first (copies, for inspection)."""
        info, vec = self.info, self.vec
        return [(k, Block(t, info[i].copy(), vec[i].copy()))
                for i, (k, t) in enumerate(zip(self.keys.tolist(), self.times.tolist()))]

    def add(self, t: float, info: Array, vec: Array) -> None:
        """Add ``(info, vec)`` at state time ``t`` (a new entry if there is none)."""
        key = time_key(t)
        keys = self.keys
        i = int(keys.searchsorted(key))
        j = self._lo + i
        if i < keys.size and keys[i] == key:
            self._writable()
            self._info[j] += info
            self._vec[j] += vec
        elif j == self._hi and j < self._keys.size:
            # a new newest entry goes into the spare room after the entries: a mark's entries
            # (up to its own end) are not written, so nothing needs copying
            self._keys[j], self._times[j], self._info[j], self._vec[j] = key, t, info, vec
            self._hi += 1
        else:
            self._set(*(np.concatenate((a[:i], np.asarray(row, dtype=a.dtype)[None], a[i:]))
                        for a, row in ((keys, key), (self.times, t), (self.info, info), (self.vec, vec))))

    def add_many(self, entries: Sequence[tuple[float, Array, Array]]) -> None:
        """Add every ``(t, info, vec)`` of ``entries`` (distinct times)."""
        if len(entries) < 4:
            for t, info, vec in entries:
                self.add(t, info, vec)
            return
        times = np.array([e[0] for e in entries], dtype=float)
        keys = time_keys(times)
        info = np.array([e[1] for e in entries], dtype=float)
        vec = np.array([e[2] for e in entries], dtype=float)
        found, pos = find_keys(self.keys, keys)
        if found.any():
            self._writable()
            self._info[self._lo + pos[found]] += info[found]
            self._vec[self._lo + pos[found]] += vec[found]
        new = ~found
        if new.any():
            keys = np.concatenate([self.keys, keys[new]])
            order = np.argsort(keys, kind="stable")
            self._set(keys[order], np.concatenate([self.times, times[new]])[order],
                      np.concatenate([self.info, info[new]])[order], np.concatenate([self.vec, vec[new]])[order])

    def subtract(self, entries: Sequence[tuple[float, Array, Array]]) -> np.ndarray:
        """Subtract ``(info, vec)`` at stored state times (information withdrawn or moved to
        another store), removing the rounding noise of the difference (:func:`clean_difference`).
        Entries at times not stored are ignored. Returns the keys changed."""
        if not entries:
            return np.zeros(0, dtype=np.int64)
        keys = time_keys(np.array([e[0] for e in entries], dtype=float))
        found, pos = find_keys(self.keys, keys)
        if not found.any():
            return np.zeros(0, dtype=np.int64)
        self._writable()
        rows = self._lo + pos[found]
        info = np.array([e[1] for e in entries], dtype=float)[found]
        vec = np.array([e[2] for e in entries], dtype=float)[found]
        scale = np.abs(self._info[rows]).max(axis=(1, 2))
        vscale = np.abs(self._vec[rows]).max(axis=1)
        self._info[rows] = clean_difference(self._info[rows] - info, scale)
        v = self._vec[rows] - vec
        v[np.abs(v) <= (ROUNDING_RTOL * vscale)[:, None]] = 0.0
        self._vec[rows] = v
        return keys[found]

    def prune(self, cutoff: int) -> None:
        """Forget the entries whose key is below ``cutoff``."""
        if self._lo < self._hi and self._keys[self._lo] < cutoff:
            self._lo += int(self.keys.searchsorted(cutoff))

    def values_at(self, keys: np.ndarray) -> tuple[Array, Array]:
        """The information at ``keys`` (zero where nothing is stored)."""
        n = self._info.shape[1]
        if len(self) and keys.size:
            found, pos = find_keys(self.keys, keys)
            if all_of(found):   # (the usual case: a message's times are stored times)
                return self.info[pos], self.vec[pos]
            info = np.zeros((keys.size, n, n))
            vec = np.zeros((keys.size, n))
            info[found] = self.info[pos[found]]
            vec[found] = self.vec[pos[found]]
            return info, vec
        return np.zeros((keys.size, n, n)), np.zeros((keys.size, n))

    def count_after(self, key: int) -> int:
        """Entries with a key above ``key``."""
        return int(len(self) - self.keys.searchsorted(key, side="right"))

    def checkpoint(self) -> tuple[np.ndarray, Array, Array, Array]:
        """Copies of the entries (to undo changes with :meth:`restore`)."""
        return self.keys.copy(), self.times.copy(), self.info.copy(), self.vec.copy()

    def restore(self, cp: tuple[np.ndarray, Array, Array, Array]) -> None:
        self._set(*cp)

    def mark(self) -> tuple:
        """A checkpoint without copies (for :meth:`rollback`): the buffers are copied when
        they are next written instead, which a receive that leaves the store alone never does."""
        self._shared = True
        return self._keys, self._times, self._info, self._vec, self._lo, self._hi

    def rollback(self, mark: tuple) -> None:
        """Go back to a :meth:`mark`."""
        self._keys, self._times, self._info, self._vec, self._lo, self._hi = mark
        self._shared = True

    def release(self) -> None:
        """The :meth:`mark` is no longer needed (the transaction succeeded): write in place again."""
        self._shared = False

    def between(self, lo: float, hi: float) -> list[tuple[float, Array, Array]]:
        """Entries with ``lo < t <= hi``, oldest first (copies)."""
        times = self.times
        if not times.size or times[-1] <= lo:
            return []
        a, b = np.searchsorted(times, (lo, hi), side="right").tolist()
        info, vec = self.info, self.vec
        return [(float(times[i]), info[i].copy(), vec[i].copy()) for i in range(a, b)]


#: Differences ``T(t) - M(t)`` smaller than this, relative to ``T(t)``, are rounding noise.
ROUNDING_RTOL = 1e-12


def clean_difference(diff: Array, scale: Array) -> Array:
    """Remove rounding noise from information differences ``T(t) - M(t)``.

    The exact difference is positive semi-definite (it is a sum of measurement
    information). Computed in floating point it carries errors of order
    ``eps * |T(t)|``: entries below ``ROUNDING_RTOL * |T(t)|`` become exactly
    zero, and rounding-level negative eigenvalues are clipped to zero.

    Blocks that are then diagonally dominant with a non-negative diagonal are
    positive semi-definite (Gershgorin) and are kept without an eigenvalue
    decomposition (diagonal blocks, such as position measurements, are the usual case).
    """
    out = diff.copy()
    out[np.abs(out) <= (ROUNDING_RTOL * scale)[:, None, None]] = 0.0
    d = np.diagonal(out, axis1=1, axis2=2)
    dominant = ((2.0 * d - np.abs(out).sum(axis=2)) >= 0.0).all(axis=1)
    rest = ~dominant
    if rest.any():
        w, V = np.linalg.eigh(out[rest])
        neg = w.min(axis=1) < 0
        if neg.any():
            w = np.where(w < 0, 0.0, w)
            fixed = np.einsum("kij,kj,klj->kil", V, w, V)
            sub = out[rest]
            sub[neg] = 0.5 * (fixed[neg] + np.transpose(fixed[neg], (0, 2, 1)))
            out[rest] = sub
    return out
