"""Decentralized fusion: channel filters, fusion nodes (one target; many targets: TrackingNode), the consistency test of neighbours' information and the tree rule for links that change."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.fusion.channel import ChannelFilter, Entry, Plan, find_keys, nonzero_blocks, time_key, time_keys
    from dfusion.fusion.guard import GuardConfig, LinkRecord, NeighbourGuard, information_statistic, split_blocks
    from dfusion.fusion.node import FusionNode
    from dfusion.fusion.stats import NodeStats
    from dfusion.fusion.tracking_node import TrackingNode, TrackingStats, TrackPrior
    from dfusion.fusion.tree import SpanningTree, TreeChange, TreeEpoch

__all__ = [
    "time_key",
    "Entry",
    "Plan",
    "time_keys",
    "nonzero_blocks",
    "find_keys",
    "ChannelFilter",
    "NodeStats",
    "FusionNode",
    "TrackingNode",
    "TrackingStats",
    "TrackPrior",
    "SpanningTree",
    "TreeEpoch",
    "TreeChange",
    "GuardConfig",
    "LinkRecord",
    "NeighbourGuard",
    "information_statistic",
    "split_blocks",
]

_WHERE = {
    "ChannelFilter": ("dfusion.fusion.channel", 'ChannelFilter'),
    "Entry": ("dfusion.fusion.channel", 'Entry'),
    "Plan": ("dfusion.fusion.channel", 'Plan'),
    "find_keys": ("dfusion.fusion.channel", 'find_keys'),
    "nonzero_blocks": ("dfusion.fusion.channel", 'nonzero_blocks'),
    "time_key": ("dfusion.fusion.channel", 'time_key'),
    "time_keys": ("dfusion.fusion.channel", 'time_keys'),
    "FusionNode": ("dfusion.fusion.node", 'FusionNode'),
    "TrackingNode": ("dfusion.fusion.tracking_node", 'TrackingNode'),
    "TrackingStats": ("dfusion.fusion.tracking_node", 'TrackingStats'),
    "TrackPrior": ("dfusion.fusion.tracking_node", 'TrackPrior'),
    "NodeStats": ("dfusion.fusion.stats", 'NodeStats'),
    "SpanningTree": ("dfusion.fusion.tree", 'SpanningTree'),
    "TreeEpoch": ("dfusion.fusion.tree", 'TreeEpoch'),
    "TreeChange": ("dfusion.fusion.tree", 'TreeChange'),
    "GuardConfig": ("dfusion.fusion.guard", 'GuardConfig'),
    "LinkRecord": ("dfusion.fusion.guard", 'LinkRecord'),
    "NeighbourGuard": ("dfusion.fusion.guard", 'NeighbourGuard'),
    "information_statistic": ("dfusion.fusion.guard", 'information_statistic'),
    "split_blocks": ("dfusion.fusion.guard", 'split_blocks'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
