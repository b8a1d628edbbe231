"""Injected one-sided liveliness lapses: the node side of ``benchmarks/chaos.py``.

A chaos run (``docs/chaos.md``) needs a fault that no outside action produces on demand: one
end of a link sees it go down and up within a step while the other end sees nothing (a lease
lapse, a one-way glitch). A node process started with ``--chaos-dir DIR`` (``dfusion run
--chaos-dir DIR`` passes it to every node; **off by default**: a normal run has no such
control surface) looks at every step for a request file ``DIR/NAME.lapse`` written by the
driver (:func:`request_lapse`). The file holds one integer ``pick``; the node takes the
neighbour ``linked[pick % len(linked)]`` of, in name order, its children in the tree (the
hard case: the parent makes a fresh channel, the child notices nothing), else its parent (it
then starts a new tree epoch), else any link (a request ``"PICK child"``: children only, and
it waits while the node has none), and calls
``link_down(j)`` then ``link_up(j)`` in the same step, which is exactly what its link rule
(``NodeProcess.sync_links``: scenario AND liveliness) does when it misses one liveliness
token for less than a step. The other end is told nothing. The node claims the file (renamed,
then removed: the driver's acknowledgement) and counts the lapse in its counters (``chaos_lapses``,
``run.nodes.NAME.chaos_lapses`` in the run's JSON). A request that comes while the node has no
link waits for a step with one.

Only the file's owner can write requests: the directory is the driver's, mode 0700.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

#: Suffix of a lapse request file: ``DIR/NAME.lapse``.
LAPSE_SUFFIX = ".lapse"


def lapse_path(chaos_dir: str | Path, node: str) -> Path:
    """The request file of ``node`` in ``chaos_dir``."""
    return Path(chaos_dir) / f"{node}{LAPSE_SUFFIX}"


def request_lapse(chaos_dir: str | Path, node: str, pick: int, *, child_only: bool = False) -> Path:
    """Ask ``node`` for one one-sided lapse of its link ``linked[pick % len(linked)]`` (atomic write);
    ``child_only``: of a child's link only (the request waits while the node has no child)."""
    path = lapse_path(chaos_dir, node)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(f"{int(pick)}{' child' if child_only else ''}\n")
    os.replace(tmp, path)
    return path


class LapseInbox:
    """One node's lapse requests (see the module docstring)."""

    def __init__(self, chaos_dir: str | Path, node: str) -> None:
        self.path = lapse_path(chaos_dir, node)
        self.node = node
        #: lapses applied by this incarnation
        self.applied = 0

    def apply_due(self, fusion_node) -> str | None:
        """Apply the waiting request, if any, to ``fusion_node`` (a :class:`FusionNode` with a tree
        rule); returns the neighbour whose link lapsed, or ``None``.

        The node claims a request by renaming it (``NAME.lapse.taken``): the driver withdraws one by
        renaming it too, so exactly one of them has it."""
        try:
            words = self.path.read_text().split()
        except OSError:   # no request (the common case: one failed open per step)
            return None
        try:
            pick = int(words[0]) if words else 0
        except ValueError:
            pick = 0
        child_only = "child" in words[1:]
        # a child's link if there is one (the parent makes a fresh channel, the child notices nothing:
        # the hard case), else the parent's (the node starts a new tree epoch), else any link
        tree = sorted(fusion_node.tree_links)
        parent = fusion_node.tree.parent if fusion_node.tree is not None else None
        children = [j for j in tree if j != parent]
        linked = children if child_only else children or tree or sorted(fusion_node.neighbors)
        if not linked:
            return None   # wait for a step with such a link
        taken = self.path.with_name(self.path.name + ".taken")
        try:
            os.replace(self.path, taken)
        except OSError:   # withdrawn meanwhile
            return None
        j = linked[pick % len(linked)]
        fusion_node.link_down(j)
        fusion_node.link_up(j)
        self.applied += 1
        taken.unlink(missing_ok=True)
        log.warning("%s: chaos: one-sided lapse of the link to %s (the other end saw nothing)", self.node, j)
        return j
