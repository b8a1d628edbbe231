"""Figures (PNG) of simulation results, with matplotlib's Agg backend."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dfusion.errors import ValidationError


def transient_end(times: np.ndarray, sigma: np.ndarray, factor: float = 2.0) -> float:
    """End of the start-up transient: the first time after which ``sigma`` (e.g. the
    centralized EKF's largest position standard deviation) stays below ``factor`` times
    its median over the second half of the run (the steady state). 0 when there is none.
    """
    s = np.asarray(sigma, dtype=float)
    t = np.asarray(times, dtype=float)
    if s.size < 4:
        return float(t[0]) if t.size else 0.0
    level = factor * float(np.median(s[s.size // 2:]))
    above = np.flatnonzero(s > level)
    if above.size == 0:
        return float(t[0])
    k = min(int(above[-1]) + 1, t.size - 1)
    # only a transient at the start counts; later excursions (outages) are data
    return float(t[k]) if t[k] <= t[0] + 0.25 * (t[-1] - t[0]) else float(t[0])


def steady_limits(t: np.ndarray, t_start: float, *curves: np.ndarray, pad: float = 0.1) -> tuple[float, float]:
    """Symmetric y-limits covering every curve after ``t_start`` (the steady state)."""
    sel = t >= t_start
    hi = max(float(np.nanmax(np.abs(c[sel]))) for c in curves) if sel.any() else 1.0
    hi = hi * (1 + pad) if hi > 0 else 1.0
    return -hi, hi


def plot_result(result, path: str | Path, *, max_nodes: int = 6, title: str | None = None) -> Path:
    """Each node's X and Y error against the centralized EKF's, with 3-sigma bands
    (:func:`plot_track_errors`: steady-state y-range, start-up transient shaded and
    clipped, link outages shaded, one legend for every line and shading)."""
    from dfusion.viz.topdown import Track, finite_rows

    if not finite_rows(result.truth[:, :2]).any():
        raise ValidationError("the error plot needs the truth, and this run has none (dfusion replay: give --truth)")
    names = sorted(result.node_mean)[:max_nodes]
    t = result.times
    tracks = [Track(n, t, result.node_mean[n][:, :2], result.node_cov[n][:, :2, :2]) for n in names]
    ref = Track("centralized EKF", t, result.central_mean[:, :2], result.central_cov[:, :2, :2], "k")
    m = result.metrics
    return plot_track_errors(
        t, result.truth[:, :2], tracks, path, reference=ref, outages=result.scenario.outages(),
        title=title or f"{Path(result.scenario.path).name}: each node's position error against the centralized "
                       f"EKF's (fusion={m['fusion']}, seed={m['seed']})")


def plot_track_errors(t: np.ndarray, truth: np.ndarray, tracks: list, path: str | Path, *, title: str,
                      reference=None, outages=(), truth_times: np.ndarray | None = None,
                      xlabel: str = "time [s]") -> Path:
    """Position errors (estimate − truth, X and Y in m) of several estimators over time.

    One row per :class:`~dfusion.viz.topdown.Track` (its own times; the truth, given at
    ``truth_times`` or at ``t``, is interpolated there), columns X and Y; a track with a
    covariance gets its ±3σ band; ``reference`` (e.g. the centralized EKF) is drawn in
    black in every row. One y-range for all panels, from the steady state: the
    start-up transient (until every covariance has settled, :func:`transient_end`) is
    shaded grey and clipped; after it every error curve fits, and each ±3σ band fits
    95 % of the time (a band that balloons while a node is cut off leaves the panel:
    the outage shading says why). ``outages`` ``(a, b, t0, t1)`` are shaded red, dark where
    the link touches the row's track. One legend explains every line and shading.
    ``xlabel`` names the horizontal axis (``"scan index"`` where the times are indices).
    Times where the truth is unknown (NaN) are left out.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    tt = np.asarray(t if truth_times is None else truth_times, float)
    truth = np.asarray(truth, float)
    known = np.isfinite(truth[:, :2]).all(axis=1)
    if not known.any():
        raise ValidationError("the error plot needs the truth, and none is known")
    tt, truth = tt[known], truth[known]

    def truth_at(ts):   # NaN outside the known truth: no error is drawn there
        out = np.column_stack([np.interp(ts, tt, truth[:, 0]), np.interp(ts, tt, truth[:, 1])])
        out[(ts < tt[0] - 1e-9) | (ts > tt[-1] + 1e-9)] = np.nan
        return out

    def sigma(tr):
        return np.sqrt(np.maximum(np.asarray(tr.cov)[:, [0, 1], [0, 1]], 0.0)).max(axis=1)

    with_cov = [tr for tr in [*tracks, reference] if tr is not None and tr.cov is not None]
    t_tr = max((transient_end(np.asarray(tr.t), sigma(tr)) for tr in with_cov), default=float(tt[0]))
    t0_all = min(float(np.asarray(tr.t)[0]) for tr in tracks)
    t1_all = max(float(np.asarray(tr.t)[-1]) for tr in tracks)
    rows = len(tracks)
    fig, axes = plt.subplots(rows, 2, figsize=(12, 2.3 * rows + 1.5), sharex=True, sharey=True, squeeze=False)
    lim = 0.0
    any_mine = any_other = False
    colors = ["tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan"]
    for row, tr in enumerate(tracks):
        ts = np.asarray(tr.t, float)
        e = np.asarray(tr.mean, float)[:, :2] - truth_at(ts)
        color = tr.color or colors[row % len(colors)]
        for col, label in enumerate(("X", "Y")):
            ax = axes[row][col]
            for a, b, o0, o1 in outages:
                mine = tr.name in (a, b)
                any_mine |= mine
                any_other |= not mine
                ax.axvspan(o0, o1, color="tab:red", alpha=0.22 if mine else 0.08, lw=0)
            # the y-range holds every error curve after the transient, and the 3-sigma
            # bands 95 % of that time (a band that balloons, e.g. during an outage, may leave it)
            errors, bands = [(ts, e[:, col])], []
            if tr.cov is not None:
                s = 3 * np.sqrt(np.maximum(np.asarray(tr.cov)[:, col, col], 0.0))
                ax.fill_between(ts, -s, s, color=color, alpha=0.18, lw=0)
                bands.append((ts, s))
            if reference is not None:
                rt = np.asarray(reference.t, float)
                re = np.asarray(reference.mean, float)[:, col] - truth_at(rt)[:, col]
                ax.plot(rt, re, color="k", lw=0.9)
                errors.append((rt, re))
                if reference.cov is not None:
                    rs = 3 * np.sqrt(np.maximum(np.asarray(reference.cov)[:, col, col], 0.0))
                    ax.plot(rt, rs, color="k", lw=0.8, ls=":")
                    ax.plot(rt, -rs, color="k", lw=0.8, ls=":")
                    bands.append((rt, rs))
            ax.plot(ts, e[:, col], color=color, lw=0.9)
            ax.axhline(0.0, color="tab:green", lw=0.6)
            for (tc, c), pct in [(x, 100.0) for x in errors] + [(x, 95.0) for x in bands]:
                cc = np.abs(np.asarray(c)[np.asarray(tc) >= t_tr])
                cc = cc[np.isfinite(cc)]
                if cc.size:
                    lim = max(lim, float(np.percentile(cc, pct)))
            if t_tr > t0_all:
                ax.axvspan(t0_all, t_tr, facecolor="0.85", edgecolor="0.6", hatch="////", lw=0, zorder=0)
                if tr.cov is not None and row == 0:
                    s0 = 3 * math.sqrt(max(float(np.asarray(tr.cov)[0, col, col]), 0.0))
                    ax.annotate(f"↑ clipped: start ±{s0:.1f} m", xy=(t_tr, 1.0), xycoords=("data", "axes fraction"),
                                xytext=(3, -3), textcoords="offset points", ha="left", va="top", fontsize=7,
                                color="0.3")
            ax.set_ylabel(f"{tr.name}:\n{label} error [m]")
            ax.grid(alpha=0.25)
    lim = lim * 1.1 if lim > 0 else 1.0
    axes[0][0].set_ylim(-lim, lim)
    for ax in axes[-1]:
        ax.set_xlabel(xlabel)
        ax.set_xlim(t0_all, t1_all)
    handles = [Line2D([], [], color="tab:blue", lw=0.9, label="estimate − truth (colour: the row's estimator)")]
    if any(tr.cov is not None for tr in tracks):
        handles.append(Patch(color="tab:blue", alpha=0.18, label="±3σ of the estimator's own covariance"))
    if reference is not None:
        handles.append(Line2D([], [], color="k", lw=0.9, label=f"{reference.name} − truth"))
        if reference.cov is not None:
            handles.append(Line2D([], [], color="k", lw=0.8, ls=":", label=f"{reference.name} ±3σ"))
    handles.append(Line2D([], [], color="tab:green", lw=0.6, label="zero error"))
    if t_tr > t0_all:
        handles.append(Patch(facecolor="0.85", edgecolor="0.6", hatch="////",
                             label=f"start-up transient to {t_tr:.1f} s (clipped: y-range from the steady state)"))
    if any_mine:
        handles.append(Patch(color="tab:red", alpha=0.22, label="outage of a link of this node"))
    if any_other:
        handles.append(Patch(color="tab:red", alpha=0.08, label="outage of another link"))
    # the title's lines, then the legend's rows under them, then the axes (heights in inches)
    height = fig.get_figheight()
    title_h = 0.05 + 0.19 * (str(title).count("\n") + 1)
    legend_h = 0.15 * math.ceil(len(handles) / 3)
    fig.suptitle(title, fontsize=10, y=1 - 0.05 / height, va="top")
    fig.legend(handles=handles, loc="upper center", ncol=3, fontsize=7.5, frameon=False,
               bbox_to_anchor=(0.5, 1 - title_h / height))
    fig.tight_layout(rect=(0, 0, 1, 1 - (title_h + legend_h) / height))
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
    if any(node in (a, b) for a, b, _, _ in outages):
        handles += [Patch(color="tab:red", alpha=0.3, label="outage of a link of this node")]
    if any(node not in (a, b) for a, b, _, _ in outages):
        handles += [Patch(color="tab:red", alpha=0.1, label="outage of another link")]
    if in_view is not None:
        handles += [Patch(color="tab:green", alpha=0.55, label=f"target in {node}'s view (ticks: detections)")]
    axes[0].legend(handles=handles, loc="lower right", fontsize=7.5, ncol=2, framealpha=0.9)

    ax = axes[2]
    shade(ax)
    d = mean - cm
    gp = np.linalg.norm(d[:, :2], axis=1)
    ax.semilogy(t, np.maximum(gp, 1e-12), color="tab:red", lw=0.9, label="position [m]")
    gaps = [gp]
    if d.shape[1] == 4:
        gv = np.linalg.norm(d[:, 2:], axis=1)
        ax.semilogy(t, np.maximum(gv, 1e-12), color="tab:purple", lw=0.8, ls="--", label="velocity [m/s]")
        gaps.append(gv)
    gap = np.concatenate(gaps)
    ax.set_ylabel("node − centralized\n(distance)")
    ax.legend(loc="upper right", fontsize=7, ncol=2, framealpha=0.9)
    ax.set_ylim(max(1e-6, float(np.min(gap[gap > 0])) * 0.5 if np.any(gap > 0) else 1e-6),
                max(1.0, float(gap.max()) * 2))
    ax.grid(alpha=0.25, which="both")
    strip(ax)
    ax.set_xlabel("time [s]")
    ax.set_xlim(t[0], t[-1])
    m = result.metrics.get("nodes", {}).get(node, {})
    sub = (f"RMSE {m['rmse']:.2f} m (centralized {result.metrics['centralized']['rmse']:.2f} m), "
           f"mean position gap {m.get('mean_gap_position', m['mean_gap']):.2g} m, "
           f"final {m.get('final_gap_position', m['final_gap']):.2g} m") if m else ""
    fig.suptitle(title or f"{node}: estimated X and Y (red) vs the centralized EKF (black), ±3σ "
                 f"— URUS Figure 33 style\n{sub}", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
