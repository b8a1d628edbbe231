r"""Figures of many targets: every track in its identity's colour, and who was given which identity when.

* :func:`identity_color`: one colour per network-wide identity, a function of the identity
  alone, so a track has the same colour in every node's panel, every figure and the MCAP
  recording. For ``TrackId(origin, serial)`` the hue is ``frac(u(origin) + serial phi)``
  with ``phi = (sqrt 5 - 1) / 2`` (the golden-ratio sequence: consecutive serials of a node
  get hues far apart, and no two serials of a node the same hue) and ``u(origin)`` the
  node name's CRC-32 over ``2^32`` (nodes start at different hues); saturation and value
  alternate with the serial (0.9 / 0.65 / 0.8, 0.9 / 0.7), so a colour is never grey (the
  truth) nor white (missed). Other identities (text) take the hue of their CRC-32.
* :func:`plot_tracks_topdown`: one panel per node: every person's true path (thin grey,
  with the name), every track's path in its identity's colour with its 3-sigma ellipse and
  identity at the track's last time; x and y in m.
* :func:`identity_timeline` / :func:`plot_identity_timeline`: per node, one row per true
  target; over the target's life a bar in the colour of the identity the node gave it (the
  CLEAR MOT matching of :func:`dfusion.metrics.clear_mot_matches`: a truth keeps its track
  while within the threshold, the rest by a minimum-distance assignment), white where no
  track is on it (missed), a change of colour is an identity switch (marked); below, the
  network label agreement over time (:func:`dfusion.metrics.label_agreement`, per frame).

The 3-sigma ellipse is :func:`dfusion.viz.topdown.ellipse_points`.
"""
from __future__ import annotations

import colorsys
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Hashable, Sequence

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.metrics import clear_mot_matches
from dfusion.tracking.history import TrackHistory, TruthPaths
from dfusion.tracking.track import TrackId
from dfusion.viz.topdown import ellipse_points

__all__ = ["identity_color", "IdentitySegment", "IdentityTimeline", "identity_timeline", "plot_tracks_topdown",
           "tracks_topdown_figure", "plot_identity_timeline", "identity_timeline_figure", "TRUTH_PATH_COLOR"]

#: Colour of the true paths in the many-target figures (thin grey).
TRUTH_PATH_COLOR = "0.55"
_PHI = (math.sqrt(5.0) - 1.0) / 2.0
_SATURATION = (0.9, 0.65, 0.8)
_VALUE = (0.9, 0.7)


def identity_color(track_id: Hashable) -> tuple[float, float, float]:
    """The RGB colour (0-1) of an identity (module docstring): stable, and a function of the identity alone."""
    if isinstance(track_id, TrackId):
        base, n = zlib.crc32(track_id.origin.encode()) / 2**32, int(track_id.serial)
    else:
        base, n = zlib.crc32(str(track_id).encode()) / 2**32, 0
    hue = (base + n * _PHI) % 1.0
    return colorsys.hsv_to_rgb(hue, _SATURATION[n % 3], _VALUE[n % 2])


# --- the identity timeline: data, then the drawing ---------------------------------------------------------------


@dataclass(frozen=True)
class IdentitySegment:
    """Target ``target`` carried identity ``track_id`` from ``t0`` to ``t1`` (s) without a break."""

    target: str
    t0: float
    t1: float
    track_id: Hashable


@dataclass
class IdentityTimeline:
    """What the identity timeline of one node draws: its rows, each target's life, the coloured segments."""

    node: str
    times: Array
    targets: list[str]
    lives: dict[str, tuple[float, float]]
    segments: list[IdentitySegment]

    def switch_times(self) -> list[tuple[str, float]]:
        """``(target, time)`` of every identity switch: a segment whose identity differs from
        the target's previous segment (after a gap too: a change of colour)."""
        out, last = [], {}
        for s in sorted(self.segments, key=lambda s: (s.target, s.t0)):
            if s.target in last and last[s.target] != s.track_id:
                out.append((s.target, s.t0))
            last[s.target] = s.track_id
        return out

    def switches(self) -> int:
        """The number of identity switches drawn (changes of colour along the rows)."""
        return len(self.switch_times())


