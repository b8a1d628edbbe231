"""The ``dfusion`` command line.

``dfusion simulate SCENARIO [--seed N] [--fusion channel|naive] [--duration S] [--json OUT] [--plot OUT.png]
[--no-protection]`` runs a scenario in one process and prints per-node RMSE, ANEES and the gap to
the centralized EKF, with message counts and the consistency diagnostics (``docs/clutter.md``).

``dfusion run SCENARIO [--speed X] [--json OUT] [--plot OUT.png] [--restart NAME@T[+D]] ...``
runs the same scenario with one OS process per node over Zenoh and prints the
same table (``docs/processes.md``).
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from dfusion.errors import DfusionError


def _simulate(args: argparse.Namespace) -> int:
    from dfusion.scenario.loader import load_scenario
    from dfusion.sim.runner import run_scenario

    sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration, plugins=args.plugin,
                       protection=False if args.no_protection else None)
    result = run_scenario(sc, progress=sys.stderr.isatty() and not args.quiet)
    print(result.table())
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json())
        print(f"wrote {args.json}")
    if args.plot:
        from dfusion.plots import plot_result

        print(f"wrote {plot_result(result, args.plot)}")
    return 0


def _run(args: argparse.Namespace) -> int:
    import signal

    stop: list[str] = []
    launcher = None

    def on_signal(signum, frame):   # only sets a flag; the launcher stops every node within 2 s
        stop.append(signal.Signals(signum).name)
        if launcher is not None:
            launcher.request_stop(stop[0])

    codes = {"SIGTERM": 128 + signal.SIGTERM, "SIGINT": 128 + signal.SIGINT}
    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        from dfusion.run.launcher import Launcher, Restart, RunOptions

        opts = RunOptions(
            scenario=args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration, speed=args.speed,
            run_dir=args.run_dir, network=args.network, network_key_file=args.network_key_file,
            restarts=[Restart.parse(r) for r in args.restart], emulate_links=args.emulate_links,
            round_timeout=args.round_timeout, progress=sys.stderr.isatty() and not args.quiet,
            startup_timeout=args.startup_timeout, keep_run_dir=args.run_dir is not None, plugins=list(args.plugin),
        )
        launcher = Launcher(opts)
        if stop:
            return codes.get(stop[0], 1)
        result = launcher.run()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    from dfusion.run.monitor import run_table

    if result is None:
        print(f"dfusion: stopped ({launcher.stop_reason}); every node process was stopped", file=sys.stderr)
        return codes.get(launcher.stop_reason or "", 1)
    print(result.table())
    print(run_table(result))
    if args.compare:
        from dfusion.sim.runner import run_scenario

        ref = run_scenario(launcher.sc).metrics
        print("\nagainst dfusion simulate (same scenario and seed):")
        print(f"{'node':<10} {'RMSE run':>9} {'RMSE sim':>9} {'diff':>9} {'gap run':>9} {'gap sim':>9}")
        for name, v in result.metrics["nodes"].items():
            r = ref["nodes"][name]
            print(f"{name:<10} {v['rmse']:9.4f} {r['rmse']:9.4f} {v['rmse'] - r['rmse']:+9.4f} "
                  f"{v['final_gap']:9.1e} {r['final_gap']:9.1e}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json())
        print(f"wrote {args.json}")
    if args.plot:
        from dfusion.plots import plot_result

        print(f"wrote {plot_result(result, args.plot)}")
    return 1 if launcher.failures else 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dfusion", description="Decentralized sensor fusion on trees of fusion nodes.")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="run a scenario in one process against the centralized EKF")
    s.add_argument("scenario", help="scenario TOML file (see docs/scenarios.md)")
    s.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    s.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    s.add_argument("--duration", type=float, default=None, help="override the scenario's duration (seconds)")
    s.add_argument("--json", metavar="OUT", help="write the figures as JSON")
    s.add_argument("--plot", metavar="OUT.png", help="write a PNG of every node against the centralized EKF")
    s.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable; docs/new-sensor-kind.md)")
    s.add_argument("--no-protection", action="store_true",
                   help="no clutter model (cameras: hard gate only) and no consistency test of neighbours "
                        "(protection.enabled = false; docs/clutter.md)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_simulate)

    r = sub.add_parser("run", help="run a scenario with one OS process per node, over Zenoh (docs/processes.md)")
    r.add_argument("scenario", help="scenario TOML file (see docs/scenarios.md)")
    r.add_argument("--speed", type=float, default=1.0, help="scenario seconds per wall-clock second (default 1: real time)")
    r.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    r.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    r.add_argument("--duration", type=float, default=None, help="override the scenario's duration (seconds)")
    r.add_argument("--json", metavar="OUT", help="write the figures as JSON (the keys of simulate, plus 'run')")
    r.add_argument("--plot", metavar="OUT.png", help="write a PNG of every node against the centralized EKF")
    r.add_argument("--restart", action="append", default=[], metavar="NAME@T[+D]",
                   help="SIGKILL node NAME at scenario time T and start it again D seconds later (repeatable)")
    r.add_argument("--network-key-file", default=None,
                   help="authenticate every message with this key (or set $DFUSION_NETWORK_KEY_FILE / $DFUSION_NETWORK_KEY)")
    r.add_argument("--emulate-links", action="store_true", help="apply the scenario's link drops and outages to sends")
    r.add_argument("--round-timeout", type=float, default=10.0,
                   help="seconds a node waits for a live neighbour's message of a final-phase round")
    r.add_argument("--run-dir", default=None, help="keep logs, state logs and results here (default: a temporary directory)")
    r.add_argument("--network", default=None, help="Zenoh network name (default: unique per run)")
    r.add_argument("--startup-timeout", type=float, default=60.0, help="seconds to wait for every node to be ready")
    r.add_argument("--compare", action="store_true", help="also run simulate and compare RMSE and final gaps")
    r.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable; every node process loads it too)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except DfusionError as exc:
        print(f"dfusion: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"dfusion: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
