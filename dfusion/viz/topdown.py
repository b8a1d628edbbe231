r"""The top-down figure: where things are, seen from above.

One picture of a run in the plane: the true path, each estimator's track with its
3-sigma ellipses at a few times (numbered markers on the truth mark the same times),
what the sensors see (camera footprints on the ground, WSN receivers, beacons,
landmarks, a map), the detections, and the fusion tree beside it (outages written on
their links). :class:`Scene` holds the things to draw; :func:`scene_of_result` builds it
for a scenario run, the real-data examples build their own (MRCLAM: robots and
landmarks; CARMEN: the map and the localizers; BLE: the floor plan and the receivers).

The 3-sigma ellipse of a 2x2 position covariance ``P`` is
``{m + 3 L u : |u| = 1}`` with ``P = L L^T`` (Cholesky): the points at Mahalanobis
distance 3, which hold 98.9 % of a 2-D Gaussian (chi-square with 2 degrees of freedom:
``1 - exp(-9/2)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Track", "Scene", "draw_scene", "scene_of_result", "plot_topdown", "ellipse_points", "camera_footprint",
           "sensor_points", "detection_point", "TRUTH_COLOR"]

#: Colour of the truth in every figure.
TRUTH_COLOR = "tab:green"
_COLORS = ["tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan", "tab:olive", "tab:red",
           "tab:gray", "navy"]


def ellipse_points(mean: np.ndarray, cov: np.ndarray, nsig: float = 3.0, n: int = 64) -> np.ndarray:
    """``(n + 1, 2)`` points of the ``nsig``-sigma ellipse of a 2-D Gaussian (closed)."""
    P = 0.5 * (np.asarray(cov, float)[:2, :2] + np.asarray(cov, float)[:2, :2].T)
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(P)
        L = V @ np.diag(np.sqrt(np.maximum(w, 0.0)))
    a = np.linspace(0.0, 2 * math.pi, n + 1)
    return np.asarray(mean, float)[:2] + nsig * (L @ np.vstack([np.cos(a), np.sin(a)])).T


@dataclass
class Track:
    """An estimator's positions over time (``mean`` (K, 2), ``cov`` (K, 2, 2) or None)."""

    name: str
    t: np.ndarray
    mean: np.ndarray
    cov: np.ndarray | None = None
    color: str | None = None
    style: str = "-"
    width: float = 1.0


@dataclass
class Scene:
    """What :func:`draw_scene` draws (every field optional except the title).

    ``truth``: name -> ``(t, xy)``; ``points``: label -> ``(xy, marker, colour)``
    (receivers, landmarks, beacons); ``polygons``: label -> ``(xy, colour)`` (camera
    footprints); ``detections``: label -> ``xy``; ``grid``: an occupancy grid or
    ``(image, extent)`` (a floor plan); ``tree``: ``(nodes, edges)`` with ``outages``
    ``(a, b, t0, t1)``; ``ellipse_times``: the times of the ellipses (default: four
    spread over the run, the first after the start-up).
    """

    title: str
    truth: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    tracks: list[Track] = field(default_factory=list)
    points: dict[str, tuple[np.ndarray, str, str]] = field(default_factory=dict)
    polygons: dict[str, tuple[np.ndarray, str]] = field(default_factory=dict)
    detections: dict[str, np.ndarray] = field(default_factory=dict)
    grid: Any = None
    tree: tuple[list[str], list[tuple[str, str]]] | None = None
    outages: list[tuple[str, str, float, float]] = field(default_factory=list)
    ellipse_times: list[float] | None = None
    node_colors: dict[str, str] = field(default_factory=dict)
    note: str = ""
    #: Colours of the truths after the first (default: the truth's green).
    truth_colors: dict[str, str] = field(default_factory=dict)
    #: Small text labels ``(xy, text)`` (landmark numbers, ...).
    labels: list[tuple[np.ndarray, str]] = field(default_factory=list)
    #: How a time is written in the titles (``"scan {:.0f}"`` where times are indices).
    time_format: str = "t = {:.1f} s"


