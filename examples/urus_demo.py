#!/usr/bin/env python
"""URUS person tracking: two cameras and a wireless sensor network, with a link outage.

Usage::

    python examples/urus_demo.py [--in-process] [--speed X] [--duration S] [--seed N]
                                 [--node NAME] [--json OUT] [--plot OUT.png] [--out DIR]

Runs ``topologies/urus.scenario.toml`` (URUS paper sec. 8, Figure 33; see
``docs/urus-demo.md``): a person walks across a 30 m x 20 m square through the
views of two fixed cameras, carrying a radio tag tracked by a 12-receiver WSN;
one link is down for 10 s. It prints the summary table (per node: RMSE, ANEES,
gap to the centralized EKF, traffic) and a few demo figures, and writes

* ``DIR/urus_figure33.png`` (or ``--plot``): the Figure-33-style plot of one
  camera node (``--node``, default ``cam_left``) against the centralized EKF;
* ``DIR/urus_nodes.png``: every node's error with 3-sigma bands
  (:func:`dfusion.viz.plot_result`);
* ``DIR/urus_topdown.png``: the square seen from above: the person's path, every
  node's estimate with 3-sigma ellipses, the cameras' footprints, the receivers, the
  tree with its outage (:func:`dfusion.viz.plot_topdown`);
* ``DIR/urus.mcap``: the run as an MCAP recording to open in Foxglove (``docs/ros.md``);
* ``DIR/urus_series.csv``: the per-step series (truth, estimates, variances, NEES, gaps);
* ``DIR/urus.json`` (or ``--json``): the metrics and the per-step series.

By default every node runs as its own OS process over Zenoh (``dfusion run``,
at ``--speed`` times real time, link outages emulated) when this dfusion has
the ``run`` command; with ``--in-process``, or when ``dfusion run`` is not
available (a warning is logged), the scenario runs in this process with
:func:`dfusion.sim.runner.run_scenario`.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENARIO = ROOT / "topologies" / "urus.scenario.toml"

log = logging.getLogger("urus_demo")


def have_run_command() -> bool:
    """Whether this dfusion has the multi-process ``dfusion run`` command."""
    try:
        from dfusion.cli import build_parser

        parser = build_parser()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        if "run" not in sub.choices:
            return False
        from dfusion.run.launcher import run_processes, RunOptions
    except (ImportError, StopIteration, AttributeError):
        return False
    return True


def run_in_process(args):
    from dfusion.sim import run_scenario
    from dfusion.scenario import load_scenario

    sc = load_scenario(args.scenario, seed=args.seed, duration=args.duration)
    return run_scenario(sc)


def run_processes_mode(args):
    from dfusion.run.launcher import run_processes, RunOptions

    opts = RunOptions(scenario=str(args.scenario), seed=args.seed, duration=args.duration, speed=args.speed,
                      emulate_links=True, progress=sys.stderr.isatty())
    return run_processes(opts)


def demo_figures(result, node: str) -> list[str]:
    """Lines about what the demo shows: views, outage, agreement between nodes."""
    sc = result.scenario
    t = result.times
    lines = []
    for name, spec in sorted(sc.nodes.items()):
        sensor = spec.sensor
        own = [m for m in result.world.measurements if m.node == name]
        clutter = sum(getattr(m, "clutter", False) for m in own)
        if sensor is not None and hasattr(sensor, "in_view"):
            seen = np.array([sensor.in_view(x) for x in result.truth])
            lines.append(f"{name}: target in view {100 * seen.mean():.0f}% of the time, "
                         f"{len(own) - clutter} detections, {clutter} false detections")
        elif spec.sensor_kind != "none":
            lines.append(f"{name}: {len(own)} {spec.sensor_kind} measurements")
    gaps = {nm: np.abs(result.node_mean[nm] - result.central_mean).max(axis=1) for nm in result.node_mean}
    for a, b, t0, t1 in sc.outages():
        during = (t >= t0) & (t <= t1)
        after = (t > t1 + 2.0) & (t <= t1 + 5.0)
        for nm in (a, b):
            if nm in gaps and during.any():
                msg = f"outage {a} - {b} [{t0:g}, {t1:g}] s: {nm} gap up to {gaps[nm][during].max():.3f}"
                if after.any():
                    msg += f", {gaps[nm][after].max():.3f} 2-5 s after"
                lines.append(msg)
    fg = [v.get("final_gap_position", v["final_gap"]) for v in result.metrics["nodes"].values()]
    lines.append(f"final position gaps to the centralized EKF: {min(fg):.3g} .. {max(fg):.3g} m (the same at every node: "
                 "the nodes agree with each other; see docs/urus-demo.md for what separates them from the EKF)")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--in-process", action="store_true", help="run every node in this process (dfusion simulate)")
    p.add_argument("--speed", type=float, default=5.0, help="scenario seconds per wall-clock second (processes; default 5)")
    p.add_argument("--duration", type=float, default=None, help="override the scenario's duration (s)")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    p.add_argument("--node", default="cam_left", help="node of the Figure-33 plot (default cam_left)")
    p.add_argument("--scenario", type=Path, default=SCENARIO, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=Path("out/urus"), help="output directory (default out/urus)")
    p.add_argument("--json", type=Path, default=None, help="metrics JSON (default DIR/urus.json)")
    p.add_argument("--plot", type=Path, default=None, help="Figure-33 PNG (default DIR/urus_figure33.png)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")

    mode = "in-process"
    if not args.in_process:
        if have_run_command():
            mode = "processes"
        else:
            log.warning("dfusion run is not available: running in-process (dfusion.sim.runner.run_scenario)")
    t0 = time.perf_counter()
    result = run_processes_mode(args) if mode == "processes" else run_in_process(args)
    wall = time.perf_counter() - t0
    if result is None:
        print("urus_demo: the run was stopped", file=sys.stderr)
        return 1

    print(result.table())
    print()
    for line in demo_figures(result, args.node):
        print(line)
    print(f"mode: {mode}" + (f" (speed x{args.speed:g})" if mode == "processes" else "") + f", wall time {wall:.1f} s")

    from dfusion.sim.runner import series_of, write_series_csv
    from dfusion.viz import plot_figure33, plot_result, plot_topdown, record_mcap

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    json_path = args.json or out / "urus.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    metrics = dict(result.metrics, demo={"mode": mode, "wall_time_s": wall}, series=series_of(result))
    json_path.write_text(json.dumps(metrics, indent=2, sort_keys=True, default=float))
    fig = plot_figure33(result, args.node, args.plot or out / "urus_figure33.png")
    nodes_png = plot_result(result, out / "urus_nodes.png")
    top_png = plot_topdown(result, out / "urus_topdown.png")
    mcap_path = record_mcap(result, out / "urus.mcap")
    csv_path = out / "urus_series.csv"
    write_series_csv(result, csv_path)
    print(f"wrote {json_path}, {fig}, {nodes_png}, {top_png}, {csv_path}, {mcap_path} (open it in Foxglove)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
