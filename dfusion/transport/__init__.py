"""Message transports between fusion nodes: the interface, a simulated network, Zenoh.

* :mod:`dfusion.transport.base` -- :class:`Transport` and its data types;
* :mod:`dfusion.transport.simulated` -- :class:`SimulatedNetwork`, links with delays,
  drops, duplicates, reordering and outages, deterministic by seed (:class:`LinkSpec`);
* :mod:`dfusion.transport.zenoh` -- :class:`ZenohTransport` between processes and hosts.

:class:`ZenohTransport`, :class:`ZenohConfig` and :class:`TlsFiles` are imported on first use, so that code
which only simulates never loads Zenoh.
"""
from dfusion.transport.base import (
    Delivery,
    LinkKey,
    StatsReport,
    Transport,
    TransportStats,
)
from dfusion.transport.simulated import LinkSpec, SimulatedNetwork, link_generator

__all__ = ["Transport", "Delivery", "TransportStats", "StatsReport", "LinkKey", "LinkSpec", "SimulatedNetwork",
           "link_generator", "ZenohTransport", "ZenohConfig", "TlsFiles"]

_LAZY = {"ZenohTransport", "ZenohConfig", "TlsFiles"}


def __getattr__(name: str):
    if name in _LAZY:
        from dfusion.transport import zenoh as _zenoh

        return getattr(_zenoh, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