def camera_footprint(sensor: Any, n: int = 16) -> np.ndarray | None:
    """The ground polygon a camera sees (its image border back-projected onto the ground
    plane, :meth:`~dfusion.models.PinholeCamera.ground_point`), or None when no border
    ray hits the ground. Border pixels whose rays miss the ground are left out."""
    if not all(hasattr(sensor, a) for a in ("ground_point", "width", "height")):
        return None
    w, h = float(sensor.width), float(sensor.height)
    s = np.linspace(0.0, 1.0, n, endpoint=False)
    border = np.concatenate([np.column_stack([s * w, np.zeros(n)]), np.column_stack([np.full(n, w), s * h]),
                             np.column_stack([w - s * w, np.full(n, h)]), np.column_stack([np.zeros(n), h - s * h])])
    pts = []
    for px in border:
        try:
            pts.append(sensor.ground_point(px))
        except Exception:   # the ray misses the ground (above the horizon)
            continue
    if len(pts) < 3:
        return None
    return np.array(pts)


def sensor_points(sensor: Any) -> np.ndarray | None:
    """Fixed positions a sensor has: WSN receivers, a beacon, a camera's position."""
    for attr in ("receivers", "beacon", "anchor", "position"):
        v = getattr(sensor, attr, None)
        if v is not None:
            a = np.asarray(v, float)
            if a.size >= 2:
                return a.reshape(-1, a.shape[-1])[:, :2]
    return None


def detection_point(sensor: Any, z: np.ndarray) -> np.ndarray | None:
    """Where a measurement puts the target on the ground, when it says so directly: a
    camera's pixel back-projected, a position fix itself; None otherwise (RSSI, ranges)."""
    z = np.asarray(z, float)
    if hasattr(sensor, "ground_point") and z.size == 2:
        try:
            return np.asarray(sensor.ground_point(z), float)
        except Exception:
            return None
    if type(sensor).__name__ == "PositionSensor" and z.size >= 2:
        return z[:2]
    return None


def _default_times(scene: Scene) -> list[float]:
    ts = [tr.t for tr in scene.tracks if tr.cov is not None and len(tr.t)]
    if not ts:
        return []
    t0, t1 = min(float(t[0]) for t in ts), max(float(t[-1]) for t in ts)
    return [t0 + f * (t1 - t0) for f in (0.25, 0.5, 0.75, 1.0)]


def _nearest(t: np.ndarray, tq: float) -> int:
    return int(np.clip(np.searchsorted(t, tq), 0, len(t) - 1))


