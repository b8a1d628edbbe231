#!/usr/bin/env python
"""The camera node program: `python nodes/camera_node.py NODE_FILE [--result OUT] [-v]`.

Runs the camera node a node file names (`docs/ros.md`, "Live use"): the scenario's node, built and
driven as in `dfusion run`, with ROS 2 topics in and the fused estimate, its health and liveliness
tokens out over Zenoh (:mod:`dfusion.run.live`). The node file's `kind` must be `camera`.
"""
import sys

from dfusion.run.live import main

if __name__ == "__main__":
    sys.exit(main(kind="camera"))
