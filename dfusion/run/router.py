"""A site's Zenoh router: ``python -m dfusion.run.router --listen EP [--connect EP ...] [TLS]``.

Nodes on several hosts meet through one Zenoh router per site (``docs/processes.md``,
"Deployment on several hosts"): every node process of a site runs in client mode connected to
its site's router, and the routers connect to each other; a router forwards fusion messages,
liveliness tokens and monitor publications between its clients and the other routers. (Peer
mode delivers only over direct links, ``docs/zenoh.md``: without routers every node would
need a link to each of its neighbours, across sites too.)

This is a Zenoh session in ``mode = "router"`` with dfusion's configuration
(:class:`~dfusion.transport.zenoh.ZenohConfig`): scouting off (a router knows only the
endpoints it is given), reconnection every 200-500 ms, a 3 s lease, and with ``--tls-ca``,
``--tls-cert``, ``--tls-key`` mutual TLS on every link (only ``tls/`` endpoints, only holders
of a certificate of the CA connect). ``zenohd`` configured the same way does the same job.

It runs until SIGTERM or SIGINT (exit 0), or until the process ``--parent-pid`` is no longer
its parent. A listen endpoint that cannot be bound is one line and exit status 2.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from dfusion.errors import DfusionError
from dfusion.run.common import add_tls_arguments, parse_zenoh_options, security_from_args

log = logging.getLogger("dfusion.router")

__all__ = ["main"]

#: Seconds between two looks at the parent process.
POLL = 0.2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m dfusion.run.router",
                                description="A site's Zenoh router for dfusion nodes on several hosts.")
    p.add_argument("--listen", action="append", required=True, metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tls/192.168.1.10:7447 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another site's router to connect to (repeatable; retried until it answers)")
    p.add_argument("--zenoh-option", action="append", default=[], metavar="PATH=JSON",
                   help="extra Zenoh configuration, e.g. transport/link/tx/lease=2000 (repeatable)")
    p.add_argument("--parent-pid", type=int, default=None, help="stop when this process is no longer the parent")
    add_tls_arguments(p, directory=True)
    p.add_argument("-v", "--verbose", action="count", default=0)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=[logging.INFO, logging.DEBUG][min(args.verbose, 1)], stream=sys.stderr, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    import zenoh

    from dfusion.transport.zenoh import ZenohConfig, close_session, open_session

    try:
        tls = security_from_args(args).tls_files("router")
        cfg = ZenohConfig(mode="router", listen=tuple(args.listen), connect=tuple(args.connect),
                          extra=parse_zenoh_options(args.zenoh_option), tls=tls)
        session = open_session(cfg)
    except (DfusionError, OSError, zenoh.ZError) as exc:
        log.error("cannot open the router (listen %s): %s", args.listen, exc)
        return 2
    log.info("router %s listening on %s, connecting to %s%s (pid %d)", session.zid(), ", ".join(args.listen),
             ", ".join(args.connect) or "nothing", ", mutual TLS" if cfg.tls else "", os.getpid())
    try:
        while not stop.wait(POLL):
            if args.parent_pid is not None and os.getppid() != args.parent_pid:
                log.info("parent process %d is gone: stopping", args.parent_pid)
                break
    finally:
        close_session(session)
    return 0


if __name__ == "__main__":
    sys.exit(main())
