r"""Running a multi-target scenario in one process: a :class:`~dfusion.fusion.tracking_node.TrackingNode`
per node on the scenario's tree, over a simulated network, beside a centralized tracker.

The world is :func:`dfusion.sim.target_world.simulate_targets`'s. Every step ``t = k dt``:

1. every frame taken by ``t`` (in time order, then node order) goes to its node: a scan of
   anonymous detections to :meth:`TrackingNode.process` (the node's tracker associates it with
   its fused tracks and starts tracks from what no track explains); a tag reading to
   :meth:`TrackingNode.observe` with the target's identity (:func:`~dfusion.scenario.targets.tag_track_id`,
   born when the target appears; if the network merged that track into another, the reading
   goes to the survivor; if it was deleted, the tag starts over under the next serial, born at
   the reading). A reader that creates a tag's track adds, as its own information at that first
   reading, the initiator's velocity prior ``N(0, velocity_std^2 I)`` (``tracking.initiator.velocity_std``:
   what is known of a person's walking speed), as the initiator does for a track it starts;
   without it one reading leaves the velocity at the broad common prior's 100 m/s;
2. the bundles that have arrived by ``t`` are received;
3. every node predicts to ``t`` (its deleter and its track-to-track association run);
4. a node whose send period has elapsed sends a bundle to each tree neighbour
   (:meth:`TrackingNode.outgoing`) over the :class:`~dfusion.transport.SimulatedNetwork` with
   the scenario's link settings (latency, jitter, drops, duplicates, reordering, outages);
5. every node's tracks are recorded (:class:`~dfusion.tracking.TrackHistory`).

**The centralized reference** (``central``): one :class:`~dfusion.tracking.MultiTargetTracker`
with the same components, given every scan of every camera at its time without delay, and
every tag reading as an update of the tag's track (created at the first reading, with the
reading as position and the initiator's velocity prior).

**Metrics** per node over the steps ``k >= 1`` (:mod:`dfusion.metrics`): mean GOSPA
(``c = tracking.gospa_c``, ``p = 1``, ``alpha = 2``) and its parts; CLEAR MOT and IDF1 with
matches within ``tracking.match`` metres, identity switches; the label agreement of the node
with each other node (pooled: of the (person, step) pairs both track, the share where they
give one identity) and of the whole network (:func:`dfusion.metrics.label_agreement`); and,
for every rendezvous of a robot with a person, which tracks the node holds on each at the
closest approach and the share of the steps within ``RENDEZVOUS_WINDOW`` seconds of it
in which the node tracks both with distinct identities.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dfusion.assignment import gated_assignment
from dfusion.errors import MessageError
from dfusion.fusion.tracking_node import TrackingNode
from dfusion.linalg import Array, symmetrize
from dfusion.metrics import gospa
from dfusion.scenario.build import build_tracking_nodes, tracker_components
from dfusion.scenario.spec import Scenario
from dfusion.scenario.targets import tag_track_id
from dfusion.sim.runner import Progress
from dfusion.sim.target_world import TargetWorld, simulate_targets
from dfusion.tracking.history import TrackHistory
from dfusion.tracking.track import TrackId
from dfusion.tracking.tracker import MultiTargetTracker
from dfusion.transport.simulated import SimulatedNetwork

__all__ = ["TrackingResult", "run_tracking_scenario", "CENTRAL", "RENDEZVOUS_WINDOW"]

log = logging.getLogger(__name__)

#: The centralized reference's name in the history and the metrics.
CENTRAL = "central"
#: Seconds either side of a rendezvous over which a node's distinct tracking of the two is measured.
RENDEZVOUS_WINDOW = 5.0


@dataclass
class TrackingResult:
    """A multi-target run: the world, every node's (and the reference's) tracks over time, the metrics."""

    scenario: Scenario
    world: TargetWorld
    history: TrackHistory
    metrics: dict[str, Any] = field(default_factory=dict)
    #: The nodes as they ended the run.
    nodes: dict[str, TrackingNode] = field(default_factory=dict)

    def to_json(self, series: bool = False) -> str:
        """The metrics as JSON; with ``series`` every node's tracks at every step (identity, mean, covariance)."""
        out = dict(self.metrics)
        if series:
            out["series"] = {node: [{"t": t, "tracks": [{"id": str(tid), "mean": m.tolist(), "cov": P.tolist()}
                                                        for tid, m, P in rows]} for t, rows in recs]
                             for node, recs in self.history.nodes.items()}
        return json.dumps(out, indent=2, sort_keys=True)

    def table(self) -> str:
        """The table ``dfusion simulate`` prints: one row per node and one for the reference."""
        m = self.metrics
        head = ["node", "GOSPA [m]", "loc.", "missed", "false", "IDF1", "MOTA", "switches", "label agr.", "tracks",
                "births", "merges", "deletions", "sent [bundles]", "sent [bytes]", "CPU/step [ms]"]
        rows = [head]
        for name, v in list(m["nodes"].items()) + [(CENTRAL, m["central"])]:
            g = v["gospa"]
            rows.append([name, f"{g['mean']:.3f}", f"{g['localization']:.3f}", f"{g['missed']:.3f}",
                         f"{g['false']:.3f}", f"{v['idf1']:.3f}", "-" if v["mota"] is None else f"{v['mota']:.3f}",
                         str(v["switches"]),
                         "-" if v.get("label_agreement") is None else f"{v['label_agreement']:.3f}",
                         str(v["tracks_at_end"]), str(v.get("births", "-")), str(v.get("merges", "-")),
                         str(v.get("deletions", "-")), str(v.get("bundles", "-")), str(v.get("bytes", "-")),
                         f"{v['cpu_ms_per_step']:.2f}"])
        widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
        lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
        lines.insert(1, "-" * len(lines[0]))
        la = m["label_agreement"]
        w = m["world"]
        lines += ["",
                  f"{len(m['nodes'])} tracking nodes, {w['targets']} targets ({w['people']} people, {w['robots']} "
                  f"robots); {w['detections']} detections + {w['false_detections']} false, {w['readings']} tag "
                  f"readings; seed {m['seed']}, {m['steps']} steps of {m['dt']:g} s, associator "
                  f"{m['tracking']['associator'].upper()}",
                  f"GOSPA: c = {m['gospa_c']:g} m, p = 1, alpha = 2, mean over the steps (parts in m); IDF1, MOTA, "
                  f"switches: matches within {m['match']:g} m; label agr.: of the (target, step) pairs this node and "
                  f"another both track, the share with one identity",
                  f"network label agreement (every node gives a target the same identity): {la['agreement']:.3f} "
                  f"({la['agreeing']} of {la['compared']} (target, step) pairs tracked by every node)"]
        net = m["traffic"]
        lines.append(f"bundles over the network: {net['sent']} sent + {net['duplicated']} duplicated = "
                     f"{net['delivered']} delivered + {net['dropped']} dropped + {net['in_flight']} in flight; "
                     f"{net['rejected']} rejected")
        for rv in m["rendezvous"]:
            lines.append(f"rendezvous: {rv['robot']} meets {rv['person']} at t = {rv['t']:.1f} s "
                         f"({rv['distance']:.2f} m apart)")
            for name, v in rv["nodes"].items():
                lines.append(f"  {name}: {rv['robot']} -> {v['robot_track'] or 'no track'}, {rv['person']} -> "
                             f"{v['person_track'] or 'no track'}; both tracked, distinct identities in "
                             f"{v['distinct_share']:.0%} of the steps within {RENDEZVOUS_WINDOW:g} s")
        for a, b, s, e in self.scenario.outages():
            lines.append(f"link outage: {a} - {b} from {s:g} s to {e:g} s")
        return "\n".join(lines)


