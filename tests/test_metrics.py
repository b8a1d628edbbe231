"""Multi-target metrics (dfusion.metrics): GOSPA against a brute-force search over every partial
assignment, CLEAR MOT / IDF1 against a hand-computed example and against motmetrics, label agreement
against a hand-computed example."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from dfusion.metrics import TrackingFrame, gospa, identity_metrics, label_agreement


def gospa_brute(X, Y, c, p):
    """min over partial assignments gamma (pairs closer than c) of sum d^p + c^p/2 (|X| + |Y| - 2|gamma|)."""
    n, m = len(X), len(Y)
    best = None
    for perm in itertools.permutations(list(range(m)) + [None] * n, n):
        pairs = [(i, j) for i, j in enumerate(perm) if j is not None and np.linalg.norm(X[i] - Y[j]) < c]
        loc = sum(np.linalg.norm(X[i] - Y[j]) ** p for i, j in pairs)
        total = loc + c**p / 2 * (n + m - 2 * len(pairs))
        if best is None or total < best[0] - 1e-12:
            best = (total, loc, n - len(pairs), m - len(pairs))
    return best


@pytest.mark.parametrize("seed", range(20))
def test_gospa_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(0, 5)), int(rng.integers(0, 5))
    X, Y = rng.uniform(0, 4, (n, 2)), rng.uniform(0, 4, (m, 2))
    c, p = float(rng.choice([1.0, 2.0, 3.0])), float(rng.choice([1.0, 2.0]))
    g = gospa(X, Y, c, p)
    total, loc, missed, false = gospa_brute(X, Y, c, p)
    assert g.distance == pytest.approx(total ** (1 / p), abs=1e-12)
    assert g.localization == pytest.approx(loc, abs=1e-12)
    assert (g.n_missed, g.n_false) == (missed, false)
    assert g.missed == pytest.approx(c**p / 2 * missed) and g.false == pytest.approx(c**p / 2 * false)


def test_gospa_edge_cases():
    assert gospa(np.zeros((0, 2)), np.zeros((0, 2))).distance == 0.0
    assert gospa(np.zeros((3, 2)), np.zeros((0, 2)), c=2.0, p=1).distance == pytest.approx(3.0)   # 3 missed, c/2 each
    assert gospa([[0.0, 0.0]], [[5.0, 0.0]], c=2.0, p=2).distance == pytest.approx(2.0)          # sqrt(2 + 2)
    with pytest.raises(ValueError, match="p >= 1"):
        gospa([[0.0, 0.0]], [[0.0, 0.0]], p=0.5)


def hand_frames():
    A, B = [0.0, 0.0], [10.0, 0.0]
    return [
        TrackingFrame(["A", "B"], [A, B], [1, 2], [[0.1, 0.0], [10.0, 0.1]]),   # A-1, B-2
        TrackingFrame(["A", "B"], [A, B], [2], [[10.0, 0.0]]),                  # A missed
        TrackingFrame(["A", "B"], [A, B], [3, 2], [[0.0, 0.2], [10.0, 0.0]]),   # a switch
        TrackingFrame(["A", "B"], [A, B], [3, 2, 4], [A, B, [5.0, 5.0]]),       # 4 is a false positive
    ]


def test_identity_metrics_of_a_hand_computed_example():
    m = identity_metrics(hand_frames(), threshold=1.0)
    # 8 truths, 8 tracks; 7 matches, 1 miss, 1 false positive, 1 switch: MOTA = 1 - 3/8
    assert (m.truth_count, m.track_count, m.matches, m.misses, m.false_positives, m.switches) == (8, 8, 7, 1, 1, 1)
    assert m.mota == pytest.approx(0.625)
    assert m.motp == pytest.approx(0.4 / 7)
    # IDF1: A-3 share 2 frames, B-2 share 4 (A-1 only 1): IDTP = 6, IDF1 = 12 / 16
    assert m.idf1 == pytest.approx(0.75)


def test_identity_metrics_agree_with_motmetrics():
    import motmetrics as mm          # the independent reference (in the test extra)

    rng = np.random.default_rng(0)
    switched = 0
    for _ in range(40):
        frames, acc = [], mm.MOTAccumulator(auto_id=True)
        G, H = int(rng.integers(1, 6)), int(rng.integers(1, 7))
        gp, hp = rng.uniform(0, 5, (G, 2)), rng.uniform(0, 5, (H, 2))
        for _k in range(int(rng.integers(3, 15))):
            gp += rng.normal(0, 0.3, gp.shape)
            hp += rng.normal(0, 0.3, hp.shape)
            gm, hm = rng.uniform(size=G) < 0.8, rng.uniform(size=H) < 0.8
            gids, hids = [int(i) for i in np.flatnonzero(gm)], [100 + int(i) for i in np.flatnonzero(hm)]
            X, Y = gp[gm], hp[hm]
            frames.append(TrackingFrame(gids, X, hids, Y))
            D = np.linalg.norm(X[:, None] - Y[None], axis=2) if len(X) and len(Y) else np.zeros((len(X), len(Y)))
            acc.update(gids, hids, np.where(D <= 1.5, D, np.nan))
        ours = identity_metrics(frames, 1.5)
        ref = mm.metrics.create().compute(acc, metrics=["mota", "idf1", "num_switches", "num_misses",
                                                        "num_false_positives"], name="x").iloc[0]
        assert ours.mota == pytest.approx(ref.mota)
        assert ours.idf1 == pytest.approx(ref.idf1)
        assert (ours.switches, ours.misses, ours.false_positives) == (ref.num_switches, ref.num_misses,
                                                                      ref.num_false_positives)
        ev = acc.mot_events                                   # per truth: motmetrics' SWITCH events
        per_truth = ev[ev.Type == "SWITCH"].OId.value_counts().to_dict()
        assert ours.switches_by_truth == {int(g): int(n) for g, n in per_truth.items()}
        switched += ours.switches
    assert switched > 0                                       # the sequences do switch


def test_label_agreement_of_a_hand_computed_example():
    truth_ids = [["A"], ["A"], ["A"]]
    truth = [np.array([[0.0, 0.0]])] * 3
    at = np.array([[0.1, 0.0]])
    node1 = [(["x"], at), (["x"], at), (["x"], at)]
    node2 = [(["x"], at), (["y"], at), ([], np.zeros((0, 2)))]
    la = label_agreement(truth_ids, truth, [node1, node2], threshold=1.0)
    assert (la.agreeing, la.compared, la.seen) == (1, 2, 3)       # frame 3: node 2 has no track on A
    assert la.per_frame == ((1, 1), (0, 1), (0, 0))               # the agreement over time
    assert la.agreement == pytest.approx(0.5)
    assert label_agreement(truth_ids, truth, [node1]).agreement == 1.0
