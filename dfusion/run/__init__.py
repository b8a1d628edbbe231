"""Fusion nodes as separate OS processes over Zenoh (``dfusion run``; see ``docs/processes.md``).

* :mod:`dfusion.run.node_process`: one node's real-time loop and command line;
* :mod:`dfusion.run.monitor`: records the nodes' estimates, builds the ``simulate`` result;
* :mod:`dfusion.run.launcher`: starts, follows, restarts and stops the processes;
* :mod:`dfusion.run.supervision`: the launcher's liveliness lock, one incarnation per
  node, the parent-death signal, the restart policy;
* :mod:`dfusion.run.links`: the scenario's links emulated at the senders;
* :mod:`dfusion.run.measurements`: measurement recordings and the restart log;
* :mod:`dfusion.run.certs`: a test CA and certificates for mutual TLS (openssl);
* :mod:`dfusion.run.router`: a site's Zenoh router, for nodes on several hosts;
* :mod:`dfusion.run.common`: network key, security options, monitor messages,
  final-phase schedule.

Names are imported on first use, so that a node process does not load the
launcher's and monitor's dependencies.
"""
__all__ = ["Launcher", "Restart", "RunOptions", "run_processes", "NodeProcess", "Monitor"]

_WHERE = {"Launcher": "launcher", "Restart": "launcher", "RunOptions": "launcher", "run_processes": "launcher",
          "NodeProcess": "node_process", "Monitor": "monitor"}


def __getattr__(name: str):
    if name in _WHERE:
        from importlib import import_module

        return getattr(import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
