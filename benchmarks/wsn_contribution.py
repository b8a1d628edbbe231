"""The WSN's information contribution, quotient against regression, on the URUS demo under clutter.

For each seed of the clutter acceptance rule (tests/helpers/clutter.py, loaded by path: the first
``--seeds`` seeds in which both cameras see the person and the person stays in the square) and each
of ``--pf-seeds`` seeds of the WSN's particle filter (the world, i.e. the truth and every
measurement, stays that of the scenario seed; only the particles' random draws change: offset 0 is
the shipped run), both methods (``pf_information = "quotient" | "regression"``, docs/wsn.md):

* the clean run and the run with ``--rate`` false detections per frame at both cameras (protections
  on); the worst node's RMSE ratio (cluttered / clean), the worst ANEES, PASS when ratio <= 1.25 and
  ANEES <= 8 (the criterion of tests/sim/test_clutter_acceptance.py);
* the WSN's own contributions against the simulated truth: the normalized error of the
  pseudo-measurement ``Omega^+ eta`` per degree of freedom, mean and largest, and how many exceed
  the chi-square 0.999 quantile (the WSN's readings do not depend on the clutter, so its
  contributions are those of the clean run);
* cam_left's clean RMSE.

Then a summary per method: failures, mean worst ratio, mean clean RMSE per node, and the
contributions' mean normalized error. Not timed: accuracy and consistency only.

``--ess``: instead, the regression contribution as the effective sample size falls: a 12-receiver
field, a prior N((6, 5), I), the truth drawn from it, one reading per receiver with 3 / 1 / 0.3 dB
noise, 200 / 2,000 / 20,000 particles, 30 draws each: the median ESS, ``trace(Omega)`` over the
trace of the readings' Fisher information ``H^T R^-1 H`` at the truth (median, largest), and the
normalized error of ``Omega^-1 eta`` against the truth per degree of freedom (mean, largest).

Usage: python benchmarks/wsn_contribution.py [--seeds 8 | --seed-list 16,...] [--pf-seeds 3] [--rate 0.3]
                                             [--method M] [--quick]
       python benchmarks/wsn_contribution.py --ess
(``--quick``: one seed, one particle-filter seed; ``--method``: one of the two only, e.g. to run
them in two processes.)
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
METHODS = ("quotient", "regression")
#: Seed offset between particle-filter seeds (any number; a prime keeps them apart from the
#: scenario's own node seeds ``1000 seed + rank``).
PF_STRIDE = 7919


# tests/helpers/clutter.py, as benchmarks/clutter.py loads it (by path)
sys.path.insert(0, str(Path(__file__).resolve().parent))
from clutter import H


def one_run(seed: int, pf_seed: int, rate: float, method: str):
    """(node metrics, contributions [(t, eta, Omega)]) of the URUS demo, WSN particle-filter seed
    offset by ``pf_seed``."""
    from dfusion.localization import WSNTracker
    from dfusion.scenario import load_scenario, wsn_kind
    from dfusion.sim import run_scenario

    contributions: list[tuple[float, np.ndarray, np.ndarray]] = []

    class Tracker(WSNTracker):
        def __init__(self, *args, seed, **kw):
            super().__init__(*args, seed=seed + PF_STRIDE * pf_seed, **kw)

        def information_contribution(self, rtol: float = 1e-9, method: str = "quotient"):
            info = super().information_contribution(rtol, method)
            contributions.append((self.time, info.eta.copy(), info.Omega.copy()))
            return info

    original = wsn_kind.WSNTracker
    wsn_kind.WSNTracker = Tracker
    try:
        raw = H.with_rate(H.SCENARIOS["urus"][0], rate, method)
        res = run_scenario(load_scenario(raw, seed=seed, protection=True))
    finally:
        wsn_kind.WSNTracker = original
    return res, contributions


def normalized_errors(res, contributions) -> np.ndarray:
    """Normalized error per degree of freedom of each non-zero contribution's ``Omega^+ eta``
    against the truth at its time, and its degrees of freedom, as rows ``(value, dof)``."""
    out = []
    for t, eta, Om in contributions:
        if not np.any(Om):
            continue
        x = np.array([np.interp(t, res.times, res.truth[:, j]) for j in range(2)])
        lam, V = np.linalg.eigh(Om)
        keep = lam > 1e-9 * lam.max()
        r = V[:, keep].T @ (eta - Om @ x)     # = Lambda (Omega^+ eta - x) in the eigenbasis
        out.append((float(np.sum(r * r / lam[keep])) / keep.sum(), int(keep.sum())))
    return np.array(out).reshape(-1, 2)


def ess_table() -> None:
    """The ``--ess`` table (module docstring)."""
    from dfusion.localization import WSNTracker
    from dfusion.models import RSSISensor

    receivers = np.array([[x, y, 2.0] for x in (1.0, 6.0, 11.0) for y in (1.0, 4.5, 9.0)]
                         + [[3.5, 6.5, 2.0], [8.5, 2.5, 2.0], [8.5, 7.5, 2.0]])
    rng = np.random.default_rng(0)
    mean = np.array([6.0, 5.0])
    print("| reading std (dB) | particles | ESS (median) | tr(Omega) / tr(Fisher at the truth): median | largest "
          "| normalized error / dof: mean | largest |")
    print("|" + "---|" * 7)
    for std in (3.0, 1.0, 0.3):
        s = RSSISensor(receivers, p0=-55.0, exponent=2.2, std=std, height=1.2)
        for n in (200, 2000, 20000):
            ratio, ess, ne = [], [], []
            for k in range(30):
                truth = rng.multivariate_normal(mean, np.eye(2))
                z = s.h(truth) + std * rng.standard_normal(12)
                t = WSNTracker(s, n, bounds=[-5, -5, 17, 15], seed=k, ess_threshold=0.0)
                t.initialize(mean=mean, cov=np.eye(2))
                t.predict(0.0)
                t.update(0.0, z)
                info = t.information_contribution(method="regression")
                jac = s.H(truth)
                ratio.append(np.trace(info.Omega) / np.trace(jac.T @ jac / std ** 2))
                ess.append(t.pf.ess)
                e = np.linalg.solve(info.Omega, info.eta) - truth
                ne.append(e @ info.Omega @ e / 2.0)
            print(f"| {std} | {n} | {np.median(ess):.1f} | {np.median(ratio):.2f} | {np.max(ratio):.2f} | "
                  f"{np.mean(ne):.2f} | {np.max(ne):.1f} |", flush=True)


def main(argv=None) -> int:
    from dfusion.linalg import chi2_isf

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=8, help="scenario seeds of the clutter rule")
    p.add_argument("--seed-list", default=None, help="comma-separated scenario seeds instead of the rule")
    p.add_argument("--ess", action="store_true", help="the regression as the effective sample size falls")
    p.add_argument("--pf-seeds", type=int, default=3, help="particle-filter seeds per scenario seed")
    p.add_argument("--rate", type=float, default=H.RATE, help="false detections per frame at every camera")
    p.add_argument("--method", choices=METHODS, default=None, help="only this method (default: both)")
    p.add_argument("--quick", action="store_true", help="one seed, one particle-filter seed")
    a = p.parse_args(argv)
    methods = METHODS if a.method is None else (a.method,)
    if a.ess:
        ess_table()
        return 0
    if a.quick:
        a.seeds, a.pf_seeds = 1, 1
    if a.seeds < 1 or a.pf_seeds < 1:
        p.error("--seeds and --pf-seeds must be at least 1")
    seeds = [int(x) for x in a.seed_list.split(",")] if a.seed_list else H.seeds_for("urus", a.seeds)
    print(f"URUS demo, {a.rate} false detections per frame at both cameras; seeds {seeds}; "
          f"particle-filter seeds 0-{a.pf_seeds - 1} (0: the shipped run)\n")
    print("| seed | PF seed | method | worst ratio | ANEES max | verdict | cam_left ratio | clean RMSE cam_left "
          "| WSN contributions | normalized error / dof: mean | largest | above 0.999 quantile |")
    print("|" + "---|" * 12)
    summary: dict[str, dict] = {m: {"fail": 0, "runs": 0, "ratio": [], "clean": {}, "nees": []} for m in methods}
    for seed in seeds:
        for pf in range(a.pf_seeds):
            for method in methods:
                t0 = time.perf_counter()
                clean, contrib = one_run(seed, pf, 0.0, method)
                dirty, _ = one_run(seed, pf, a.rate, method)
                c, d = clean.metrics["nodes"], dirty.metrics["nodes"]
                ratios = {n: d[n]["rmse"] / c[n]["rmse"] for n in c}
                worst, anees = max(ratios.values()), max(v["anees"] for v in d.values())
                ok = worst <= H.RATIO and anees <= H.ANEES
                ne = normalized_errors(clean, contrib)
                above = int(sum(v * k > chi2_isf(1e-3, int(k)) for v, k in ne))
                s = summary[method]
                s["runs"] += 1
                s["fail"] += not ok
                s["ratio"].append(worst)
                s["nees"].append(ne)
                for n in c:
                    s["clean"].setdefault(n, []).append(c[n]["rmse"])
                print(f"| {seed} | {pf} | {method} | {worst:.2f} | {anees:.2f} | {'PASS' if ok else 'FAIL'} | "
                      f"{ratios['cam_left']:.2f} | {c['cam_left']['rmse']:.3f} | {len(ne)} | {ne[:, 0].mean():.2f} | "
                      f"{ne[:, 0].max():.1f} | {above} |", flush=True)
                print(f"<!-- seed {seed} pf {pf} {method}: {time.perf_counter() - t0:.1f} s -->", file=sys.stderr)
    nodes = sorted(summary[methods[0]]["clean"])
    print("\n| method | runs | FAIL | mean worst ratio | " + " | ".join(f"clean RMSE {n} (mean)" for n in nodes)
          + " | contributions: normalized error / dof (mean) | above 0.999 quantile |")
    print("|" + "---|" * (6 + len(nodes)))
    for method in methods:
        s = summary[method]
        ne = np.vstack(s["nees"])
        above = int(sum(v * k > chi2_isf(1e-3, int(k)) for v, k in ne))
        print(f"| {method} | {s['runs']} | {s['fail']} | {np.mean(s['ratio']):.2f} | "
              + " | ".join(f"{np.mean(s['clean'][n]):.3f}" for n in nodes)
              + f" | {ne[:, 0].mean():.2f} | {above} of {len(ne)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
