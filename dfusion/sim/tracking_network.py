r"""A network of multi-target fusion nodes on the plaza, in one process.

:func:`run_tracking_network` drives one :class:`~dfusion.fusion.tracking_node.TrackingNode`
per camera of a :class:`~dfusion.sim.plaza.PlazaWorld`: node ``i`` takes only camera ``i``'s
scan of every frame, and every frame every node sends each neighbour its bundle
(:meth:`TrackingNode.outgoing`), delivered ``delay`` seconds later. Frame ``k`` at time ``t``:

1. the bundles that arrive by ``t`` are received (in the order they were sent);
2. each node processes its camera's scan (:meth:`TrackingNode.process`);
3. each node sends; with ``delay = 0`` the bundles are received at once, after every node
   has sent (so information crosses one link per frame);
4. every node's tracks are recorded (:class:`~dfusion.tracking.history.TrackHistory`, one
   record per node and frame, at ``t``).

Links are lossless and keep their order (a bundle is received ``delay`` after it was sent);
for drops, duplicates and reordering see the property tests of ``TrackingNode``
(``tests/fusion/test_tracking_node.py``). The CPU time (``time.process_time``) of each node's
``receive``, ``process`` and ``outgoing`` is measured per frame.
"""
from __future__ import annotations

import heapq
import itertools
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dfusion.errors import ValidationError
from dfusion.fusion.tracking_node import TrackingNode
from dfusion.linalg import Array
from dfusion.sim.plaza import PlazaWorld
from dfusion.tracking.history import TrackHistory

__all__ = ["TrackingNetworkRun", "run_tracking_network"]


@dataclass
class TrackingNetworkRun:
    """What :func:`run_tracking_network` measured."""

    history: TrackHistory       # every node's tracks after every frame
    node_cpu: Array             # (frames, nodes): CPU seconds of each node per frame
    bytes_sent: int             # by all nodes
    merges_decided: int         # by all nodes
    deletions_decided: int      # by all nodes

    @property
    def network_cpu(self) -> Array:
        """(frames,): CPU seconds of the whole network per frame."""
        return self.node_cpu.sum(axis=1)


def run_tracking_network(world: PlazaWorld, nodes: Sequence[TrackingNode], delay: float = 0.0) -> TrackingNetworkRun:
    """Run ``nodes`` (node ``i`` fed camera ``i`` of ``world``) over every frame (module docstring)."""
    nodes = list(nodes)
    if len(nodes) != len(world.config.cameras):
        raise ValidationError(f"one node per camera: {len(world.config.cameras)} cameras, {len(nodes)} nodes")
    if not (isinstance(delay, (int, float)) and math.isfinite(delay) and delay >= 0):
        raise ValidationError(f"delay must be a finite number of seconds >= 0, got {delay!r}")
    index = {node.name: i for i, node in enumerate(nodes)}
    if len(index) != len(nodes):
        raise ValidationError("node names must be unique")
    for node in nodes:
        strangers = sorted(set(node.links) - set(index))
        if strangers:
            raise ValidationError(f"{node.name!r} links to nodes that are not in the network: {strangers}")
    history = TrackHistory()
    node_cpu = np.zeros((len(world.times), len(nodes)))
    in_flight: list = []
    order = itertools.count()

    def deliver(k: int, t: float) -> None:
        while in_flight and in_flight[0][0] <= t + 1e-9:
            _, _, dst, data = heapq.heappop(in_flight)
            t0 = time.process_time()
            nodes[dst].receive(data)
            node_cpu[k, dst] += time.process_time() - t0

    for k in range(len(world.times)):
        t = float(world.times[k])
        deliver(k, t)
        for i, scan in enumerate(world.scans(k)):
            t0 = time.process_time()
            nodes[i].process(scan)
            node_cpu[k, i] += time.process_time() - t0
        for i, node in enumerate(nodes):
            t0 = time.process_time()
            out = node.outgoing(t)
            node_cpu[k, i] += time.process_time() - t0
            for dst, data in out:
                heapq.heappush(in_flight, (t + delay, next(order), index[dst], data))
        deliver(k, t)
        for node in nodes:
            history.record(node.name, t, node.estimates())
    return TrackingNetworkRun(history, node_cpu, sum(x.stats.bytes_sent for x in nodes),
                              sum(x.stats.merges_decided for x in nodes), sum(x.stats.deletions_decided for x in nodes))