class _TagReader:
    """A tag reader's identities: the track each tag's readings go to at one node (module docstring, step 1)."""

    def __init__(self) -> None:
        self.serial: dict[str, int] = {}
        self.born: dict[str, float] = {}
        self.restarts = 0

    def track_of(self, node: TrackingNode, target: str, appear: float, t: float) -> tuple[TrackId, float]:
        tid = TrackId(target, self.serial.get(target, 0)) if target in self.serial else tag_track_id(target)
        born = self.born.get(target, appear)
        for _ in range(len(node.ended) + 1):
            if tid not in node.ended:
                return tid, (node.born(tid) if tid in node.tracks else born)
            end = node.ended[tid][0]
            if end.into is None:
                break
            tid = end.into
        # deleted: the tag starts over under the next serial, born now
        self.serial[target] = self.serial.get(target, 0) + 1
        self.born[target] = t
        self.restarts += 1
        return TrackId(target, self.serial[target]), t


def _central_reading(tracker: MultiTargetTracker, tid: TrackId, t: float, z: Array, sensor, velocity_std: float):
    """The reference's update of an identified track with a tag reading (created at the first one)."""
    track = next((tr for tr in tracker.tracks if tr.id == tid), None)
    R = np.asarray(sensor.R, float)
    if track is None:
        track = tracker.add_track(np.concatenate([z, np.zeros(2)]), np.diag([R[0, 0], R[1, 1]] + [velocity_std**2] * 2),
                                  t, tid)
        track.record(True, 1)
        return
    if t > track.time:
        track.predict(t)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    Ri = np.linalg.inv(R)
    track.add_information(symmetrize(H.T @ Ri @ H), H.T @ Ri @ np.asarray(z, float))
    track.record(True, 1)


