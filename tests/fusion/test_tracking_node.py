"""TrackingNode: many tracks over a tree, with identities known (an oracle association), against
filterpy's Kalman filter per track (tests/helpers/tracking_harness.py): never over-confident at
any step, every node's every track exact to 1e-9 once links settle, under drops, delays,
duplicates, reordering, late measurements, links that change, births at any node, merges and
deletions decided by any node."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import MessageError, ValidationError
from dfusion.fusion.bundle import TrackBundle, TrackEnd, TrackMessage, decode_bundle, encode_bundle
from dfusion.fusion.tracking_node import TrackingNode
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.tracking import TrackId
from dfusion.wire import FrameKey
from tests.helpers.dynamic_harness import rel
from tests.helpers.tracking_harness import PRIOR, TrackSchedule, run_tracks


def assert_exact(run) -> None:
    expected = {run.survivor(tid) for tid in run.born} - {None}
    expected = {tid for tid in expected if any(run.measurements[x] for x in run.closure(tid))}
    for name, node in run.nodes.items():
        got = {tid for tid, _, _ in node.estimates()}
        assert got == expected, (name, sorted(map(str, got)), sorted(map(str, expected)))
        for tid, mean, P in node.estimates():
            m_ref, P_ref = run.reference(tid, run.t_end)
            assert rel(mean, m_ref) < 1e-9 and rel(P, P_ref) < 1e-9, (name, str(tid), rel(mean, m_ref), rel(P, P_ref))
    assert run.worst >= -1e-9, run.worst


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 6), targets=st.integers(1, 4),
       drop=st.floats(0.0, 0.4), duplicate=st.floats(0.0, 0.3), max_latency=st.floats(0.0, 0.5))
def test_property_every_track_exact_and_never_over_confident_on_a_fixed_tree(seed, n, targets, drop, duplicate,
                                                                             max_latency):
    run = run_tracks(TrackSchedule(seed=seed, n=n, targets=targets, drop=drop, duplicate=duplicate,
                                   max_latency=max_latency))
    assert run.checks > 0
    assert_exact(run)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 6), aliases=st.integers(1, 3),
       deletions=st.integers(0, 2), drop=st.floats(0.0, 0.4), max_latency=st.floats(0.0, 0.5))
def test_property_merges_and_deletions_never_double_count_and_lose_nothing(seed, n, aliases, deletions, drop,
                                                                           max_latency):
    """One target under two identities (started by two nodes) merged by one node into the one born
    first; tracks deleted by one node: afterwards every node holds each survivor as the Kalman
    filter of every measurement of its identities, and nothing of the deleted ones."""
    run = run_tracks(TrackSchedule(seed=seed, n=n, targets=3, aliases=aliases, deletions=deletions, drop=drop,
                                   max_latency=max_latency, steps=30))
    assert run.merged or run.deleted or aliases == 0
    assert_exact(run)
    for node in run.nodes.values():
        assert not set(node.tracks) & (set(run.merged) | run.deleted)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 6), change=st.floats(0.2, 0.8),
       drop=st.floats(0.0, 0.3), max_latency=st.floats(0.0, 0.4))
def test_property_links_that_change_every_track_follows_the_tree_rule(seed, n, change, drop, max_latency):
    run = run_tracks(TrackSchedule(seed=seed, n=n, targets=3, aliases=1, link_changes=change, drop=drop,
                                   max_latency=max_latency, steps=30))
    assert_exact(run)


def test_keyed_bundles_and_a_merge_heard_by_a_node_that_never_had_the_track():
    run = run_tracks(TrackSchedule(seed=3, n=5, targets=3, aliases=2, deletions=1, key=b"k" * 32, steps=30))
    assert_exact(run)
    assert sum(x.stats.merges for x in run.nodes.values()) >= len(run.merged)


def _pair(**kw):
    m = ConstantVelocity(2, 0.3)
    return (TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1, **kw),
            TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, **kw))


def test_bundle_round_trip_and_refusals():
    key = FrameKey(b"x" * 16, "net", "run")
    b = TrackBundle("a", "b", 5, 1.5, (TrackMessage(TrackId("a", 3), 0.5, b"DF..."),),
                    (TrackEnd(TrackId("c", 1), TrackId("a", 0), 0.2, 1.0), TrackEnd(TrackId("c", 2))))
    assert decode_bundle(encode_bundle(b, key), key) == b
    data = bytearray(encode_bundle(b, key))
    data[12] ^= 1
    with pytest.raises(MessageError, match="checksum"):
        decode_bundle(bytes(data), key)
    with pytest.raises(MessageError, match="authenticat"):
        decode_bundle(encode_bundle(b), key)
    twice = TrackBundle("a", "b", 5, 1.5, b.tracks * 2)
    with pytest.raises(MessageError, match="twice"):
        decode_bundle(encode_bundle(twice))
    selfmerge = TrackBundle("a", "b", 5, 1.5, (), (TrackEnd(TrackId("c", 1), TrackId("c", 1)),))
    with pytest.raises(MessageError, match="itself"):
        decode_bundle(encode_bundle(selfmerge))
    with pytest.raises(MessageError, match="no DT header"):
        decode_bundle(b"DF" + bytes(20))


def test_a_refused_bundle_or_track_message_changes_nothing():
    a, b = _pair()
    s = PositionSensor(2, 0.5)
    tid = TrackId("a", 0)
    a.observe(tid, 0.0, [1.0, 2.0], s)
    (_, data), = a.outgoing(0.0)
    before = b.estimates()
    with pytest.raises(MessageError):
        b.receive(data[:-5])
    assert b.estimates() == before and b.stats.bundles_rejected == 1
    # a bundle with one good and one garbage track message: the good one is fused, the other counted
    good = decode_bundle(data)
    bad = TrackBundle("a", "b", 1, 0.0, good.tracks + (TrackMessage(TrackId("a", 9), 0.0, b"garbage"),))
    b.receive(encode_bundle(bad))
    assert [str(t) for t, _, _ in b.estimates()] == ["a#0"]
    assert b.stats.track_messages_rejected == 1 and TrackId("a", 9) not in b.tracks
    # misaddressed, and from a stranger
    stranger = TrackBundle("z", "b", 1, 0.0)
    with pytest.raises(MessageError, match="not a neighbour"):
        b.receive(encode_bundle(stranger))
    with pytest.raises(MessageError, match="delivered to"):
        b.receive(encode_bundle(TrackBundle("a", "c", 1, 0.0)))


def test_messages_for_an_ended_track_are_ignored_and_answered_with_the_end():
    a, b = _pair()
    s = PositionSensor(2, 0.5)
    tid = TrackId("a", 0)
    a.observe(tid, 0.0, [1.0, 2.0], s)
    for j, d in a.outgoing(0.0):
        b.receive(d)
    b.delete(tid)
    b.outgoing(0.1)    # the end's bundle is lost
    a.predict(0.1)
    a.observe(tid, 0.1, [1.0, 2.1], s)
    for j, d in a.outgoing(0.1):
        b.receive(d)
    assert tid not in b.tracks and b.stats.ended_track_messages == 1
    for j, d in b.outgoing(0.2):   # answered with the end again
        a.receive(d)
    assert tid not in a.tracks and tid in a.ended
    with pytest.raises(ValidationError, match="ended"):
        a.observe(tid, 0.2, [1.0, 2.0], s)


def test_max_tracks_bounds_what_a_neighbour_can_make_a_node_hold():
    m = ConstantVelocity(2, 0.3)
    a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, max_tracks=3)
    s = PositionSensor(2, 0.5)
    for k in range(6):
        a.observe(TrackId("a", k), 0.0, [k, 0.0], s)
    for _, d in a.outgoing(0.0):
        b.receive(d)
    assert len(b.tracks) == 3 and b.stats.tracks_refused == 3


def test_bundles_split_under_the_size_limit():
    m = ConstantVelocity(2, 0.3)
    a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1, max_message_bytes=4096)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, max_message_bytes=4096)
    s = PositionSensor(2, 0.5)
    for k in range(40):
        a.observe(TrackId("a", k), 0.0, [k, 0.0], s)
    out = a.outgoing(0.0)
    assert len(out) > 1 and all(len(d) <= 4096 for _, d in out)
    for _, d in out:
        b.receive(d)
    assert len(b.estimates()) == 40
    for (tid, m1, P1), (_, m2, P2) in zip(a.estimates(), b.estimates()):
        np.testing.assert_allclose(m1, m2, rtol=1e-12, atol=1e-12)


def test_a_node_cut_off_from_the_sensors_does_not_merge_tracks_its_predictions_bring_together():
    """Two people walking towards each other, seen by node a; b hears of them, then the link
    fails. b's predictions of the two meet, but nobody has seen them together: b must not
    decide that they are one target (its merge would be enforced on the whole network when the
    link returns). Fresh tracks of one target under two identities still merge."""
    m = ConstantVelocity(2, 0.01)
    a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, epoch=2)
    s = PositionSensor(2, 0.1)
    x, y = TrackId("a", 0), TrackId("a", 1)
    for k in range(11):
        t = 0.1 * k
        a.predict(t)
        a.observe(x, t, [t, 0.0], s, born=0.0)
        a.observe(y, t, [6.0 - t, 0.0], s, born=0.0)
        for _, d in a.outgoing(t):
            b.receive(d)
        b.predict(t)
    for k in range(11, 40):     # the link is down from here: b only predicts; x and y meet at (3, 0) at t = 3
        b.predict(0.1 * k)
    assert {x, y} <= set(b.tracks) and b.stats.merges == 0
    # fresh information of one target under two identities: merged
    z1, z2 = TrackId("a", 2), TrackId("b", 0)
    for k in range(40, 50):
        t = 0.1 * k
        b.predict(t)
        b.observe(z1, t, [10.0, 0.1 * k], s, born=4.0)
        if z2 not in b.ended:
            b.observe(z2, t, [10.0, 0.1 * k], s, born=4.0)
    assert b.stats.merges_decided == 1 and z2 not in b.tracks and z1 in b.tracks


def test_a_node_that_does_not_see_two_people_walking_side_by_side_does_not_merge_them():
    """a sees two people walk side by side 0.3 m apart (a camera would find them distinct: both
    take a detection of one scan); b, a relay with fresh information from a but no sensor of its
    own, has no such evidence: it must not merge them (a merge is enforced on every node)."""
    m = ConstantVelocity(2, 0.01)
    a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, epoch=2)
    s = PositionSensor(2, 0.3)
    x, y = TrackId("a", 0), TrackId("a", 1)
    rng = np.random.default_rng(0)
    for k in range(40):
        t = 0.1 * k
        a.predict(t)
        a.observe(x, t, [t, 0.0] + 0.3 * rng.standard_normal(2), s, born=0.0)
        a.observe(y, t, [t, 0.3] + 0.3 * rng.standard_normal(2), s, born=0.0)
        for _, d in a.outgoing(t):
            b.receive(d)
        b.predict(t)
    assert {x, y} <= set(b.tracks) and b.stats.merges == 0


def test_a_flood_of_ends_is_bounded():
    m = ConstantVelocity(2, 0.3)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, max_tracks=4)
    s = PositionSensor(2, 0.5)
    b.observe(TrackId("b", 0), 0.0, [0.0, 0.0], s)
    for k in range(10):
        ends = tuple(TrackEnd(TrackId("x", 1000 * k + i)) for i in range(50))
        b.receive(encode_bundle(TrackBundle("a", "b", 1, 0.0, (), ends)))
    assert len(b.ended) == b.max_ended == 64 and b.stats.ends_forgotten == 500 - 64
    assert sum(len(p) for p in b._announce.values()) <= 64
    assert [str(t) for t, _, _ in b.estimates()] == ["b#0"]


def test_two_cameras_that_both_start_a_track_for_each_person_end_with_one_identity_each():
    """Two nodes, each with a camera seeing both people (no clutter, P_D = 1): each starts its own
    tracks; track-to-track association merges a pair into the track born first, or the duplicate
    that both nodes' association starves ends stale, and both nodes end with two tracks under the
    same two identities, near the truth (3 sigma of the fused position error, a bound from the
    detections' noise alone: std 0.2 m over 2 x 30 detections)."""
    from dfusion.tracking import GNN, MofNInitiator, Scan, StaleDeleter
    rng = np.random.default_rng(4)
    motion = ConstantVelocity(2, 0.01)
    sensor = PositionSensor(2, 0.2)
    nodes = {n: TrackingNode(n, [o], motion, associator=GNN(), initiator=MofNInitiator(motion, m=3, n=4),
                             deleter=StaleDeleter(1.0), epoch=i + 1, window=None, horizon=3.0)
             for i, (n, o) in enumerate((("cam1", "cam2"), ("cam2", "cam1")))}
    people = [np.array([0.0, 0.0, 1.0, 0.2]), np.array([10.0, 5.0, -0.5, 0.3])]
    dt = 0.1
    for k in range(1, 31):
        t = round(k * dt, 9)
        truth = [p[:2] + p[2:] * t for p in people]
        for name in sorted(nodes):   # one scan per camera; the second camera's a little later
            ts = round(t + (0.02 if name == "cam2" else 0.0), 9)
            z = np.array([x + rng.normal(0, 0.2, 2) for x in truth])
            nodes[name].predict(ts)
            nodes[name].process(Scan(ts, z, sensor, clutter_density=1e-4, detection_probability=0.99))
        out = [(j, d) for n in sorted(nodes) for j, d in nodes[n].outgoing(t)]
        for j, d in out:
            nodes[j].receive(d)
    ids = {n: sorted(str(tid) for tid, _, _ in x.estimates()) for n, x in nodes.items()}
    assert ids["cam1"] == ids["cam2"] and len(ids["cam1"]) == 2, ids
    assert sum(x.stats.births for x in nodes.values()) == 4
    # each node ends both duplicates, by a merge or by starvation (which one depends on timing: a node
    # compares a track it has just heard of only after one of its own scans bore on it, merge_fresh)
    assert all(x.stats.merges + x.stats.deletions == 2 for x in nodes.values())
    for x in nodes.values():
        for _, mean, P in x.estimates():
            err = min(np.linalg.norm(mean[:2] - (p[:2] + p[2:] * x.time)) for p in people)
            assert err < 3 * 0.2 * np.sqrt(2 / 10), err


def test_tracks_added_with_a_given_prior_are_exact_against_filterpy_from_that_prior():
    """A team of known size: both nodes add the same two tracks with the same given prior
    (add_track); each observes them (known association) at its own times; after the links
    settle both nodes hold each track as filterpy's Kalman filter from that prior over every
    measurement of it, to 1e-9. An anonymous scan is associated with a given track before
    any measurement of it; a node that did not add a track creates it with TrackPrior."""
    from filterpy.kalman import KalmanFilter

    from dfusion.tracking import Scan
    from tests.helpers.fusion_harness import Q_PSD, cv_F, cv_Q

    motion = ConstantVelocity(2, Q_PSD)
    a = TrackingNode("a", ["b"], motion, prior=PRIOR, deleter=False, merger=False, epoch=1)
    b = TrackingNode("b", ["a"], motion, prior=PRIOR, deleter=False, merger=False, epoch=2)
    priors = {TrackId("team", 1): (np.array([1.0, 2.0, 0.1, 0.0]), np.diag([0.09, 0.09, 0.01, 0.01])),
              TrackId("team", 2): (np.array([8.0, -3.0, 0.0, -0.2]), np.diag([0.25, 0.16, 0.04, 0.02]))}
    for node in (a, b):
        for tid, (m0, P0) in priors.items():
            node.add_track(tid, 0.0, m0, P0)
    assert [t for t, _, _ in a.estimates()] == sorted(priors)     # estimates before any measurement
    with pytest.raises(ValidationError, match="already known"):
        a.add_track(TrackId("team", 1), 0.0, *priors[TrackId("team", 1)])
    rng = np.random.default_rng(7)
    meas = {tid: [] for tid in priors}
    for k in range(1, 16):
        for node, dt, std in ((a, 0.0, 0.3), (b, 0.05, 0.5)):
            t = round(0.2 * k + dt, 9)
            node.predict(t)
            for tid, (m0, _) in priors.items():
                if rng.random() < 0.7:
                    z = m0[:2] + m0[2:] * t + rng.normal(0, std, 2)
                    node.observe(tid, t, z, PositionSensor(2, std))
                    meas[tid].append((t, z, std))
        for src, dst in ((a, b), (b, a)):
            for _, d in src.outgoing(0.2 * k):
                dst.receive(d)
    t_end = 3.5
    for _ in range(3):
        for src, dst in ((a, b), (b, a)):
            src.predict(t_end)
            for _, d in src.outgoing(t_end):
                dst.receive(d)
    for tid, (m0, P0) in priors.items():
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.x, kf.P = m0.reshape(4, 1).copy(), P0.copy()
        kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
        t_prev = 0.0
        for t, z, std in sorted(meas[tid], key=lambda x: x[0]) + [(t_end, None, None)]:
            if t > t_prev:
                kf.F, kf.Q = cv_F(t - t_prev), cv_Q(t - t_prev)
                kf.predict()
                t_prev = t
            if z is not None:
                kf.R = std**2 * np.eye(2)
                kf.update(z.reshape(2, 1))
        for node in (a, b):
            mean, P = node.tracks[tid].estimate(t_end)
            assert rel(mean, kf.x.ravel()) < 1e-9 and rel(P, kf.P) < 1e-9, (node.name, str(tid))
    # anonymous: a fresh node's given track takes a detection near its prior before any measurement
    c = TrackingNode("c", ["a"], motion, prior=PRIOR, deleter=False, merger=False, epoch=3, initiator=None)
    c.add_track(TrackId("team", 1), 0.0, *priors[TrackId("team", 1)])
    c.predict(0.1)
    c.process(Scan(0.1, np.array([[1.05, 2.0]]), PositionSensor(2, 0.2), 1e-4, 0.9))
    assert c.tracks[TrackId("team", 1)].newest_information_time() == pytest.approx(0.1)
    # a bundle of a track c did not add: created with TrackPrior (broad), not the given prior
    a2 = TrackingNode("a", ["c"], motion, prior=PRIOR, deleter=False, merger=False, epoch=4)
    a2.add_track(TrackId("team", 2), 0.0, *priors[TrackId("team", 2)])
    a2.observe(TrackId("team", 2), 0.1, [8.0, -3.0], PositionSensor(2, 0.3))
    for _, d in a2.outgoing(0.1):
        c.receive(d)
    _, P_c = c.tracks[TrackId("team", 2)].estimate()
    assert P_c[2, 2] > 50.0 and c.stats.tracks_heard == 1


def test_a_node_that_does_not_see_two_close_targets_does_not_merge_them():
    """Two people walk side by side 0.25 m apart in node a's view only; a's scans detect both in
    every scan (two targets), b has no sensor and holds a's two tracks as received. b must not
    declare them one target (its merger has no evidence either way), nor may a."""
    from dfusion.tracking import GNN, Scan
    from dfusion.tracking.track_to_track import TrackToTrackAssociator
    m = ConstantVelocity(2, 0.05)
    sensor = PositionSensor(2, 0.3)
    a = TrackingNode("a", ["b"], m, associator=GNN(), deleter=False, merger=TrackToTrackAssociator(confirm=3),
                     epoch=1, window=20)
    b = TrackingNode("b", ["a"], m, associator=GNN(), deleter=False, merger=TrackToTrackAssociator(confirm=3),
                     epoch=2, window=20)
    rng = np.random.default_rng(4)
    for k in range(1, 41):
        t = round(0.1 * k, 9)
        people = np.array([[1.0 * t, 0.0], [1.0 * t, 0.25]])
        a.process(Scan(t, people + 0.02 * rng.standard_normal((2, 2)), sensor, 1e-3, 0.9))
        b.predict(t)
        for _, d in a.outgoing(t):
            b.receive(d)
        for _, d in b.outgoing(t):
            a.receive(d)
    assert a.stats.births == 2 and len(a.tracks) == 2
    assert len(b.tracks) == 2, [str(x) for x in b.tracks]
    assert a.stats.merges == 0 and b.stats.merges == 0


def test_staleness_is_judged_by_the_nodes_that_see_a_track():
    """a sees a person until t = 1; its bundles reach b 0.3 s late. With ObserverDeleter
    (StaleDeleter(0.2 s)) b, which does not see the person, never ends the track while a still sees it (a
    StaleDeleter of 0.2 s at b would: b's newest information is always 0.3 s old); a ends it
    0.2 s after its last detection and b hears."""
    from dfusion.tracking import ObserverDeleter, StaleDeleter
    m = ConstantVelocity(2, 0.05)
    s = PositionSensor(2, 0.3)
    tid = TrackId("a", 0)

    def run(deleter_b):
        a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=ObserverDeleter(StaleDeleter(0.2), 1.0), merger=False, epoch=1,
                         window=20)
        b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=deleter_b, merger=False, epoch=2, window=20)
        flight, ended_at = [], None
        for k in range(1, 26):
            t = round(0.1 * k, 9)
            a.predict(t)
            b.predict(t)
            for at, d in [f for f in flight if f[0] <= t + 1e-9]:
                b.receive(d)
            flight = [f for f in flight if f[0] > t + 1e-9]
            if t <= 1.0:
                a.observe(tid, t, [1.0 * t, 2.0], s, born=0.1)
            flight += [(t + 0.3, d) for _, d in a.outgoing(t)]
            for _, d in b.outgoing(t):
                a.receive(d)
            if tid in a.ended and ended_at is None:
                ended_at = t
            if t <= 1.0 and b.stats.deletions_decided:
                return a, b, ended_at, t
        return a, b, ended_at, None

    a, b, ended_at, early = run(ObserverDeleter(StaleDeleter(0.2), 1.0))
    assert early is None and b.stats.deletions_decided == 0
    assert ended_at == pytest.approx(1.3) and a.stats.deletions_decided == 1
    assert tid not in b.tracks and tid in b.ended
    _, b2, _, early = run(StaleDeleter(0.2))
    assert early is not None and early <= 1.0       # the naive rule ends a track that is still seen
    with pytest.raises(ValidationError, match="needs a Deleter"):
        ObserverDeleter(0.2)


