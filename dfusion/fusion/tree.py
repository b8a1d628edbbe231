r"""The tree rule: which of the links that exist carry fusion, decided by each node from its neighbours' messages.

Channel-filter fusion is exact only on a tree (``docs/fusion.md``). When links appear and
disappear at run time (robots driving in and out of radio range, nodes joining and
leaving) the nodes must keep the fusion links a tree without any node knowing the whole
graph. :class:`SpanningTree` is one node's state of that rule: a pure state machine (no
I/O, no numpy) that :class:`~dfusion.fusion.FusionNode` drives with what it hears and
with the links its transport reports (``docs/dynamic-topology.md``).

**Tree epochs.** Every node holds a *tree epoch* ``E = (term, root)``. Epochs are totally
ordered: the higher term is newer; of two epochs with the same term the one whose root's
name sorts first is newer. Every message carries its sender's epoch and its parent (a
*beacon* is a message without blocks; beacons go over every link that exists, fusion
messages over tree links only).

* **Adoption.** A node that hears a strictly newer epoch from a neighbour adopts it and
  takes that neighbour as its parent. The neighbour had adopted the epoch before, so
  within one epoch every parent adopted it strictly earlier than its children: parent
  pointers of one epoch form a forest, whatever cycles the radio graph has, and a node
  keeps its parent for as long as it stays in the epoch (it never returns to an epoch it
  left: it only ever adopts newer ones).
* **Tree links.** The tree links of a node are the link to its parent and the links to
  the neighbours whose latest message names it as their parent, *in the same epoch*.
* **Link breaks.** A non-tree link that breaks changes nothing. A child's link that breaks
  ends that tree link (the node withdraws what came over it). The parent's link that
  breaks makes the node the root of a new epoch ``(max term seen + 1, itself)``, newer than
  every epoch it has heard of: it floods through the node's subtree and over any other
  link, so the component re-forms.
* **Joins.** A node that joins a running network (or restarts) starts in the epoch
  ``(0, itself)``, older than the epochs of the running network (their terms are at least
  :data:`START_TERM`): it adopts the network's epoch and the network does not re-form.

:class:`TreeChange` says what an event changed: a new epoch (the node withdraws
everything it received and starts fresh channels), tree links lost (withdraw what came
over them) and gained (fresh channels, full messages first). Why that never double counts
is argued in ``docs/dynamic-topology.md``.

:func:`initial_parents` computes the tree a network starts with (breadth-first from the
smallest name of each component of the links that exist at the start: the tree the rule
settles on when every message takes the same time), and :func:`forest_settled` checks
from the outside (a simulator, a test) whether the rule has settled.
"""
from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

__all__ = ["TreeEpoch", "TreeChange", "SpanningTree", "NodeTreeState", "START_TERM", "JOIN_TERM",
           "initial_parents", "forest_settled", "tree_components"]

#: Term of the epochs a network starts with (:func:`initial_parents`).
START_TERM = 1
#: Term of a node that joins a running network or restarts: older than any running epoch.
JOIN_TERM = 0


@functools.total_ordering
@dataclass(frozen=True)
class TreeEpoch:
    """A tree epoch ``(term, root)``; ``a < b`` means ``b`` is newer (higher term, then smaller root name)."""

    term: int
    root: str

    def __post_init__(self) -> None:
        if isinstance(self.term, bool) or not isinstance(self.term, int) or self.term < 0:
            raise ValueError(f"a tree epoch's term must be a non-negative integer, got {self.term!r}")
        if not isinstance(self.root, str) or not self.root:
            raise ValueError(f"a tree epoch's root must be a node name, got {self.root!r}")

    def __lt__(self, other: object) -> bool:
        if not isinstance(other, TreeEpoch):
            return NotImplemented
        return self.term < other.term or (self.term == other.term and self.root > other.root)

    def __str__(self) -> str:
        return f"({self.term}, {self.root})"


@dataclass(frozen=True)
class TreeChange:
    """What one event changed at a node (all empty: nothing).

    Attributes
    ----------
    new_epoch : bool
        The node is in a new epoch: it withdraws everything it received and every tree
        link starts with a fresh channel.
    lost : frozenset of str
        Tree links that ended (withdraw what came over them).
    gained : frozenset of str
        Tree links that began (a fresh channel each).
    """

    new_epoch: bool = False
    lost: frozenset[str] = frozenset()
    gained: frozenset[str] = frozenset()

    def __bool__(self) -> bool:
        return self.new_epoch or bool(self.lost) or bool(self.gained)


@dataclass(frozen=True)
class NodeTreeState:
    """A node's view of the tree, for outside checks (:func:`forest_settled`) and figures."""

    name: str
    epoch: TreeEpoch
    parent: str | None
    tree_links: frozenset[str]


