"""Building a scenario's fusion nodes and front ends: the one place, for ``simulate`` and ``run``.

``dfusion simulate`` builds every node in one process (:func:`build_nodes`);
``dfusion run`` builds one node per process (:func:`build_node`). Both build the same
:class:`~dfusion.fusion.FusionNode` (common prior, window, policy) and the same front end
(seeded from the scenario's seed and the node's rank), so that the two runs fuse the
same measurements the same way.
"""
from __future__ import annotations

import copy

from dfusion.frontends.base import EIFFrontEnd, FrontEnd
from dfusion.fusion.node import FusionNode
from dfusion.scenario.spec import Scenario

__all__ = ["build_node", "build_nodes", "build_front_end", "build_front_ends"]


def build_node(sc: Scenario, name: str, *, network_key: bytes | None = None, epoch: int | None = None,
               network: str = "", run: str = "") -> FusionNode:
    """The :class:`FusionNode` of scenario node ``name``.

    Its neighbours are its tree neighbours, its prior the scenario's common prior at
    time 0, its policy a copy of the node's (a policy keeps state, so every node built
    gets its own), its guard the consistency test of ``[protection]`` (channel fusion only,
    :mod:`dfusion.fusion.guard`). ``epoch`` identifies the incarnation (the wall clock in nanoseconds
    when ``None``; a node process takes :func:`dfusion.run.measurements.claim_epoch`, strictly
    newer than its previous incarnation's). ``network`` and ``run`` name the
    network and the run the message key is derived for (``docs/security.md``).
    """
    spec = sc.nodes[name]
    return FusionNode(
        name,
        sc.neighbors(name),
        sc.target.motion,
        window=sc.window,
        horizon=sc.horizon,
        prior=(0.0, sc.target.initial_mean, sc.target.initial_cov),
        fusion=sc.fusion,
        policy=copy.deepcopy(spec.policy),
        network_key=network_key,
        network=network,
        run=run,
        epoch=epoch,
        guard=sc.protection.node_guard() if sc.fusion == "channel" else None,
    )


def build_nodes(sc: Scenario, *, network_key: bytes | None = None) -> dict[str, FusionNode]:
    """Every node of the scenario, with epochs 1, 2, ... in name order (deterministic runs)."""
    return {name: build_node(sc, name, network_key=network_key, epoch=i + 1)
            for i, name in enumerate(sorted(sc.nodes))}


def build_front_end(sc: Scenario, name: str) -> FrontEnd | None:
    """The front end of node ``name`` (None without a sensor), seeded from the scenario's
    seed and the node's rank, so that ``simulate`` and ``run`` build the same one."""
    spec = sc.nodes[name]
    if spec.sensor is None:
        return None
    kind = sc.kinds.sensors.get(spec.sensor_kind) if sc.kinds is not None else None
    seed = sc.seed * 1000 + sorted(sc.nodes).index(name)
    if kind is not None and kind.front_end is not None:
        return kind.front_end(spec, sc, seed)
    return EIFFrontEnd(spec.sensor)


def build_front_ends(sc: Scenario) -> dict[str, FrontEnd]:
    """The front end of every node with a sensor."""
    return {name: fe for name in sorted(sc.nodes) if (fe := build_front_end(sc, name)) is not None}
