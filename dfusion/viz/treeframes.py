"""The tree over time: a sequence of top-down frames of a run whose links change.

Each frame shows, at one time, where the nodes are (fixed nodes as squares, robots as
triangles pointing along their heading, their paths dotted), the person (the target's
true path so far, a star where it is), the links that exist then (thin grey: radio range
or wire) and the fusion tree the nodes agree on (thick, blue; the root of each tree epoch
ringed). Nodes without a place of their own (a wireless sensor network's node, wired to
its gateway) sit on a row under the site. The frames are taken at the start and right
after changes of the tree settled (:class:`dfusion.sim.links.DynamicLinks`), so that
consecutive frames show the tree before and after the robots re-attached
(``docs/dynamic-topology.md``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dfusion.viz.topdown import TRUTH_COLOR

__all__ = ["frame_times", "plot_tree_frames"]

TREE_COLOR = "tab:blue"
LINK_COLOR = "0.72"


def frame_times(result, count: int = 6) -> list[float]:
    """``count`` times: the start, then (spread over the run) times at which a change of the
    tree had just settled; the end when there are fewer changes."""
    dyn = result.links
    t_end = float(result.times[-1])
    if dyn is None:
        return [0.0, t_end]
    settled = [c.tree_settled for c in dyn.changes if c.tree_changed and c.tree_settled is not None]
    if len(settled) <= count - 1:
        picks = settled
    else:
        idx = np.linspace(0, len(settled) - 1, count - 1).round().astype(int)
        picks = [settled[i] for i in idx]
    times = [0.0] + [float(t) for t in picks]
    if len(times) < count:
        times.append(t_end)
    return sorted(set(times))


def _place(sc, names: list[str], t: float, site: tuple[float, float, float, float]) -> dict[str, np.ndarray]:
    """Where each node is drawn at ``t``: its position, or a slot on the row under the site."""
    xmin, xmax, ymin, _ = site
    out, homeless = {}, []
    for n in names:
        p = sc.nodes[n].position_at(t)
        if p is None:
            homeless.append(n)
        else:
            out[n] = np.asarray(p, float)[:2]
    for i, n in enumerate(homeless):
        out[n] = np.array([xmin + (i + 1) * (xmax - xmin) / (len(homeless) + 1), ymin - 0.12 * (site[3] - ymin)])
    return out


def plot_tree_frames(result, path: str | Path, *, times: list[float] | None = None, ncols: int = 3) -> Path:
    """Write the frames of a run whose links change (module docstring) as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc, dyn = result.scenario, result.links
    if dyn is None:
        raise ValueError("the tree frames need a run whose links change ([[events]] or radio ranges)")
    times = frame_times(result) if times is None else sorted(times)
    names = sorted(sc.nodes)
    hist_t = np.array([h[0] for h in dyn.history])
    # the site: every position the nodes and the target take
    pts = [result.truth[:, :2]]
    for n in names:
        spec = sc.nodes[n]
        if spec.path is not None:
            pts.append(np.array([spec.path.position(t) for t in result.times[::10]]))
        elif spec.position is not None:
            pts.append(np.asarray(spec.position, float)[None, :2])
    allp = np.vstack(pts)
    pad = 2.0
    site = (allp[:, 0].min() - pad, allp[:, 0].max() + pad, allp[:, 1].min() - pad, allp[:, 1].max() + pad)
    rows = math.ceil(len(times) / ncols)
    width = site[1] - site[0]
    height = (site[3] - site[2]) * 1.25
    fig, axes = plt.subplots(rows, ncols, figsize=(5.2 * ncols, 5.2 * rows * height / width * 1.15 + 1.0),
                             squeeze=False)
    for ax in axes.ravel()[len(times):]:
        ax.axis("off")
    for ax, t in zip(axes.ravel(), times):
        k = int(np.argmin(np.abs(result.times - t)))
        h = int(np.argmin(np.abs(hist_t - t)))
        tree = dyn.history[h][1]
        roots = dyn.roots[h][1] if h < len(dyn.roots) else set()
        where = _place(sc, names, t, site)
        for n in names:
            spec = sc.nodes[n]
            if spec.path is not None:
                xy = np.array([spec.path.position(tt) for tt in np.linspace(0, result.times[-1], 300)])
                ax.plot(xy[:, 0], xy[:, 1], ":", color="0.6", lw=0.8, zorder=1)
        for a, b in sorted(dyn.schedule.links(t)):
            if a in where and b in where:
                ax.plot(*zip(where[a], where[b]), color=LINK_COLOR, lw=1.0, zorder=2)
        for a, b in sorted(tree):
            ax.plot(*zip(where[a], where[b]), color=TREE_COLOR, lw=3.2, alpha=0.85, zorder=3)
        ax.plot(result.truth[: k + 1, 0], result.truth[: k + 1, 1], color=TRUTH_COLOR, lw=1.4, zorder=4)
        ax.plot(*result.truth[k, :2], marker="*", color=TRUTH_COLOR, ms=15, mec="k", mew=0.6, zorder=6)
        present = {n for n in names if sc.nodes[n].is_present(t)}
        for n in names:
            spec, p = sc.nodes[n], where[n]
            faded = n not in present
            if spec.path is not None:
                th = spec.path.heading(t)
                ax.plot(*p, marker=(3, 0, math.degrees(th) - 90), ms=13, color="tab:orange", mec="k", zorder=7,
                        alpha=0.3 if faded else 1.0)
            else:
                ax.plot(*p, marker="s", ms=9, color="white" if faded else "0.85", mec="k", zorder=7)
            if n in roots:
                ax.plot(*p, marker="o", ms=20, mfc="none", mec="tab:red", mew=1.6, zorder=8)
            # robots labelled below, fixed nodes above: a robot passing a fixed node stays readable
            ax.annotate(n, p, xytext=(6, -13) if spec.path is not None else (5, 6), textcoords="offset points",
                        fontsize=8.5, zorder=9, color="0.5" if faded else "k",
                        fontweight="bold" if spec.path is not None else "normal")
        n_changes = sum(1 for c in dyn.changes if c.t <= t + 1e-9 and c.tree_changed)
        ax.set_title(f"t = {t:.1f} s  ({n_changes} tree change{'' if n_changes == 1 else 's'} so far)", fontsize=10)
        ax.set_xlim(site[0], site[1])
        ax.set_ylim(site[2] - 0.2 * (site[3] - site[2]), site[3])
        ax.axhline(site[2], color="0.85", lw=0.6)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x [m]", fontsize=8)
        ax.set_ylabel("y [m]", fontsize=8)
    handles = [
        plt.Line2D([], [], color=TREE_COLOR, lw=3.2, label="fusion tree (agreed by both ends)"),
        plt.Line2D([], [], color=LINK_COLOR, lw=1.0, label="link that exists (radio range, wire)"),
        plt.Line2D([], [], marker="o", ms=10, mfc="none", mec="tab:red", ls="", label="root of a tree epoch"),
        plt.Line2D([], [], marker="s", ms=8, color="0.85", mec="k", ls="", label="fixed node (no place: row below)"),
        plt.Line2D([], [], marker="^", ms=9, color="tab:orange", mec="k", ls="", label="robot (dotted: its path)"),
        plt.Line2D([], [], marker="*", ms=12, color=TRUTH_COLOR, mec="k", ls="", label="person (line: path so far)"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8.5, frameon=False)
    fig.suptitle(f"{Path(sc.path).name}: the fusion tree as the robots move (seed {sc.seed})", fontsize=11)
    fig.tight_layout(rect=(0, 0.09, 1, 0.97))
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
