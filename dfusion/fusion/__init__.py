"""Decentralized fusion: channel filters and fusion nodes."""
from dfusion.fusion.channel import (
    ChannelFilter,
    Entry,
    Plan,
    find_keys,
    nonzero_blocks,
    time_key,
    time_keys,
)
from dfusion.fusion.node import FusionNode, NodeStats

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
]
