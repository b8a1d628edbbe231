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
            ax.fill_between(t, -s, s, color="tab:blue", alpha=0.18, lw=0, label="node ±3σ")
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


def _intervals(mask: np.ndarray, t: np.ndarray) -> list[tuple[float, float]]:
    """``[start, end]`` time intervals where ``mask`` is true (half a step added on each side)."""
    if not mask.any():
        return []
    half = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    m = np.concatenate([[False], mask, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    ends = np.flatnonzero(np.diff(m) == -1) - 1
    return [(float(t[a]) - half, float(t[b]) + half) for a, b in zip(starts, ends)]


def plot_figure33(result, node: str, path: str | Path, *, title: str | None = None) -> Path:
    """URUS Figure 33: one node's X and Y against the centralized EKF, with 3-sigma bounds, over time.

    Rows: X, Y (node mean in red with its ±3σ bounds, centralized EKF in black
    with its ±3σ band, truth dotted green), then the gap ``max |node - centralized|``
    over the state on a log scale. Link outages are shaded red (darker where the
    link touches ``node``); periods when the target is in ``node``'s camera view
    (its sensor's ``in_view`` at the true state) are marked by a green strip at the
    top of each panel, with a tick per detection of the node (grey crosses: false
    detections).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    if node not in result.node_mean:
        raise KeyError(f"{node!r} is not a node of the result (nodes: {sorted(result.node_mean)})")
    t = result.times
    mean, cov = result.node_mean[node], result.node_cov[node]
    cm, cc = result.central_mean, result.central_cov
    spec = result.scenario.nodes.get(node)
    sensor = getattr(spec, "sensor", None)
    in_view = None
    if sensor is not None and hasattr(sensor, "in_view"):
        in_view = np.array([sensor.in_view(x) for x in result.truth])
    meas = [m for m in getattr(result.world, "measurements", []) if m.node == node]
    det_t = np.array([m.t for m in meas if not getattr(m, "clutter", False)])
    clut_t = np.array([m.t for m in meas if getattr(m, "clutter", False)])
    outages = result.scenario.outages()

    fig, axes = plt.subplots(3, 1, figsize=(11, 8.2), sharex=True, gridspec_kw={"height_ratios": [3, 3, 1.6]})

    def shade(ax) -> None:
        for a, b, t0, t1 in outages:
            ax.axvspan(t0, t1, color="tab:red", alpha=0.16 if node in (a, b) else 0.06, lw=0)

    def strip(ax) -> None:
        tr = ax.get_xaxis_transform()   # x in data, y in axes fraction
        if in_view is not None:
            for a, b in _intervals(in_view, t):
                ax.fill_between([a, b], 0.955, 1.0, transform=tr, color="tab:green", alpha=0.55, lw=0)
        if det_t.size:
            ax.vlines(det_t, 0.925, 0.955, transform=tr, color="tab:green", lw=0.6)
        if clut_t.size:
            ax.plot(clut_t, np.full(clut_t.size, 0.94), "x", transform=tr, color="0.4", ms=3, mew=0.7)

    for row, label in enumerate(("X", "Y")):
        ax = axes[row]
        shade(ax)
        s_node = 3 * np.sqrt(cov[:, row, row])
        s_cen = 3 * np.sqrt(cc[:, row, row])
        ax.fill_between(t, cm[:, row] - s_cen, cm[:, row] + s_cen, color="0.55", alpha=0.35, lw=0,
                        label="centralized ±3σ")
        ax.plot(t, cm[:, row], color="k", lw=1.1, label="centralized EKF")
        ax.plot(t, mean[:, row], color="tab:red", lw=1.1, label=f"{node}")
        ax.plot(t, mean[:, row] + s_node, color="tab:red", lw=0.8, ls="--", label=f"{node} ±3σ")
        ax.plot(t, mean[:, row] - s_node, color="tab:red", lw=0.8, ls="--")
        ax.plot(t, result.truth[:, row], color="tab:green", lw=0.9, ls=":", label="truth")
        strip(ax)
        lo = np.minimum(cm[:, row] - s_cen, result.truth[:, row]).min()
        hi = np.maximum(cm[:, row] + s_cen, result.truth[:, row]).max()
        pad = 0.08 * (hi - lo) + 0.2
        # keep the node's bounds from flattening the curves: clip the axis to the centralized range
        ax.set_ylim(lo - pad, hi + 2.2 * pad)
        ax.set_ylabel(f"{label} [m]")
        ax.grid(alpha=0.25)
    handles, labels = axes[0].get_legend_handles_labels()
    handles += [Patch(color="tab:red", alpha=0.3, label="link outage (this node)")]
    if in_view is not None:
        handles += [Patch(color="tab:green", alpha=0.55, label=f"target in {node}'s view (ticks: detections)")]
    axes[0].legend(handles=handles, loc="lower right", fontsize=7.5, ncol=2, framealpha=0.9)

    ax = axes[2]
    shade(ax)
    gap = np.abs(mean - cm).max(axis=1)
    ax.semilogy(t, np.maximum(gap, 1e-12), color="tab:red", lw=0.9)
    ax.set_ylabel("|node − central|\nmax over state")
    ax.set_ylim(max(1e-6, float(np.min(gap[gap > 0])) * 0.5 if np.any(gap > 0) else 1e-6),
                max(1.0, float(gap.max()) * 2))
    ax.grid(alpha=0.25, which="both")
    strip(ax)
    ax.set_xlabel("time [s]")
    ax.set_xlim(t[0], t[-1])
    m = result.metrics.get("nodes", {}).get(node, {})
    sub = (f"RMSE {m['rmse']:.2f} m (centralized {result.metrics['centralized']['rmse']:.2f} m), "
           f"mean gap {m['mean_gap']:.2g}, final gap {m['final_gap']:.2g}") if m else ""
    fig.suptitle(title or f"{node}: estimated X and Y (red) vs the centralized EKF (black), ±3σ "
                 f"— URUS Figure 33 style\n{sub}", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
