"""Message transports between fusion nodes: the abstract interface and its data types.

:class:`ZenohTransport` and :class:`ZenohConfig` (``dfusion.transport.zenoh``) are
imported on first use, so that code which only simulates never loads Zenoh.
"""
from .base import Delivery, LinkKey, StatsReport, Transport, TransportStats

__all__ = ["Transport", "Delivery", "TransportStats", "StatsReport", "LinkKey", "ZenohTransport", "ZenohConfig"]

_LAZY = {"ZenohTransport", "ZenohConfig"}


def __getattr__(name: str):
    if name in _LAZY:
        from . import zenoh as _zenoh

        return getattr(_zenoh, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