class SpanningTree:
    """One node's state of the tree rule (module docstring).

    Parameters
    ----------
    name : str
        This node.
    links : iterable of str
        The links that exist now.
    epoch : TreeEpoch, optional
        The epoch to start in (default ``(JOIN_TERM, name)``: a joining node).
    parent : str, optional
        The parent in ``epoch`` (must be one of ``links``); ``None``: the root of ``epoch``.
    known : mapping of str to (TreeEpoch, parent), optional
        What the node knows of its neighbours at the start (a configured start, see
        :func:`initial_parents`): their epoch and parent.

    Attributes
    ----------
    epoch : TreeEpoch
    parent : str or None
    links : set of str
    max_term : int
        The largest term this node has seen.
    epochs_started, epochs_adopted : int
        How often this node became the root of a new epoch, and adopted a neighbour's.
    """

    def __init__(self, name: str, links: Iterable[str] = (), *, epoch: TreeEpoch | None = None,
                 parent: str | None = None,
                 known: Mapping[str, tuple[TreeEpoch, str | None]] | None = None) -> None:
        if not isinstance(name, str) or not name:
            raise ValueError("a node name must be a non-empty string")
        self.name = name
        self.links: set[str] = set(links)
        if name in self.links:
            raise ValueError(f"{name!r} cannot link to itself")
        self.epoch = TreeEpoch(JOIN_TERM, name) if epoch is None else epoch
        if parent is None and self.epoch.root != name:
            raise ValueError(f"{name!r} without a parent must be the root of its epoch {self.epoch}")
        if parent is not None and (parent not in self.links or self.epoch.root == name):
            raise ValueError(f"parent {parent!r} of {name!r} must be a link, and the root has no parent")
        self.parent = parent
        #: What each neighbour's latest message said: ``(epoch, parent)``; kept while the link exists.
        self.heard: dict[str, tuple[TreeEpoch, str | None]] = {}
        #: The newest epoch heard from each neighbour (kept across link breaks: older messages are stale).
        self.seen: dict[str, TreeEpoch] = {}
        for j, (e, p) in (known or {}).items():
            if j in self.links:
                self.heard[j] = (e, p)
                self.seen[j] = e
        self.max_term = max([self.epoch.term] + [e.term for e in self.seen.values()])
        self.epochs_started = 0
        self.epochs_adopted = 0

    def __repr__(self) -> str:
        return (f"SpanningTree({self.name!r}, epoch={self.epoch}, parent={self.parent!r}, "
                f"tree={sorted(self.tree_links())}, links={sorted(self.links)})")

    # ------------------------------------------------------------------ views
    def children(self) -> frozenset[str]:
        """Neighbours whose latest message names this node as their parent in this node's epoch."""
        return frozenset(j for j, (e, p) in self.heard.items()
                         if p == self.name and e == self.epoch and j in self.links and j != self.parent)

    def tree_links(self) -> frozenset[str]:
        """The links that carry fusion: the parent's and the children's."""
        kids = self.children()
        return kids | {self.parent} if self.parent is not None else kids

    def is_tree_link(self, j: str) -> bool:
        return j in self.tree_links()

    def state(self) -> NodeTreeState:
        return NodeTreeState(self.name, self.epoch, self.parent, self.tree_links())

    def snapshot(self) -> tuple:
        """Everything the events change (to undo them with :meth:`restore`)."""
        return (self.epoch, self.parent, set(self.links), dict(self.heard), dict(self.seen), self.max_term,
                self.epochs_started, self.epochs_adopted)

    def restore(self, snap: tuple) -> None:
        (self.epoch, self.parent, links, heard, seen, self.max_term, self.epochs_started,
         self.epochs_adopted) = snap
        self.links, self.heard, self.seen = set(links), dict(heard), dict(seen)

    # ------------------------------------------------------------------ events
    def _change(self, before: frozenset[str], new_epoch: bool) -> TreeChange:
        after = self.tree_links()
        if new_epoch:
            return TreeChange(True, before, after)
        return TreeChange(False, before - after, after - before)

    def _start_epoch(self) -> None:
        self.max_term += 1
        self.epoch = TreeEpoch(self.max_term, self.name)
        self.parent = None
        self.epochs_started += 1

    def link_up(self, j: str) -> TreeChange:
        """A link to ``j`` now exists. Nothing else changes until a message crosses it."""
        if j == self.name:
            raise ValueError(f"{self.name!r} cannot link to itself")
        self.links.add(j)
        return TreeChange()

    def link_down(self, j: str) -> TreeChange:
        """The link to ``j`` is gone: the parent's starts a new epoch, a child's ends that tree link."""
        before = self.tree_links()
        self.links.discard(j)
        self.heard.pop(j, None)
        if j == self.parent:
            self._start_epoch()
            return self._change(before, True)
        return self._change(before, False)

    def forget(self, j: str) -> TreeChange:
        """``j`` restarted (a new incarnation): what it said before no longer holds.

        Like the link going down and coming back: if ``j`` was the parent this node starts a
        new epoch, if it was a child that tree link ends.
        """
        linked = j in self.links
        change = self.link_down(j)
        self.seen.pop(j, None)
        if linked:
            self.links.add(j)
        return change

    def heard_from(self, j: str, epoch: TreeEpoch, parent: str | None) -> TreeChange:
        """``j``'s message said it is in ``epoch`` with ``parent`` (``None``: it is the root).

        ``parent`` is this node's name only when the message was addressed to this
        incarnation of it (the caller checks). A message older than what ``j`` said before
        (a lower epoch: reordered on the way) is ignored. ``j`` must be a link.
        """
        if j not in self.links:
            raise ValueError(f"{self.name!r} has no link to {j!r}")
        last = self.seen.get(j)
        if last is not None and epoch < last:
            return TreeChange()          # stale: j only ever moves to newer epochs
        self.seen[j] = epoch
        self.max_term = max(self.max_term, epoch.term)
        before = self.tree_links()
        if epoch > self.epoch:
            self.epoch, self.parent = epoch, j
            self.epochs_adopted += 1
            self.heard[j] = (epoch, parent)
            return self._change(before, True)
        if j == self.parent and parent == self.name:
            return TreeChange()          # inconsistent (a cycle of two): keep what was heard before
        self.heard[j] = (epoch, parent)
        return self._change(before, False)


