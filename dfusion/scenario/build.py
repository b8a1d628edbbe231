"""Building a scenario's fusion nodes and front ends: the one place, for ``simulate`` and ``run``.

``dfusion simulate`` builds every node in one process (:func:`build_nodes`);
``dfusion run`` builds one node per process (:func:`build_node`). Both build the same
:class:`~dfusion.fusion.FusionNode` (common prior, window, policy) and the same front end
(seeded from the scenario's seed and the node's rank), so that the two runs fuse the
same measurements the same way.

With links that change at run time (``Scenario.dynamic``: ``[[events]]``, radio ranges) the
nodes carry the tree rule (:class:`~dfusion.fusion.tree.SpanningTree`): those present at the
start begin on the tree :func:`~dfusion.fusion.tree.initial_parents` picks among the links
that exist then, a node that joins later begins alone (:func:`build_joining_node`).
"""
from __future__ import annotations

import copy
from typing import TYPE_CHECKING

from collections.abc import Collection

from dfusion.errors import ScenarioError
from dfusion.frontends.base import EIFFrontEnd, FrontEnd
from dfusion.fusion.node import FusionNode
from dfusion.fusion.tree import SpanningTree, TreeEpoch, initial_parents
from dfusion.scenario.spec import Scenario, TrackingSpec

if TYPE_CHECKING:   # the multi-target builders import the tracker on first use: a single-target node program
    from dfusion.fusion.tracking_node import TrackingNode   # loads no scipy (tests/run/test_node_process.py)

__all__ = ["build_node", "build_nodes", "build_joining_node", "build_front_end", "build_front_ends",
           "build_tracking_node", "build_tracking_nodes", "tracker_components"]


def build_node(sc: Scenario, name: str, *, network_key: bytes | None = None, epoch: int | None = None,
               network: str = "", run: str = "", links: Collection[str] | None = None,
               tree_start: dict[str, tuple[TreeEpoch, str | None]] | None = None) -> FusionNode:
    """The :class:`FusionNode` of scenario node ``name``.

    Its neighbours are its tree neighbours, its prior the scenario's common prior at
    time 0, its policy a copy of the node's (a policy keeps state, so every node built
    gets its own), its guard the consistency test of ``[protection]`` (channel fusion only,
    :mod:`dfusion.fusion.guard`). ``epoch`` identifies the incarnation (the wall clock in nanoseconds
    when ``None``; a node process takes :func:`dfusion.run.measurements.claim_epoch`, strictly
    newer than its previous incarnation's). ``network`` and ``run`` name the
    network and the run the message key is derived for (``docs/security.md``).

    Links that change (``sc.dynamic``): ``links`` are the node's links now and
    ``tree_start`` the tree it starts on (:func:`~dfusion.fusion.tree.initial_parents`; ``None``:
    it joins, alone in its own epoch).
    """
    spec = sc.nodes[name]
    tree = None
    if sc.dynamic:
        if links is None:
            raise ScenarioError(f"{sc.path}: links change at run time ([[events]], radio ranges): build_node "
                                "needs the node's links now (links=...)")
        links = sorted(links)
        if tree_start is None:
            tree = SpanningTree(name, links)
        else:
            epoch0, parent = tree_start[name]
            tree = SpanningTree(name, links, epoch=epoch0, parent=parent, known={j: tree_start[j] for j in links})
    return FusionNode(
        name,
        sc.neighbors(name) if tree is None else links,
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
        tree=tree,
        guard=sc.protection.node_guard() if sc.fusion == "channel" else None,
    )


def build_nodes(sc: Scenario, *, network_key: bytes | None = None,
                links: Collection[tuple[str, str]] | None = None) -> dict[str, FusionNode]:
    """Every node of the scenario, with epochs 1, 2, ... in name order (deterministic runs).

    Links that change: the nodes present at the start, on ``links`` (the links that exist
    then), starting on the tree :func:`~dfusion.fusion.tree.initial_parents` picks.
    """
    if not sc.dynamic:
        return {name: build_node(sc, name, network_key=network_key, epoch=i + 1)
                for i, name in enumerate(sorted(sc.nodes))}
    present = [n for n in sorted(sc.nodes) if sc.nodes[n].is_present(0.0)]
    links = list(links or ())
    start = initial_parents(present, links)
    return {name: build_node(sc, name, network_key=network_key, epoch=sorted(sc.nodes).index(name) + 1,
                             links=[b if a == name else a for a, b in links if name in (a, b)], tree_start=start)
            for name in present}


