"""Clutter: every node's RMSE and ANEES under false detections, with and without the protections.

For each scenario and seed: the clean run (no false detections, protections on), the cluttered
run with the protections (PDA cameras, consistency test of neighbours) and without them
(``protection = false``: hard gate only, no test), at ``--rate`` false detections per frame at
every camera. Per run: the worst node's RMSE ratio (cluttered / clean), the worst ANEES, PASS when
ratio <= 1.25 and ANEES <= 8 at every node (docs/clutter.md), the fair and oracle centralized
RMSE, the share of false detections, quarantines and track losses. With ``--nodes`` every node's
figures are printed too.

Seeds: the first ``--seeds`` seeds from 0 (or those of ``--seed-list``) in which every camera sees
the target at least 10 % of the time (the URUS square: and the person stays in it), as in
tests/sim/test_clutter_acceptance.py (the rule and the runs: tests/helpers/clutter.py, loaded by
path); ``--all-seeds`` takes seeds 0.. without the rule.

``--urus-mc``: instead, the URUS demo as shipped (0.1 false detections per frame, or ``--rate``)
over the Monte Carlo seeds of docs/urus-demo.md (100-107): per node ANEES and RMSE (the mean of
the runs' RMSE), both references, final gaps, quarantines and track losses, and the consistency
test by sending node: messages tested, failed, and the statistic per degree of freedom.

``--pf-information quotient|regression``: the WSN nodes' contribution method for every run (default:
the scenario files' own; only the URUS demo has a WSN node among these scenarios; docs/wsn.md).

Usage: python benchmarks/clutter.py [--quick] [--rate 0.3] [--seeds 3] [--all-seeds] [--nodes]
                                    [--pf-information M] [SCENARIO ...]
       python benchmarks/clutter.py --urus-mc [--rate R]
(``--quick``: one seed per scenario.)
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _helpers():
    spec = importlib.util.spec_from_file_location("clutter_helpers", ROOT / "tests" / "helpers" / "clutter.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


H = _helpers()
SCENARIOS, run, seeds_for, false_share = H.SCENARIOS, H.run, H.seeds_for, H.false_share


def urus_monte_carlo(rate: float | None) -> None:
    """The URUS demo over seeds 100-107 (see the module docstring)."""
    import numpy as np

    from dfusion.fusion.guard import NeighbourGuard
    from dfusion.metrics import nees
    from dfusion.scenario import load_scenario
    from dfusion.sim import run_scenario

    tested: list[tuple[str, bool, float, int]] = []   # (sender, failed, statistic, dof)
    judge = NeighbourGuard.judge

    def recording(self, j, stat, dof):
        if dof > 0:
            tested.append((j, not stat <= self.threshold(dof), stat, dof))
        return judge(self, j, stat, dof)

    NeighbourGuard.judge = recording
    raw = H.with_rate(SCENARIOS["urus"][0], rate) if rate is not None else None
    per: dict[str, list] = {}
    gaps, quarantines, losses = [], 0, 0
    try:
        for seed in range(100, 108):
            res = run_scenario(load_scenario(raw if raw is not None else SCENARIOS["urus"][0], seed=seed))
            series = {**{n: (res.node_mean[n], res.node_cov[n]) for n in res.node_mean},
                      "centralized (fair)": (res.central_mean, res.central_cov),
                      "centralized oracle": (res.oracle_mean, res.oracle_cov)}
            for name, (mean, cov) in series.items():
                err = np.sqrt(np.mean(np.sum((mean[:, :2] - res.truth[:, :2]) ** 2, axis=1)))
                per.setdefault(name, []).append((nees(mean, cov, res.truth)[1:], err))
            nodes = res.metrics["nodes"].values()
            gaps += [v["final_gap"] for v in nodes]
            quarantines += sum(v["quarantines"] or 0 for v in nodes)
            losses += sum(v["track_losses"] or 0 for v in nodes)
    finally:
        NeighbourGuard.judge = judge
    print("| node | ANEES (8 runs) | RMSE [m] (mean of the runs) |")
    print("|---|---|---|")
    for name, runs in per.items():
        print(f"| {name} | {np.mean(np.concatenate([r[0] for r in runs])):.2f} | {np.mean([r[1] for r in runs]):.3f} |")
    print(f"\nfinal gap: median {np.median(gaps):.3f} m, largest {np.max(gaps):.3f} m; quarantines {quarantines}, "
          f"track losses {losses}")
    print("\n| sender | messages tested | failed (alpha = 1e-3) | statistic per dof |")
    print("|---|---|---|---|")
    for sender in sorted({t[0] for t in tested}) + ["all"]:
        rows = [t for t in tested if sender in ("all", t[0])]
        fails = sum(t[1] for t in rows)
        print(f"| {sender} | {len(rows)} | {fails} ({fails / len(rows):.2%}) | "
              f"{sum(t[2] for t in rows) / sum(t[3] for t in rows):.2f} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenarios", nargs="*", default=sorted(SCENARIOS), help=f"some of {sorted(SCENARIOS)}")
    p.add_argument("--rate", type=float, default=0.3, help="false detections per frame at every camera")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--seed-list", default=None, help="comma-separated seeds instead of the rule")
    p.add_argument("--all-seeds", action="store_true", help="seeds 0.. without the geometric rule")
    p.add_argument("--nodes", action="store_true", help="print every node's RMSE and ANEES")
    p.add_argument("--quick", action="store_true", help="one seed per scenario")
    p.add_argument("--pf-information", choices=("quotient", "regression"), default=None,
                   help="the WSN nodes' contribution method (default: the scenario file's)")
    p.add_argument("--urus-mc", action="store_true", help="the URUS demo over seeds 100-107 (docs/urus-demo.md)")
    a = p.parse_args(argv)
    if a.urus_mc:
        urus_monte_carlo(a.rate if "--rate" in (argv if argv is not None else sys.argv) else None)
        return 0
    if a.quick:
        a.seeds = 1
    unknown = set(a.scenarios) - set(SCENARIOS)
    if unknown:
        p.error(f"unknown scenarios {sorted(unknown)}; known: {sorted(SCENARIOS)}")
    print("| scenario | seed | false share | clean RMSE (worst node) | protected: worst ratio | ANEES max | "
          "verdict | unprotected: worst ratio | ANEES max | verdict | central fair / oracle RMSE | "
          "quarantines | track losses |")
    print("|" + "---|" * 13)
    for name in a.scenarios:
        seeds = ([int(s) for s in a.seed_list.split(",")] if a.seed_list
                 else seeds_for(name, a.seeds, not a.all_seeds))
        for seed in seeds:
            t0 = time.perf_counter()
            runs = {key: run(name, seed, rate, prot, a.pf_information)
                    for key, rate, prot in (("clean", 0.0, True), ("on", a.rate, True), ("off", a.rate, False))}
            clean = runs["clean"].metrics["nodes"]
            cells = []
            for key in ("on", "off"):
                m = runs[key].metrics["nodes"]
                ratio = max(m[n]["rmse"] / clean[n]["rmse"] for n in m)
                anees = max(v["anees"] for v in m.values())
                ok = ratio <= H.RATIO and anees <= H.ANEES
                cells += [f"{ratio:.2f}", f"{anees:.3g}", "PASS" if ok else "FAIL"]
            share = false_share(runs["on"])
            on = runs["on"].metrics
            q = sum(v.get("quarantines") or 0 for v in on["nodes"].values())
            losses = sum(v.get("track_losses") or 0 for v in on["nodes"].values())
            print(f"| {name} | {seed} | {share:.2f} | {max(v['rmse'] for v in clean.values()):.3f} | "
                  + " | ".join(cells)
                  + f" | {on['centralized']['rmse']:.3f} / {on['centralized_oracle']['rmse']:.3f} | {q} | {losses} |",
                  flush=True)
            if a.nodes:
                for n in clean:
                    print(f"|   | {n} | | {clean[n]['rmse']:.3f} | "
                          f"{runs['on'].metrics['nodes'][n]['rmse']:.3f} | {runs['on'].metrics['nodes'][n]['anees']:.2f} | | "
                          f"{runs['off'].metrics['nodes'][n]['rmse']:.3f} | {runs['off'].metrics['nodes'][n]['anees']:.3g} "
                          f"| | | | |")
            print(f"<!-- {name} seed {seed}: {time.perf_counter() - t0:.1f} s -->", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