def run_tracking_scenario(sc: Scenario, *, world: TargetWorld | None = None, progress: bool = False) -> TrackingResult:
    """Run multi-target scenario ``sc`` with every node in this process (module docstring)."""
    if not sc.multi_target:
        raise ValueError(f"{sc.path} is a single-target scenario: dfusion.sim.runner.run_scenario runs it")
    world = simulate_targets(sc) if world is None else world
    nodes = build_tracking_nodes(sc)
    names = sorted(nodes)
    net = SimulatedNetwork(((a, b, spec) for (a, b), spec in sc.links.items()), seed=sc.seed)
    motion = sc.target.motion
    parts = tracker_components(sc.tracking, motion)
    central = MultiTargetTracker(motion, parts["associator"], parts["initiator"], parts["deleter"], origin=CENTRAL,
                                 hypothesiser=parts["hypothesiser"])
    vstd = sc.tracking.velocity_std or sc.tracking.prior_velocity_std
    velocity_prior = (np.diag([0.0, 0.0, vstd**-2, vstd**-2]) if sc.tracking.velocity_std is not None else None)
    appear = {t.name: t.appear for t in sc.targets}
    readers = {n: _TagReader() for n in names}
    history = TrackHistory()
    cpu = dict.fromkeys(names, 0.0)
    cpu_central = 0.0
    last_sent = dict.fromkeys(names, -math.inf)
    rejected = 0
    fi = 0
    frames = world.frames
    bar = Progress(len(world.times) - 1) if progress else None
    for k, t in enumerate(world.times):
        t = float(t)
        while fi < len(frames) and frames[fi].t <= t + 1e-9:
            f = frames[fi]
            fi += 1
            node = nodes[f.node]
            c0 = time.process_time()
            if f.scan is not None:
                node.process(f.scan)
            for r in f.readings:
                tid, born = readers[f.node].track_of(node, r.target, appear[r.target], f.t)
                new = tid not in node.tracks
                node.observe(tid, f.t, r.z, sc.nodes[f.node].sensor, born=born)
                if new and velocity_prior is not None:   # what the reader knows of a target's speed
                    node.tracks[tid].add_local_information(f.t, velocity_prior, np.zeros(4))
            c1 = time.process_time()
            if f.scan is not None:
                central.step(f.scan)
            for r in f.readings:
                _central_reading(central, tag_track_id(r.target), f.t, r.z, sc.nodes[f.node].sensor, vstd)
            cpu[f.node] += c1 - c0
            cpu_central += time.process_time() - c1
        for n in names:
            c0 = time.process_time()
            for d in net.receive(n, t + 1e-9):
                try:
                    nodes[n].receive(d.data)
                except MessageError as exc:   # a simulated network never corrupts; log anyway
                    rejected += 1
                    log.warning("%s: %s", n, exc)
            nodes[n].predict(t)
            if t - last_sent[n] >= sc.nodes[n].send_period - 1e-9:
                last_sent[n] = t
                for j, data in nodes[n].outgoing(t):
                    net.send(n, j, data, t)
            cpu[n] += time.process_time() - c0
        if k == 0:
            continue
        for n in names:
            history.record(n, t, nodes[n].estimates())
        c0 = time.process_time()
        for tr in central.tracks:
            tr.predict(t)
        cpu_central += time.process_time() - c0
        history.record(CENTRAL, t, central.estimates())
        if bar is not None:
            bar.update(k)
    if bar is not None:
        bar.close()
    result = TrackingResult(sc, world, history, nodes=nodes)
    result.metrics = _metrics(sc, world, history, nodes, net, rejected, cpu, cpu_central,
                              sum(r.restarts for r in readers.values()))
    return result


def _gospa_parts(history: TrackHistory, node: str, world: TargetWorld, c: float) -> dict[str, float]:
    rows = np.array([[g.distance, g.localization, g.missed, g.false] for g in
                     (gospa(f.truth, f.tracks, c, 1.0) for f in history.frames(node, world.truth))])
    mean = rows.mean(axis=0) if len(rows) else np.zeros(4)
    return {"mean": float(mean[0]), "localization": float(mean[1]), "missed": float(mean[2]), "false": float(mean[3]),
            "max": float(rows[:, 0].max()) if len(rows) else 0.0}