def test_a_track_is_not_deleted_just_before_the_scan_that_detects_it():
    """Detections at 0.1 .. 0.5 s, four misses, a detection at 1.0 s: with StaleDeleter(0.45) the
    track's newest information is 0.5 s old at 1.0 s before the scan, 0 after it. As a centralized
    tracker's, the deleter runs after the scan: the track lives on, under its identity."""
    from dfusion.tracking import GNN, MofNInitiator, Scan, StaleDeleter
    m = ConstantVelocity(2, 0.05)
    sensor = PositionSensor(2, 0.1)
    a = TrackingNode("a", [], m, associator=GNN(), initiator=MofNInitiator(m, m=3, n=5), deleter=StaleDeleter(0.45),
                     merger=False, epoch=1, window=20)
    for k in list(range(1, 6)) + list(range(10, 13)):
        t = round(0.1 * k, 9)
        a.process(Scan(t, np.array([[1.0 * t, 0.0]]), sensor, 1e-3, 0.9))
    assert a.stats.births == 1 and a.stats.deletions == 0
    assert [str(tid) for tid, _, _ in a.estimates()] == ["a#0"]


def test_ends_count_in_the_byte_budget_of_a_split_send():
    """One large track message and many ends: every bundle stays under max_message_bytes (the
    receiver would refuse a larger one whole, ends and tracks with it)."""
    m = ConstantVelocity(2, 0.3)
    a = TrackingNode("a", ["b"], m, prior=PRIOR, deleter=False, merger=False, epoch=1, max_message_bytes=6000)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, max_message_bytes=6000)
    s = PositionSensor(2, 0.5)
    tid = TrackId("a", 0)
    for k in range(60):                      # a window of 60 states: a message of several kilobytes
        a.predict(0.1 * k)
        a.observe(tid, 0.1 * k, [0.1 * k, 0.0], s, born=0.0)
    for i in range(200):
        a._record_end(TrackEnd(TrackId("gone", i)))
    out = a.outgoing(6.0)
    assert len(out) > 1 and all(len(d) <= 6000 for _, d in out), [len(d) for _, d in out]
    for _, d in out:
        b.receive(d)
    assert len(b.ended) == 200 and [str(t) for t, _, _ in b.estimates()] == ["a#0"]