def _draw_layers(ax, scene: Scene, times: list[float], main: bool) -> list[Any]:
    """Draw every layer of ``scene`` on ``ax``; returns the legend handles."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles: list[Any] = []
    # background: map or floor plan
    if scene.grid is not None:
        if isinstance(scene.grid, tuple):
            img, extent = scene.grid
            ax.imshow(img, extent=extent, origin="lower", cmap="Greys", alpha=0.45, zorder=0)
            handles.append(Patch(facecolor="0.6", label="floor plan (walls dark)"))
        else:
            g = scene.grid
            occ = g.occupied.astype(float)
            if g.origin[2] == 0.0:
                ext = [g.origin[0], g.origin[0] + g.width * g.resolution, g.origin[1],
                       g.origin[1] + g.height * g.resolution]
                ax.imshow(np.ma.masked_where(occ == 0, occ), extent=ext, origin="lower", cmap="Greys", vmin=0,
                          vmax=1.8, interpolation="nearest", zorder=0)
            else:
                p = g.occupied_points(boundary_only=False)
                ax.plot(p[:, 0], p[:, 1], ",", color="0.4", zorder=0)
            handles.append(Patch(facecolor="0.55", label=f"map: occupied cells ({g.resolution:g} m)"))
    for label, (poly, color) in scene.polygons.items():
        ax.fill(poly[:, 0], poly[:, 1], color=color, alpha=0.12, lw=0, zorder=1)
        ax.plot(np.r_[poly[:, 0], poly[:1, 0]], np.r_[poly[:, 1], poly[:1, 1]], color=color, lw=0.8, ls="--", zorder=1)
        handles.append(Patch(facecolor=color, alpha=0.25, edgecolor=color, ls="--", label=label))
    for label, (xy, marker, color) in scene.points.items():
        xy = np.asarray(xy, float).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], marker, color=color, ms=6, mec="k", mew=0.5, ls="none", zorder=4)
        handles.append(Line2D([], [], marker=marker, color=color, mec="k", mew=0.5, ls="none", label=label))
    for xy, text in scene.labels:
        ax.annotate(text, np.asarray(xy, float)[:2], xytext=(4, -9), textcoords="offset points", fontsize=7,
                    color="0.25", zorder=6, annotation_clip=True)
    for label, xy in scene.detections.items():
        xy = np.asarray(xy, float).reshape(-1, 2)
        if xy.size:
            color = scene.node_colors.get(label.split(" ")[0], "0.3")
            ax.plot(xy[:, 0], xy[:, 1], ".", color=color, ms=3.5, alpha=0.5, zorder=2)
            handles.append(Line2D([], [], marker=".", color=color, ls="none", alpha=0.6, label=label))
    for k, (name, (t, xy)) in enumerate(scene.truth.items()):
        xy = np.asarray(xy, float)
        tc = scene.truth_colors.get(name, TRUTH_COLOR)
        ax.plot(xy[:, 0], xy[:, 1], color=tc, lw=2.0 if k == 0 else 0.8, alpha=0.75 if k == 0 else 0.4, zorder=3,
                ls="-" if k == 0 else (0, (4, 2)))
        ax.plot(xy[0, 0], xy[0, 1], "o", color=tc, ms=5, zorder=5)
        if k == 0 and main:
            for i, tq in enumerate(times, 1):
                j = _nearest(np.asarray(t), tq)
                ax.annotate(str(i), xy[j], xytext=(5, 5), textcoords="offset points", fontsize=8, weight="bold",
                            color="darkgreen", zorder=6)
                ax.plot(xy[j, 0], xy[j, 1], "s", color=TRUTH_COLOR, ms=4, zorder=6)
        handles.append(Line2D([], [], color=tc, lw=2.0 if k == 0 else 1.0, ls="-" if k == 0 else (0, (4, 2)),
                              label=f"truth: {name} (o start" + (", squares 1-n: ellipse times)" if k == 0 else ")")))
    for i, tr in enumerate(scene.tracks):
        color = tr.color or scene.node_colors.get(tr.name) or _COLORS[i % len(_COLORS)]
        m = np.asarray(tr.mean, float)
        ax.plot(m[:, 0], m[:, 1], color=color, lw=tr.width, ls=tr.style, alpha=0.85, zorder=4)
        label = tr.name
        if tr.cov is not None:
            for tq in times:
                j = _nearest(np.asarray(tr.t), tq)
                e = ellipse_points(m[j], tr.cov[j])
                ax.plot(e[:, 0], e[:, 1], color=color, lw=1.0, ls=tr.style, zorder=5)
                ax.plot(m[j, 0], m[j, 1], "+", color=color, ms=7, mew=1.3, zorder=5)
            label += " (+: estimate, ring: 3σ)"
        handles.append(Line2D([], [], color=color, lw=max(tr.width, 1.0), ls=tr.style, label=label))
    return handles


def finite_rows(*arrays: np.ndarray | None) -> np.ndarray:
    """Rows (along the first axis) where every given array is finite: an estimate before
    its node's first one, or an unknown truth, is NaN and is not drawn."""
    ok = None
    for a in arrays:
        if a is None:
            continue
        a = np.asarray(a, float)
        f = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        ok = f if ok is None else ok & f
    return ok


def _finite_scene(scene: Scene) -> Scene:
    """``scene`` without NaN rows in its truths and tracks (and without those left empty)."""
    from dataclasses import replace

    truth = {}
    for name, (t, xy) in scene.truth.items():
        ok = finite_rows(xy)
        if ok.any():
            truth[name] = (np.asarray(t)[ok], np.asarray(xy, float)[ok])
    tracks = []
    for tr in scene.tracks:
        ok = finite_rows(tr.mean, tr.cov)
        if ok.any():
            tracks.append(replace(tr, t=np.asarray(tr.t)[ok], mean=np.asarray(tr.mean, float)[ok],
                                  cov=None if tr.cov is None else np.asarray(tr.cov, float)[ok]))
    return replace(scene, truth=truth, tracks=tracks)