def _labels(history: TrackHistory, node: str, world: TargetWorld, t: float, match: float) -> dict[str, TrackId]:
    """Target -> the node's track on it at ``t`` (minimum-distance assignment within ``match``)."""
    gids, X = world.truth.at(t)
    hids, Y = history.positions(node, t)
    if not gids or not hids:
        return {}
    D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=2)
    return {gids[i]: hids[j] for i, j in zip(*gated_assignment(D, D <= match))}


def _rendezvous(sc: Scenario, history: TrackHistory, world: TargetWorld, names: list[str]) -> list[dict[str, Any]]:
    out = []
    match = sc.tracking.match
    times = history.times(names[0]) if names else np.zeros(0)
    for rv in sc.rendezvous:
        at = float(times[int(np.argmin(np.abs(times - rv.t)))]) if times.size else rv.t
        near = times[np.abs(times - rv.t) <= RENDEZVOUS_WINDOW + 1e-9]
        per = {}
        for n in names:
            lab = _labels(history, n, world, at, match)
            distinct = 0
            for t in near:
                other = _labels(history, n, world, float(t), match)
                distinct += rv.robot in other and rv.person in other and other[rv.robot] != other[rv.person]
            per[n] = {"robot_track": str(lab[rv.robot]) if rv.robot in lab else None,
                      "person_track": str(lab[rv.person]) if rv.person in lab else None,
                      "distinct_share": distinct / len(near) if len(near) else 0.0}
        out.append({"robot": rv.robot, "person": rv.person, "t": rv.t, "distance": rv.distance, "nodes": per})
    return out


def _metrics(sc: Scenario, world: TargetWorld, history: TrackHistory, nodes: dict[str, TrackingNode],
             net: SimulatedNetwork, rejected: int, cpu: dict[str, float], cpu_central: float,
             tag_restarts: int) -> dict[str, Any]:
    spec = sc.tracking
    names = sorted(nodes)
    steps = len(world.times) - 1
    c, match = spec.gospa_c, spec.match
    pairs = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            _, la = history.label_agreement(world.truth, match, nodes=[a, b])
            pairs[(a, b)] = (la.agreeing, la.compared)
    _, network = history.label_agreement(world.truth, match, nodes=names)
    out: dict[str, Any] = {
        "kind": "multi_target", "scenario": sc.path, "seed": sc.seed, "steps": steps, "dt": sc.dt,
        "gospa_c": c, "match": match,
        "tracking": {"associator": spec.associator, "q": spec.q, "confirm": list(spec.confirm),
                     "max_age": spec.max_age, "max_misses": spec.max_misses, "region": spec.region,
                     "merge": spec.merge},
        "world": {"targets": len(sc.targets), "people": sum(t.kind == "person" for t in sc.targets),
                  "robots": sum(t.kind == "robot" for t in sc.targets), "detections": world.detections,
                  "false_detections": world.false_detections, "readings": world.readings,
                  "tag_restarts": tag_restarts},
        "label_agreement": {"agreement": network.agreement, "agreeing": network.agreeing,
                            "compared": network.compared},
        "nodes": {},
    }
    for n in names + [CENTRAL]:
        ids = history.identity_metrics(n, world.truth, match)
        v: dict[str, Any] = {"gospa": _gospa_parts(history, n, world, c), "idf1": ids.idf1,
                             "mota": ids.mota if math.isfinite(ids.mota) else None, "switches": ids.switches,
                             "tracks_at_end": len(history.nodes[n][-1][1]) if history.nodes.get(n) else 0}
        if n == CENTRAL:
            v["cpu_ms_per_step"] = 1e3 * cpu_central / max(steps, 1)
            out["central"] = v
            continue
        agree = [pairs[tuple(sorted((n, o)))] for o in names if o != n]
        num, den = sum(a for a, _ in agree), sum(b for _, b in agree)
        st = nodes[n].stats
        v.update({"label_agreement": num / den if den else None, "births": st.births, "tracks_heard": st.tracks_heard,
                  "merges": st.merges, "merges_decided": st.merges_decided, "deletions": st.deletions,
                  "deletions_decided": st.deletions_decided, "bundles": st.bundles_sent, "bytes": st.bytes_sent,
                  "bundles_received": st.bundles_received, "bundles_rejected": st.bundles_rejected,
                  "cpu_ms_per_step": 1e3 * cpu[n] / max(steps, 1)})
        out["nodes"][n] = v
    total = net.stats.total
    out["traffic"] = {"sent": int(total.sent), "duplicated": int(total.duplicated), "delivered": int(total.delivered),
                      "dropped": int(total.dropped), "in_flight": int(total.in_flight), "rejected": rejected}
    out["rendezvous"] = _rendezvous(sc, history, world, names)
    return out
