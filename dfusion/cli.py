"""The ``dfusion`` command line.

``dfusion simulate SCENARIO [--seed N] [--fusion channel|naive] [--duration S] [--json OUT] [--plot OUT.png]``
runs a scenario in one process and prints per-node RMSE, ANEES and the gap to
the centralized EKF, with message counts.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .errors import DfusionError


def _simulate(args: argparse.Namespace) -> int:
    from .sim.runner import run_scenario
    from .sim.scenario import load_scenario

    sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration)
    result = run_scenario(sc, progress=sys.stderr.isatty() and not args.quiet)
    print(result.table())
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json())
        print(f"wrote {args.json}")
    if args.plot:
        from .plots import plot_result

        print(f"wrote {plot_result(result, args.plot)}")
    return 0


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
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_simulate)
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
