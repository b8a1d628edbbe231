"""Figures (PNG) of simulation results, with matplotlib's Agg backend."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_result(result, path: str | Path, *, max_nodes: int = 6, title: str | None = None) -> Path:
    """Each node's X and Y error against the centralized EKF's, with 3-sigma bands.

    One row per node (at most ``max_nodes``), columns X and Y; every curve is
    *estimate minus truth*, so the bands (±3σ) are visible whatever the
    trajectory's extent. Link outages are shaded (darker where they touch the
    node).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted(result.node_mean)[:max_nodes]
    t = result.times
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.4 * len(names) + 0.9), sharex=True, squeeze=False)
    outages = result.scenario.outages()
    for row, name in enumerate(names):
        for col, label in enumerate(("X", "Y")):
            ax = axes[row][col]
            truth = result.truth[:, col]
            m = result.node_mean[name][:, col] - truth
            s = 3 * np.sqrt(result.node_cov[name][:, col, col])
            cm = result.central_mean[:, col] - truth
            cs = 3 * np.sqrt(result.central_cov[:, col, col])
            for a, b, t0, t1 in outages:
                mine = name in (a, b)
                ax.axvspan(t0, t1, color="tab:red", alpha=0.18 if mine else 0.07, lw=0)
            ax.fill_between(t, -s, s, color="tab:blue", alpha=0.18, lw=0, label=f"node ±3σ")
            ax.plot(t, cs, color="k", lw=0.8, ls=":", label="centralized ±3σ")
            ax.plot(t, -cs, color="k", lw=0.8, ls=":")
            ax.plot(t, cm, color="k", lw=0.9, label="centralized EKF error")
            ax.plot(t, m, color="tab:blue", lw=0.9, label="node error")
            ax.axhline(0.0, color="tab:green", lw=0.6)
            ax.set_ylabel(f"{name}: {label} error [m]")
            if row == 0 and col == 0:
                ax.legend(loc="upper right", fontsize=7, ncol=2)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    m = result.metrics
    fig.suptitle(title or f"{Path(result.scenario.path).name}: estimate − truth per node vs centralized EKF "
                 f"(fusion={m['fusion']}, seed={m['seed']}; red: link outages)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