def _frame_spans(times: Array) -> tuple[Array, Array]:
    """Each frame's span on the time axis: from the midpoint with the previous frame to the
    midpoint with the next (half the neighbouring step at the ends)."""
    t = np.asarray(times, float)
    if len(t) == 1:
        return t - 0.05, t + 0.05
    mid = 0.5 * (t[1:] + t[:-1])
    return np.r_[t[0] - (mid[0] - t[0]), mid], np.r_[mid, t[-1] + (t[-1] - mid[-1])]


def identity_timeline(history: TrackHistory, truth: TruthPaths, node: str, threshold: float = 1.0) -> IdentityTimeline:
    """The identity timeline of ``node`` over its record times (module docstring); a track is
    on a target when the CLEAR MOT matching within ``threshold`` (m) pairs them."""
    if node not in history.nodes:
        raise ValidationError(f"{node!r} has no tracks in the history (nodes: {sorted(history.nodes)})")
    times = history.times(node)
    frames = history.frames(node, truth, times)
    matches = clear_mot_matches(frames, threshold)
    lo, hi = _frame_spans(times)
    lives: dict[str, tuple[float, float]] = {}
    open_seg: dict[str, IdentitySegment] = {}
    segments: list[IdentitySegment] = []
    for k, (f, pairs) in enumerate(zip(frames, matches)):
        for g in f.truth_ids:
            a, b = lives.get(g, (lo[k], hi[k]))
            lives[g] = (min(a, lo[k]), max(b, hi[k]))
        now = {p.truth_id: p.track_id for p in pairs}
        for g in list(open_seg):
            s = open_seg[g]
            if now.get(g, _NO_TRACK) != s.track_id:
                segments.append(open_seg.pop(g))
            else:
                open_seg[g] = IdentitySegment(g, s.t0, float(hi[k]), s.track_id)
        for g, h in now.items():
            if g not in open_seg:
                open_seg[g] = IdentitySegment(g, float(lo[k]), float(hi[k]), h)
    segments.extend(open_seg.values())
    targets = sorted(lives, key=lambda g: (lives[g][0], g))
    return IdentityTimeline(node, times, targets, lives, sorted(segments, key=lambda s: (s.target, s.t0)))


_NO_TRACK = object()


def _label(track_id: Hashable) -> str:
    return str(track_id)


def plot_identity_timeline(history: TrackHistory, truth: TruthPaths, path: str | Path, *,
                           nodes: Sequence[str] | None = None, threshold: float = 1.0, title: str | None = None,
                           dpi: int = 100) -> tuple[Path, list[IdentityTimeline]]:
    """Draw the identity timeline of each node and the network label agreement over time to a PNG
    (:func:`identity_timeline_figure`). Returns the path and the timelines drawn."""
    fig, timelines = identity_timeline_figure(history, truth, nodes=nodes, threshold=threshold, title=title)
    return _save(fig, path, dpi), timelines


