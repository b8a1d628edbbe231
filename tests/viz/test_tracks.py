"""Many-target figures and recording: identity colours, the identity timeline (its switches
against motmetrics, an independent reference), the top-down view and the timeline as PNG
with units on the axes, and every track in the MCAP recording, read back with the ``mcap``
library's reader and Foxglove's published protobuf types."""
from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from dfusion.tracking import TrackHistory, TrackId, TruthPaths
from dfusion.viz.foxglove import record_tracks_mcap
from dfusion.viz.tracks import (identity_color, identity_timeline_figure, plot_identity_timeline, plot_tracks_topdown,
                                tracks_topdown_figure)

ROOT = Path(__file__).resolve().parents[2]
THRESHOLD = 1.0


def synthetic_run(seed: int = 0, nodes=("cam1", "cam2"), frames: int = 80):
    """Four people walking; each node tracks them with noise, misses, a false track, new
    identities at random times and swaps of two identities (so that there are switches)."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    times = np.round(dt * np.arange(1, frames + 1), 9)
    paths = {}
    for i in range(4):
        a, b = (0, frames) if i < 3 else (frames // 4, 3 * frames // 4)   # person 3 is born late, dies early
        p0, v = rng.uniform(0, 10, 2), rng.uniform(-1, 1, 2)
        xy = p0 + np.cumsum(np.tile(v * dt, (b - a, 1)) + rng.normal(0, 0.02, (b - a, 2)), axis=0)
        paths[f"person {i}"] = (times[a:b], xy)
    truth = TruthPaths(paths)
    history = TrackHistory()
    for node in nodes:
        serial = itertools.count()
        label = {g: TrackId(node, next(serial)) for g in paths}
        for k, t in enumerate(times):
            names, pos = truth.at(float(t))
            if rng.uniform() < 0.08:                              # a new identity for one person
                label[names[int(rng.integers(len(names)))]] = TrackId(node, next(serial))
            if rng.uniform() < 0.05 and len(names) >= 2:          # two tracks swap their people
                g, h = (names[int(i)] for i in rng.choice(len(names), 2, replace=False))
                label[g], label[h] = label[h], label[g]
            rows = []
            for g, p in zip(names, pos):
                if rng.uniform() < 0.15:                          # missed
                    continue
                m = np.r_[p + rng.normal(0, 0.2, 2), 0.0, 0.0]
                rows.append((label[g], m, np.diag([0.04, 0.05, 0.3, 0.3])))
            if k % 7 == 0:                                        # a false track far from everyone
                rows.append((TrackId(node, 1000 + k), np.array([50.0, 50.0, 0, 0]), np.eye(4)))
            history.record(node, float(t), rows)
    return history, truth


def test_identity_colour_is_stable_and_distinct():
    ids = [TrackId(o, s) for o in ("cam1", "cam2", "cam3", "cam4", "cam5", "cam6", "central") for s in range(40)]
    colours = [identity_color(i) for i in ids]
    assert len(set(colours)) == len(ids)                          # distinct identities, distinct colours
    assert identity_color(TrackId("cam1", 3)) == colours[3]       # a new object with the same identity
    for c in colours:                                             # never grey (the truth) nor white (missed)
        assert max(c) - min(c) >= 0.2 and min(c) < 0.95
    one_node = np.array(colours[:20])                             # one node's first 20 tracks: far apart
    assert min(np.linalg.norm(a - b) for a, b in itertools.combinations(one_node, 2)) >= 0.15
    # stable across processes (no salted hash): the same colours under another PYTHONHASHSEED
    code = ("from dfusion.tracking import TrackId; from dfusion.viz.tracks import identity_color; "
            "print([identity_color(TrackId(o, s)) for o in ('cam1', 'central') for s in range(5)])")
    env = {**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip() == str([identity_color(TrackId(o, s)) for o in ("cam1", "central") for s in range(5)])


def test_timeline_switches_equal_motmetrics():
    import matplotlib.pyplot as plt
    import motmetrics as mm          # the independent reference (in the test extra)

    history, truth = synthetic_run()
    fig, timelines = identity_timeline_figure(history, truth, threshold=THRESHOLD)
    for ax, tl in zip(fig.axes, timelines):
        # what is drawn: one bar per target's life and one per segment
        assert len(ax.collections) == len(tl.lives) + len(tl.segments)
        acc = mm.MOTAccumulator(auto_id=True)
        number: dict = defaultdict(lambda: len(number))            # motmetrics takes numeric ids
        for f in history.frames(tl.node, truth):
            X, Y = np.asarray(f.truth).reshape(-1, 2), np.asarray(f.tracks).reshape(-1, 2)
            D = np.linalg.norm(X[:, None] - Y[None], axis=2) if len(X) and len(Y) else np.zeros((len(X), len(Y)))
            acc.update([number[g] for g in f.truth_ids], [number[h] for h in f.track_ids],
                       np.where(D <= THRESHOLD, D, np.nan))
        ref = mm.metrics.create().compute(acc, metrics=["num_switches"], name=tl.node).iloc[0]
        assert tl.switches() == ref.num_switches
        assert tl.switches() >= 3                                 # the data has switches to count
    plt.close(fig)


def test_figures_render_with_units(tmp_path):
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    history, truth = synthetic_run(frames=40)
    fig = tracks_topdown_figure(history, truth, region=(0.0, 12.0, 0.0, 12.0))
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.axison]
    assert len(panels) == 2
    assert all(ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]" for ax in panels)
    plt.close(fig)
    fig, _ = identity_timeline_figure(history, truth)
    assert fig.axes[-1].get_xlabel() == "time [s]"
    plt.close(fig)
    for path in (plot_tracks_topdown(history, truth, tmp_path / "topdown.png"),
                 plot_identity_timeline(history, truth, tmp_path / "timeline.png")[0]):
        img = mpimg.imread(path)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400


def test_mcap_carries_every_track(tmp_path):
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader

    history, truth = synthetic_run(frames=30)
    path = record_tracks_mcap(history, tmp_path / "tracks.mcap", truth)
    topics = defaultdict(list)
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if schema.name == "foxglove.SceneUpdate":
                topics[channel.topic].append((message.log_time, SceneUpdate.FromString(message.data)))
            else:
                assert schema.name == "dfusion/Tracks" and channel.message_encoding == "json"
                topics[channel.topic].append((message.log_time, json.loads(message.data)))
    for node, series in history.nodes.items():
        scenes, data = topics[f"/nodes/{node}/tracks"], topics[f"/nodes/{node}/track_estimates"]
        assert len(scenes) == len(data) == len(series)           # one message per node per time
        before: set[str] = set()
        for (t, rows), (lt, scene), (lt2, est) in zip(series, scenes, data):
            assert lt == lt2 == round(t * 1e9)
            ids = {f"track/{node}/{tid}" for tid, _, _ in rows}
            assert {e.id for e in scene.entities} == ids
            assert {d.id for d in scene.deletions} == before - ids    # a track gone is deleted
            before = ids
            by_id = {str(tid): (tid, m, P) for tid, m, P in rows}
            assert [d["id"] for d in est["tracks"]] == [str(tid) for tid, _, _ in rows]
            for d in est["tracks"]:
                tid, m, P = by_id[d["id"]]
                assert (d["origin"], d["serial"]) == (tid.origin, tid.serial)
                np.testing.assert_array_equal(d["mean"], m)
                np.testing.assert_array_equal(np.reshape(d["covariance"], P.shape), P)
            for e in scene.entities:
                tid, m, _ = by_id[e.id.split("/", 2)[2]]
                s = e.spheres[0]
                assert (s.pose.position.x, s.pose.position.y) == (m[0], m[1])
                assert (s.color.r, s.color.g, s.color.b) == pytest.approx(identity_color(tid))
    truth_msgs = topics["/truth/targets"]
    assert len(truth_msgs) == len(history.times())
    for (lt, scene) in truth_msgs:
        names, pos = truth.at(lt / 1e9)
        assert {e.id for e in scene.entities} == {f"truth/{n}" for n in names}
