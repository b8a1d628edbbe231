"""Where the node processes of a ``dfusion run`` listen: bound first, advertised after.

A port chosen in advance and written on a command line can be taken by anyone on the
machine before the node binds it (a command line is readable in ``/proc`` for seconds
before the node's imports are done), and a restarted node that reuses its old port
fails as long as someone holds it. So no port is chosen in advance:

* every session of a run listens on ``SCHEME/127.0.0.1:0``: the kernel gives it a free
  port as it binds, and the session reads back the endpoint it got
  (:func:`bound_endpoints`, from Zenoh's admin space of the session itself);
* a node process (a *host*: one session for its nodes) opening its session takes the
  run's registry lock (``RUN_DIR/endpoints.lock``), reads the endpoints of its peers
  registered so far (``RUN_DIR/endpoints/NODE.json``), opens its session connected to
  them and to the launcher's monitor, writes its own nodes' entries and releases the
  lock (:class:`EndpointRegistry`). A Zenoh link is one TCP connection that either end
  may open, so every pair of peers is linked: whichever of the two opened its session
  second connected to the first (the lock orders them). A restarted node gets a fresh
  port and connects to its peers' current endpoints itself; its peers' attempts at its
  old endpoint fail and are retried in the background, harmless even if someone else
  holds that port now;
* the launcher's monitor binds its own port the same way before the endpoint is written
  anywhere (``RUN_DIR/run.json``, key ``monitor_endpoint``).

An entry is one JSON object: ``{"node", "host", "endpoint", "pid", "written"}`` (UNIX
time), replaced atomically (write, then rename). A tool that wants to reach a node (a
test, a chaos driver) reads :meth:`EndpointRegistry.endpoint`; the launcher reports
every endpoint each host used in ``run.endpoints`` of the run's JSON.
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from dfusion.errors import DfusionError
from dfusion.run.supervision import FileLock, lock_holder

log = logging.getLogger(__name__)

#: Registry of a run directory: one file per node.
ENDPOINTS_DIR = "endpoints"
#: Lock held while a session is opened and registered (orders the peers' connections).
ENDPOINTS_LOCK = "endpoints.lock"
#: Seconds a process waits for the registry lock (another holds it only while opening a session).
LOCK_TIMEOUT = 10.0


def bound_endpoints(session: Any) -> list[str]:
    """The endpoints ``session`` listens on, with the ports the kernel gave it.

    Read from the session's own admin space (``@/<zid>/<whatami>``, key ``locators``):
    the session must have been opened with ``adminspace/enabled`` (``ZenohConfig.report_endpoints``).
    Raises :class:`DfusionError` when the admin space does not answer.
    """
    zid = str(session.info.zid())
    for reply in session.get(f"@/{zid}/*"):
        ok = getattr(reply, "ok", None)
        if ok is None:
            continue
        try:
            info = json.loads(ok.payload.to_string())
        except ValueError:
            continue
        if isinstance(info, dict) and isinstance(info.get("locators"), list):
            return [str(x) for x in info["locators"]]
    raise DfusionError("the Zenoh session did not report the endpoints it listens on "
                       "(its admin space is off or did not answer)")


class EndpointRegistry:
    """The endpoints of the node processes of one run directory (see the module docstring)."""

    def __init__(self, run_dir: str | Path) -> None:
        self.dir = Path(run_dir) / ENDPOINTS_DIR
        self.lock_path = Path(run_dir) / ENDPOINTS_LOCK

    def lock(self, timeout: float = LOCK_TIMEOUT) -> FileLock:
        """Take the registry lock (a context manager, :meth:`FileLock.release`).

        A holder opens a session in milliseconds; if the lock stays taken for ``timeout`` seconds
        (its holder frozen, e.g. SIGSTOPped while opening its session), the caller goes on without
        it, with a warning: only a peer registering at that very moment could then miss the link.
        """
        lock = FileLock(self.lock_path)
        if not lock.acquire(timeout=timeout):
            log.warning("the endpoint registry %s stayed locked for %.0f s (pid %s): registering without the lock",
                        self.lock_path, timeout, lock_holder(self.lock_path))
        return lock

    def entry(self, node: str) -> dict[str, Any] | None:
        """Node ``node``'s entry, or None (not registered yet, or unreadable)."""
        try:
            d = json.loads((self.dir / f"{node}.json").read_text())
        except (OSError, ValueError):
            return None
        return d if isinstance(d, dict) and isinstance(d.get("endpoint"), str) else None

    def endpoint(self, node: str) -> str | None:
        """Where node ``node``'s process listens now (None: not registered yet)."""
        e = self.entry(node)
        return None if e is None else e["endpoint"]

    def endpoints(self, nodes) -> dict[str, str]:
        """``{node: endpoint}`` of the registered nodes among ``nodes``."""
        out = {}
        for n in nodes:
            ep = self.endpoint(n)
            if ep is not None:
                out[n] = ep
        return out

    def register(self, host: str, nodes, endpoint: str) -> None:
        """Write the entries of ``host``'s ``nodes`` (atomically each)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        for n in nodes:
            tmp = self.dir / f".{n}.json.tmp"
            tmp.write_text(json.dumps({"node": n, "host": host, "endpoint": endpoint, "pid": os.getpid(),
                                       "written": time.time()}))
            tmp.replace(self.dir / f"{n}.json")