def identity_timeline_figure(history: TrackHistory, truth: TruthPaths, *, nodes: Sequence[str] | None = None,
                             threshold: float = 1.0, title: str | None = None) -> tuple[Any, list[IdentityTimeline]]:
    """The identity timeline figure (matplotlib, Agg): one panel per node (rows: true targets,
    bars: the :class:`IdentityTimeline` segments in their identity's colour, switches marked),
    and the network label agreement per frame below. Returns the figure and the timelines drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    names = list(history.nodes) if nodes is None else list(nodes)
    if not names:
        raise ValidationError("the identity timeline needs at least one node with tracks")
    timelines = [identity_timeline(history, truth, n, threshold) for n in names]
    heights = [max(len(tl.targets), 1) * 0.22 + 0.5 for tl in timelines] + [1.3]
    fig, axes = plt.subplots(len(names) + 1, 1, figsize=(11.5, sum(heights) + 1.2), sharex=True,
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    axes = axes[:, 0]
    t_all = history.times()
    t_lo, t_hi = (float(t_all[0]), float(t_all[-1])) if len(t_all) else (0.0, 1.0)
    for ax, tl in zip(axes, timelines):
        row = {g: i for i, g in enumerate(tl.targets)}
        ax.set_facecolor("0.92")
        for g, (a, b) in tl.lives.items():
            ax.broken_barh([(a, b - a)], (row[g] - 0.4, 0.8), facecolors="white", edgecolors="0.75", linewidth=0.4)
        span = max(t_hi - t_lo, 1e-9)
        for s in tl.segments:
            ax.broken_barh([(s.t0, s.t1 - s.t0)], (row[s.target] - 0.4, 0.8), facecolors=[identity_color(s.track_id)],
                           linewidth=0)
            if (s.t1 - s.t0) > 0.06 * span:
                ax.text(0.5 * (s.t0 + s.t1), row[s.target], _label(s.track_id), ha="center", va="center",
                        fontsize=6, color="k", clip_on=True)
        sw = tl.switch_times()
        if sw:
            ax.plot([t for _, t in sw], [row[g] + 0.42 for g, _ in sw], "v", color="k", ms=4, ls="none", zorder=5)
        ax.set_yticks(range(len(tl.targets)))
        ax.set_yticklabels(tl.targets, fontsize=6.5)
        ax.set_ylim(len(tl.targets) - 0.5, -0.5)
        ax.set_ylabel(f"{tl.node}:\ntrue target", fontsize=8)
        ax.set_title(f"{tl.node}: which identity it gave each true target ({tl.switches()} identity switches)",
                     fontsize=8.5, loc="left")
    ax = axes[-1]
    ts, la = history.label_agreement(truth, threshold, names)
    share = np.array([a / c if c else np.nan for a, c in la.per_frame], float)
    ax.plot(ts, share, color="k", lw=0.9)
    ax.set_ylim(-0.05, 1.08)
    ax.set_ylabel("label\nagreement", fontsize=8)
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)
    one = " (one node: 1 by definition)" if len(names) == 1 else ""
    overall = (f"overall {la.agreement:.3f} = {la.agreeing} / {la.compared} target-frames{one}" if la.compared
               else "no target tracked by every node at once: nothing compared")
    ax.set_title(f"network label agreement per frame (of the targets every node tracks, the share all give one "
                 f"identity): {overall}", fontsize=8.5, loc="left")
    ax.set_xlim(t_lo, t_hi)
    handles = [Patch(facecolor=identity_color(TrackId("node", 0)), label="a track's identity (one colour each)"),
               Patch(facecolor="white", edgecolor="0.6", label="missed: no track on the target"),
               Patch(facecolor="0.92", label="target not present"),
               Line2D([], [], marker="v", color="k", ls="none", ms=4, label="identity switch")]
    _title_and_legend(fig, title or f"identity timeline (a track is on a target within {threshold:g} m)", handles, 4)
    return fig, timelines


def _save(fig, path: str | Path, dpi: int) -> Path:
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _title_and_legend(fig, title: str, handles: list, ncol: int) -> None:
    """The title on top, the legend's row under it, then the axes (heights in inches)."""
    height = fig.get_figheight()
    title_h = 0.08 + 0.2 * (title.count("\n") + 1)
    legend_h = 0.22 * math.ceil(len(handles) / ncol)
    fig.suptitle(title, fontsize=10, y=1 - 0.05 / height, va="top")
    fig.legend(handles=handles, loc="upper center", ncol=ncol, fontsize=7.5, frameon=False,
               bbox_to_anchor=(0.5, 1 - title_h / height))
    fig.tight_layout(rect=(0, 0, 1, 1 - (title_h + legend_h) / height))


# --- the top-down view --------------------------------------------------------------------------------------------


def plot_tracks_topdown(history: TrackHistory, truth: TruthPaths | None, path: str | Path, *,
                        nodes: Sequence[str] | None = None, views: Sequence[Any] = (),
                        region: tuple[float, float, float, float] | None = None, title: str | None = None,
                        dpi: int = 100) -> Path:
    """Draw the top-down view of every node's tracks to a PNG (:func:`tracks_topdown_figure`)."""
    return _save(tracks_topdown_figure(history, truth, nodes=nodes, views=views, region=region, title=title), path, dpi)


