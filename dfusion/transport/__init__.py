"""Message transports between fusion nodes: the abstract interface and its data types."""
from .base import Delivery, LinkKey, StatsReport, Transport, TransportStats

__all__ = ["Transport", "Delivery", "TransportStats", "StatsReport", "LinkKey"]
