"""Decentralized fusion: channel filters, fusion nodes and output policies."""
from .channel import ChannelFilter
from .node import FusionNode, NodeStats
from .policy import InformationFusionPolicy, Policy, SourceEstimate

__all__ = ["ChannelFilter", "FusionNode", "NodeStats", "InformationFusionPolicy", "Policy", "SourceEstimate"]
