"""Scenarios generated from a random tree: any number of position-sensor nodes, for runs at scale.

:func:`random_tree_scenario` returns the mapping of a scenario file (what
:func:`dfusion.scenario.load_scenario` accepts): the linear scenario of the shipped chain
(constant velocity target, position sensors) on the random recursive tree of
:func:`dfusion.topology.random_tree`, with a window long enough for exact fusion on that
tree (:func:`dfusion.topology.minimum_window`). :func:`scenario_toml` writes it as TOML.

``python -m dfusion.scenario.generate N [--seed S] [-o FILE] ...`` writes one::

    python -m dfusion.scenario.generate 128 --seed 1 -o tree128.scenario.toml
    dfusion run tree128.scenario.toml --nodes-per-process 8
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, Mapping

from dfusion.errors import ValidationError
from dfusion.topology import Tree, minimum_window, random_tree

__all__ = ["random_tree_scenario", "scenario_toml"]


def random_tree_scenario(
    n: int,
    *,
    seed: int = 1,
    duration: float = 60.0,
    dt: float = 0.1,
    rate: float = 10.0,
    send_period: float = 0.5,
    latency: float = 0.02,
    drop: float = 0.0,
    window: int | None = None,
) -> dict[str, Any]:
    """A linear scenario on a random tree of ``n`` nodes ``n0 .. n{n-1}``.

    Every node has a position sensor measuring at ``rate`` Hz on the ``dt`` grid (phase 0;
    noise standard deviations 0.5-1.0 m in turn) and sends every ``send_period`` seconds;
    every link has ``latency`` seconds and drops a fraction ``drop`` of the messages. The
    window (``None``: the shortest exact one) is ``ceil(W / dt) + 2`` states with ``W =
    diameter (latency + send_period)`` (:func:`dfusion.topology.minimum_window`), so that
    every node can end on the centralized estimate. ``seed`` draws the tree and the world.
    """
    if not (dt > 0 and duration >= dt and rate >= 0 and send_period > 0 and latency >= 0 and 0 <= drop < 1):
        raise ValidationError(f"invalid settings: dt={dt}, duration={duration}, rate={rate}, "
                              f"send_period={send_period}, latency={latency}, drop={drop}")
    links = random_tree(n, seed)
    tree = Tree()
    for k in range(n):
        tree.add_node(f"n{k}")
    for a, b in links:
        tree.add_edge(a, b)
    if window is None:
        seconds = minimum_window(tree, max_latency=latency, send_period=send_period)
        window = max(10, math.ceil(seconds / dt - 1e-9) + 2)
    stds = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
    return {
        "duration": float(duration), "dt": float(dt), "seed": int(seed), "window": int(window),
        "target": {"motion": "constant_velocity", "q": 0.05, "initial_mean": [0.0, 0.0, 1.0, 0.0],
                   "initial_cov_diag": [1.0, 1.0, 1.0, 1.0]},
        "nodes": [{"name": f"n{k}", "sensor": "position", "std": stds[k % len(stds)], "rate": float(rate),
                   "send_period": float(send_period)} for k in range(n)],
        "links": [{"between": [a, b], "latency": float(latency), **({"drop": float(drop)} if drop else {})}
                  for a, b in links],
    }


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise ValidationError(f"cannot write {v!r} as a TOML value")


def scenario_toml(scenario: Mapping[str, Any], comment: str = "") -> str:
    """A scenario mapping (plain values, ``[target]``, ``[[nodes]]``, ``[[links]]``) as TOML text."""
    lines = [f"# {line}" for line in comment.splitlines()]
    tables = {k: v for k, v in scenario.items() if isinstance(v, Mapping)}
    arrays = {k: v for k, v in scenario.items() if isinstance(v, list) and v and isinstance(v[0], Mapping)}
    lines += [f"{k} = {_value(v)}" for k, v in scenario.items() if k not in tables and k not in arrays]
    for name, table in tables.items():
        lines += ["", f"[{name}]"] + [f"{k} = {_value(v)}" for k, v in table.items()]
    for name, items in arrays.items():
        for item in items:
            lines += ["", f"[[{name}]]"] + [f"{k} = {_value(v)}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m dfusion.scenario.generate",
                                description="Write a linear scenario on a random tree of N position-sensor nodes.")
    p.add_argument("n", type=int, help="number of nodes")
    p.add_argument("--seed", type=int, default=1, help="draws the tree and the world (default 1)")
    p.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    p.add_argument("--dt", type=float, default=0.1, help="time step of the filters (default 0.1: 10 Hz)")
    p.add_argument("--rate", type=float, default=10.0, help="measurements per second per node (default 10)")
    p.add_argument("--send-period", type=float, default=0.5, help="seconds between messages on a link (default 0.5)")
    p.add_argument("--latency", type=float, default=0.02, help="link latency, seconds (default 0.02)")
    p.add_argument("--drop", type=float, default=0.0, help="fraction of messages each link drops (default 0)")
    p.add_argument("--window", type=int, default=None, help="states kept (default: the shortest exact window)")
    p.add_argument("-o", "--output", default=None, help="file to write (default: standard output)")
    args = p.parse_args(argv)
    sc = random_tree_scenario(args.n, seed=args.seed, duration=args.duration, dt=args.dt, rate=args.rate,
                              send_period=args.send_period, latency=args.latency, drop=args.drop, window=args.window)
    text = scenario_toml(sc, f"A random tree of {args.n} position-sensor nodes (python -m dfusion.scenario.generate "
                             f"{' '.join(argv if argv is not None else sys.argv[1:])})")
    if args.output:
        Path(args.output).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
