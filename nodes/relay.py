#!/usr/bin/env python
"""The relay node program: `python nodes/relay.py NODE_FILE [--result OUT] [-v]`.

Runs the relay node a node file names (`docs/ros.md`, "Live use"): the scenario's node, built and
driven as in `dfusion run`, with ROS 2 topics in and the fused estimate, its health and liveliness
tokens out over Zenoh (:mod:`dfusion.run.live`). The node file's `kind` must be `relay`.
"""
import sys

from dfusion.run.live import main

if __name__ == "__main__":
    sys.exit(main(kind="relay"))