def test_a_merge_heard_by_a_full_node_takes_the_place_of_the_merged_track():
    m = ConstantVelocity(2, 0.3)
    b = TrackingNode("b", ["a"], m, prior=PRIOR, deleter=False, merger=False, epoch=2, max_tracks=1)
    s = PositionSensor(2, 0.5)
    g, k = TrackId("b", 0), TrackId("a", 0)
    b.observe(g, 0.0, [1.0, 2.0], s)
    b.receive(encode_bundle(TrackBundle("a", "b", 1, 0.0, (), (TrackEnd(g, k, 0.0, 0.0),))))
    assert list(b.tracks) == [k] and g in b.ended and b.stats.tracks_refused == 0
    mean, _ = b.tracks[k].estimate()
    np.testing.assert_allclose(mean[:2], [1.0, 2.0], atol=1e-3)   # b's own measurement moved into k


def test_a_bundle_older_than_the_remembered_ends_starts_no_track():
    """A replay of an old bundle after its track's end is forgotten (ended_for) must not bring the track back."""
    a, b = _pair()
    s = PositionSensor(2, 0.5)
    g = TrackId("a", 0)
    a.observe(g, 0.0, [1.0, 2.0], s)
    (_, old), = a.outgoing(0.0)
    b.receive(old)
    b.delete(g)
    b.predict(200.0)                          # the end is forgotten after ended_for = 120 s
    assert g not in b.ended
    b.receive(old)
    assert g not in b.tracks and b.stats.track_messages_rejected == 1