def initial_parents(nodes: Iterable[str], links: Iterable[tuple[str, str]]) -> dict[str, tuple[TreeEpoch, str | None]]:
    """The tree a network starts with: per node its epoch and parent.

    Breadth-first from the smallest name of each connected component of ``links``
    (neighbours in name order), in the epoch ``(START_TERM, that name)``. On a graph that is
    already a tree this is the tree itself; nodes built with it (``FusionNode(...,
    tree_start=...)``) exchange fusion messages from the first send on, like a fixed tree.
    """
    adj: dict[str, set[str]] = {n: set() for n in nodes}
    for a, b in links:
        if a not in adj or b not in adj:
            raise ValueError(f"link {a} - {b} names an unknown node")
        adj[a].add(b)
        adj[b].add(a)
    out: dict[str, tuple[TreeEpoch, str | None]] = {}
    for start in sorted(adj):
        if start in out:
            continue
        epoch = TreeEpoch(START_TERM, start)
        out[start] = (epoch, None)
        frontier = [start]
        while frontier:
            nxt = []
            for u in frontier:
                for v in sorted(adj[u]):
                    if v not in out:
                        out[v] = (epoch, u)
                        nxt.append(v)
            frontier = nxt
    return out


def tree_components(links: Iterable[tuple[str, str]], nodes: Iterable[str]) -> list[set[str]]:
    """Connected components of the graph of ``links`` over ``nodes`` (sorted by smallest name)."""
    adj: dict[str, set[str]] = {n: set() for n in nodes}
    for a, b in links:
        adj[a].add(b)
        adj[b].add(a)
    seen: set[str] = set()
    comps = []
    for n in sorted(adj):
        if n in seen:
            continue
        comp, stack = {n}, [n]
        while stack:
            for v in adj[stack.pop()]:
                if v not in comp:
                    comp.add(v)
                    stack.append(v)
        seen |= comp
        comps.append(comp)
    return comps


def forest_settled(states: Mapping[str, NodeTreeState], links: Iterable[tuple[str, str]]) -> tuple[bool, str]:
    """Whether the rule has settled on ``links`` (the links that exist), and if not, why.

    Settled: in every connected component every node is in the same epoch, whose root is
    in the component and has no parent; every other node's parent is a neighbour in the
    component that lists it as a tree link; the agreed tree links are exactly those
    parent links (so they form a spanning tree of the component).
    """
    links = [tuple(sorted(l)) for l in links]
    for comp in tree_components(links, states):
        epochs = {states[n].epoch for n in comp}
        if len(epochs) != 1:
            return False, f"component {sorted(comp)} spans {len(epochs)} epochs"
        (epoch,) = epochs
        if epoch.root not in comp or states[epoch.root].parent is not None:
            return False, f"component {sorted(comp)}: the root {epoch.root} of {epoch} is not in it"
        for n in comp:
            s = states[n]
            if n == epoch.root:
                continue
            p = s.parent
            if p is None or p not in comp or tuple(sorted((n, p))) not in links:
                return False, f"{n}: parent {p!r} is not a neighbour in its component"
            if n not in states[p].tree_links or p not in s.tree_links:
                return False, f"{n} - {p}: the two ends do not agree on the tree link yet"
            for j in s.tree_links:
                if j != p and states[j].parent != n:
                    return False, f"{n} lists {j} as a child, but {j}'s parent is {states[j].parent!r}"
    return True, ""