def build_joining_node(sc: Scenario, name: str, *, network_key: bytes | None = None,
                       epoch: int | None = None) -> FusionNode:
    """The node ``name`` of a scenario whose links change, joining the running network: no links
    yet, alone in the lowest epoch, the common prior at time 0 (it predicts to the current time
    and gets what its neighbours' windows still hold)."""
    return build_node(sc, name, network_key=network_key,
                      epoch=epoch if epoch is not None else sorted(sc.nodes).index(name) + 1, links=())


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


def tracker_components(spec: TrackingSpec, motion) -> dict:
    """The tracker of ``[tracking]`` as keyword arguments of :class:`~dfusion.fusion.tracking_node.TrackingNode` (fresh objects:
    the initiator and the merger keep state, so every node gets its own): ``associator``,
    ``hypothesiser``, ``initiator``, ``deleter``, ``merger``, ``prior``."""
    from dfusion.fusion.tracking_node import TrackPrior
    from dfusion.tracking.association import GNN, JPDA
    from dfusion.tracking.deletion import AnyDeleter, Deleter, MissDeleter, RegionDeleter, StaleDeleter
    from dfusion.tracking.gating import GaussianHypothesiser
    from dfusion.tracking.initiation import MofNInitiator
    from dfusion.tracking.track_to_track import TrackToTrackAssociator

    deleters: list[Deleter] = [StaleDeleter(spec.max_age)]
    if spec.max_misses:
        deleters.append(MissDeleter(spec.max_misses))
    if spec.region is not None:
        deleters.append(RegionDeleter(spec.inside, spec.region_grace))
    m, n = spec.confirm
    merger = (TrackToTrackAssociator(spec.merge_gate, spec.merge_confirm, spec.merge_distance,
                                     spec.merge_distinct_for) if spec.merge else False)
    return dict(associator=JPDA() if spec.associator == "jpda" else GNN(), hypothesiser=GaussianHypothesiser(spec.gate),
                initiator=MofNInitiator(motion, m=m, n=n, gate=spec.gate, velocity_std=spec.velocity_std,
                                        max_speed=spec.max_speed, max_seed_age=spec.max_seed_age),
                deleter=AnyDeleter(*deleters), merger=merger,
                prior=TrackPrior(spec.prior_position_std, spec.prior_velocity_std))


def build_tracking_node(sc: Scenario, name: str, *, network_key: bytes | None = None, epoch: int | None = None,
                        network: str = "", run: str = "") -> TrackingNode:
    """The :class:`~dfusion.fusion.tracking_node.TrackingNode` of node ``name`` of a multi-target scenario: its tree
    neighbours, the scenario's window and horizon, the tracker of ``[tracking]``
    (:func:`tracker_components`)."""
    from dfusion.fusion.tracking_node import TrackingNode

    if sc.tracking is None:
        raise ScenarioError(f"{sc.path}: not a multi-target scenario ([[targets]], [tracking])")
    motion = sc.target.motion
    return TrackingNode(name, sc.neighbors(name), motion, window=sc.window, horizon=sc.horizon,
                        network_key=network_key, network=network, run=run, epoch=epoch,
                        **tracker_components(sc.tracking, motion))


def build_tracking_nodes(sc: Scenario, *, network_key: bytes | None = None) -> dict[str, TrackingNode]:
    """Every node of a multi-target scenario, with epochs 1, 2, ... in name order (deterministic runs)."""
    return {name: build_tracking_node(sc, name, network_key=network_key, epoch=i + 1)
            for i, name in enumerate(sorted(sc.nodes))}