def tracks_topdown_figure(history: TrackHistory, truth: TruthPaths | None, *, nodes: Sequence[str] | None = None,
                          views: Sequence[Any] = (), region: tuple[float, float, float, float] | None = None,
                          title: str | None = None) -> Any:
    """The top-down figure (matplotlib, Agg), one panel per node: the true paths (thin grey,
    named), every track's path in its identity's colour, its 3-sigma ellipse, estimate (+)
    and identity at the track's last time; ``views`` (objects with ``name, x0, x1, y0, y1``,
    e.g. :class:`~dfusion.sim.plaza.CameraView`) dashed, ``region = (x0, x1, y0, y1)`` outlined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    names = list(history.nodes) if nodes is None else list(nodes)
    if not names:
        raise ValidationError("the top-down view needs at least one node with tracks")
    ncol = min(len(names), 3)
    nrow = math.ceil(len(names) / ncol)
    w, h = (9.5, 7.6) if len(names) == 1 else (6.2, 5.0)          # inches per panel
    fig, axes = plt.subplots(nrow, ncol, figsize=(w * ncol, h * nrow + 0.8), squeeze=False)
    for i, node in enumerate(names):
        ax = axes[i // ncol][i % ncol]
        if region is not None:
            x0, x1, y0, y1 = region
            ax.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], color="k", lw=0.8)
        for v in views:
            ax.plot([v.x0, v.x1, v.x1, v.x0, v.x0], [v.y0, v.y0, v.y1, v.y1, v.y0], color="0.5", lw=0.7, ls="--")
            ax.text(v.x0 + 0.3, v.y1 - 0.3, v.name, fontsize=6.5, color="0.45", va="top")
        if truth is not None:
            for name, (_, xy) in truth.paths.items():
                ax.plot(xy[:, 0], xy[:, 1], color=TRUTH_PATH_COLOR, lw=0.7, zorder=2)
                ax.plot(xy[0, 0], xy[0, 1], "o", color=TRUTH_PATH_COLOR, ms=2.5, zorder=2)
                ax.annotate(name, xy[-1], xytext=(2, 2), textcoords="offset points", fontsize=5.5,
                            color="0.4", zorder=2, annotation_clip=True)
        paths = history.paths(node)
        for tid, (_, means, covs) in sorted(paths.items(), key=lambda kv: str(kv[0])):
            c = identity_color(tid)
            ax.plot(means[:, 0], means[:, 1], color=c, lw=1.2, zorder=3)
            e = ellipse_points(means[-1, :2], covs[-1, :2, :2])
            ax.plot(e[:, 0], e[:, 1], color=c, lw=1.0, zorder=4)
            ax.plot(means[-1, 0], means[-1, 1], "+", color=c, ms=6, mew=1.2, zorder=4)
            ax.annotate(_label(tid), means[-1, :2], xytext=(3, -8), textcoords="offset points", fontsize=6,
                        color=c, weight="bold", zorder=5, annotation_clip=True)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.grid(alpha=0.25)
        ax.set_title(f"{node}: {len(paths)} tracks", fontsize=9)
    for j in range(len(names), nrow * ncol):
        axes[j // ncol][j % ncol].axis("off")
    handles = [Line2D([], [], color=TRUTH_PATH_COLOR, lw=0.7, marker="o", ms=2.5,
                      label="true path (o start, name at the end)"),
               Line2D([], [], color=identity_color(TrackId("node", 0)), lw=1.2,
                      label="track (colour: its identity, the same in every panel)"),
               Line2D([], [], color=identity_color(TrackId("node", 1)), lw=1.0, marker="+", ms=6,
                      label="3σ ellipse and estimate at the track's last time")]
    _title_and_legend(fig, title or "tracks and truth, top-down", handles, 3 if ncol > 1 else 1)
    return fig
