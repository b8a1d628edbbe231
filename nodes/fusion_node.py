#!/usr/bin/env python3
"""One dfusion fusion node as its own process, over Zenoh.

    python nodes/fusion_node.py --scenario topologies/chain3.scenario.toml --node a \
        --listen tcp/127.0.0.1:7501 --connect tcp/127.0.0.1:7502 --start-time $(date +%s)

A thin wrapper around ``python -m dfusion.run.node_process`` (same options;
``--help`` lists them). ``dfusion run SCENARIO`` starts one per node for you;
see docs/processes.md.
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dfusion.run.node_process import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