def draw_scene(scene: Scene, path: str | Path, *, figsize: tuple[float, float] = (13.5, 9.5),
               zoom: tuple[float, float, float, float] | None = None, zooms: bool = True) -> Path:
    """Draw ``scene`` to a PNG: the plane in metres (equal axes), below it one close-up
    per ellipse time (centred on the truth then, wide enough for every ellipse: on a
    long path the ellipses are too small to read in the whole view), on the right the
    tree and the legend. ``zoom = (xmin, xmax, ymin, ymax)`` limits the main panel.
    NaN rows (no estimate yet, unknown truth) are left out; without a truth there are
    no close-ups."""
    import matplotlib

    scene = _finite_scene(scene)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_tree = scene.tree is not None and len(scene.tree[0]) > 1
    times = scene.ellipse_times if scene.ellipse_times is not None else _default_times(scene)
    first_truth = next(iter(scene.truth.values()), None)
    zooms = zooms and bool(times) and first_truth is not None
    fig = plt.figure(figsize=figsize)
    gs = fig.add_gridspec(3, 2, width_ratios=[2.6, 1.0], height_ratios=[1.0, 1.25, 0.75 if zooms else 0.001],
                          wspace=0.06, hspace=0.25)
    ax = fig.add_subplot(gs[0:2, 0])
    handles = _draw_layers(ax, scene, times, True)
    ax.set_aspect("equal", adjustable="datalim")
    if zoom is not None:
        ax.set_xlim(zoom[0], zoom[1])
        ax.set_ylim(zoom[2], zoom[3])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.25)
    if times:
        t_txt = ", ".join(f"{i}: " + scene.time_format.format(t) for i, t in enumerate(times, 1))
        ax.set_title(f"3σ ellipses at {t_txt}" + (" (close-ups below)" if zooms else ""), fontsize=8.5)
    if zooms:
        sub = gs[2, 0].subgridspec(1, len(times), wspace=0.25)
        tt, txy = first_truth
        for i, tq in enumerate(times):
            zax = fig.add_subplot(sub[0, i])
            _draw_layers(zax, scene, times, False)
            c = np.asarray(txy, float)[_nearest(np.asarray(tt), tq)]
            half = 0.25
            for tr in scene.tracks:
                if tr.cov is None:   # the close-ups are for the ellipses
                    continue
                k = _nearest(np.asarray(tr.t), tq)
                m = np.asarray(tr.mean, float)[k]
                ext = np.abs(m - c).max()
                if tr.cov is not None:
                    ext += 3 * math.sqrt(max(np.linalg.eigvalsh(np.asarray(tr.cov[k])[:2, :2]).max(), 0.0))
                half = max(half, 1.15 * ext)
            zax.set_xlim(c[0] - half, c[0] + half)
            zax.set_ylim(c[1] - half, c[1] + half)
            zax.set_aspect("equal", adjustable="box")
            zax.set_title(f"{i + 1}: " + scene.time_format.format(tq), fontsize=8)
            zax.tick_params(labelsize=7)
            zax.grid(alpha=0.25)
            if i == 0:
                zax.set_ylabel("y [m]", fontsize=8)
            zax.set_xlabel("x [m]", fontsize=8)
    lax = fig.add_subplot(gs[1:, 1])
    lax.axis("off")
    lax.legend(handles=handles, loc="upper left", ncol=1, fontsize=7.5, frameon=False, borderaxespad=0.0)
    if has_tree:
        _draw_tree(fig.add_subplot(gs[0, 1]), scene)
    fig.suptitle(scene.title + (f"\n{scene.note}" if scene.note else ""), fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def _draw_tree(ax, scene: Scene) -> None:
    import networkx as nx

    nodes, edges = scene.tree
    g = nx.Graph()
    g.add_nodes_from(nodes)
    g.add_edges_from(edges)
    root = max(nodes, key=lambda n: g.degree[n])
    pos = _tree_layout(g, root)
    down = {}
    for a, b, t0, t1 in scene.outages:
        down.setdefault(frozenset((a, b)), []).append((t0, t1))
    for a, b in g.edges:
        (x0, y0), (x1, y1) = pos[a], pos[b]
        out = down.get(frozenset((a, b)))
        ax.plot([x0, x1], [y0, y1], color="tab:red" if out else "0.4", lw=1.5, ls="--" if out else "-", zorder=1)
        if out:
            txt = "down " + ", ".join(f"{t0:g}-{t1:g} s" for t0, t1 in out)
            ax.text(0.5 * (x0 + x1), 0.5 * (y0 + y1), txt, fontsize=7, color="tab:red", ha="center", va="bottom",
                    rotation=0, zorder=3, bbox=dict(fc="white", ec="none", alpha=0.8, pad=0.5))
    for n in g.nodes:
        x, y = pos[n]
        ax.plot(x, y, "o", ms=14, color=scene.node_colors.get(n, "0.8"), mec="k", zorder=2)
        ax.text(x, y - 0.09, n, ha="center", va="top", fontsize=7.5, zorder=3, rotation=30 if len(g) > 3 else 0,
                rotation_mode="anchor")
    ax.set_title("fusion tree (links; red dashed: outages)", fontsize=8.5)
    ax.set_xlim(-0.05, 1.05)
    ax.set_ylim(-0.35, 1.12)
    ax.axis("off")


def _tree_layout(g, root: str) -> dict[str, tuple[float, float]]:
    """Layered layout: the root on top, each depth one row, leaves spread evenly."""
    import networkx as nx

    depth = nx.single_source_shortest_path_length(g, root)
    rows: dict[int, list[str]] = {}
    for n in nx.dfs_preorder_nodes(g, root):
        rows.setdefault(depth[n], []).append(n)
    dmax = max(rows) if rows else 0
    pos = {}
    for d, ns in rows.items():
        for i, n in enumerate(ns):
            pos[n] = ((i + 1) / (len(ns) + 1), 1.0 - (d / dmax if dmax else 0.0))
    return pos


def scene_of_result(result, *, times: list[float] | None = None) -> Scene:
    """The :class:`Scene` of a scenario run (:class:`~dfusion.sim.runner.SimulationResult`):
    truth, every node's track with its 3-sigma ellipses, the centralized EKF (black,
    dashed), camera footprints, receivers and beacons, the detections a camera or
    position sensor made (clutter grey), and the tree with its outages."""
    sc = result.scenario
    names = sorted(result.node_mean)
    colors = {n: _COLORS[i % len(_COLORS)] for i, n in enumerate(names)}
    t = result.times
    sig = np.sqrt(np.maximum(result.central_cov[:, 0, 0], 0.0))
    settled = t[np.argmax(sig < 2 * np.median(sig[len(sig) // 2:]))] if len(t) > 3 else t[0]
    if times is None:
        times = [float(settled + f * (t[-1] - settled)) for f in (0.1, 0.4, 0.7, 1.0)]
    scene = Scene(title=f"{Path(sc.path).name}: top-down view (seed {sc.seed})", ellipse_times=times,
                  node_colors=colors)
    if finite_rows(result.truth[:, :2]).any():
        scene.truth["target"] = (t, result.truth[:, :2])
    for n in names:
        scene.tracks.append(Track(n, t, result.node_mean[n][:, :2], result.node_cov[n][:, :2, :2], colors[n]))
    scene.tracks.append(Track("centralized EKF", t, result.central_mean[:, :2], result.central_cov[:, :2, :2], "k",
                              style="--", width=0.8))
    for n in names:
        spec = sc.nodes[n]
        sensor = spec.sensor
        if sensor is None:
            continue
        fp = camera_footprint(sensor)
        if fp is not None:
            scene.polygons[f"{n} camera footprint (ground it sees)"] = (fp, colors[n])
        pts = sensor_points(sensor)
        if pts is not None:
            kind = "receivers" if getattr(sensor, "receivers", None) is not None else (
                "camera" if fp is not None else "sensor")
            marker = {"receivers": "^", "camera": "s"}.get(kind, "D")
            scene.points[f"{n} {kind}"] = (pts, marker, colors[n])
        det, clut = [], []
        for m in result.world.measurements:
            if m.node != n:
                continue
            p = detection_point(sensor, m.z)
            if p is not None:
                (clut if m.clutter else det).append(p)
        if det:
            scene.detections[f"{n} detections (on the ground)"] = np.array(det)
        if clut:
            scene.detections["false detections (clutter)"] = np.array(clut)
    scene.tree = (names, [tuple(e) for e in sc.graph.edges])
    scene.outages = list(sc.outages())
    m = result.metrics.get("nodes", {})
    if m and not scene.truth:
        scene.note = "no truth: RMSE unknown"
    elif m:
        scene.note = "RMSE " + ", ".join(f"{n} {v['rmse']:.2f} m" for n, v in m.items()) + \
            f"; centralized {result.metrics['centralized']['rmse']:.2f} m"
    return scene


def plot_topdown(result, path: str | Path, *, times: list[float] | None = None) -> Path:
    """The top-down figure of a scenario run (:func:`scene_of_result`, :func:`draw_scene`)."""
    return draw_scene(scene_of_result(result, times=times), path)
