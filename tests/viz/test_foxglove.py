"""The MCAP recording of a scenario run, read back with the ``mcap`` library's reader
(not dfusion's writer) and checked against Foxglove's own schema definitions (the
protobuf descriptors of foxglove-schemas-protobuf, published by Foxglove): every
foxglove.* channel must carry Foxglove's published descriptor and its messages must
parse with it; ``/diagnostics`` must decode with rosbags as
``diagnostic_msgs/msg/DiagnosticArray``; every node's estimate at every step, the tree
with its outage and the ground truth must be in it."""
from __future__ import annotations

import importlib
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore

from dfusion.scenario import load_scenario
from dfusion.sim.runner import run_scenario
from dfusion.viz.foxglove import record_mcap

ROOT = Path(__file__).resolve().parents[2]
ROS2 = get_typestore(Stores.ROS2_HUMBLE)


def _foxglove_type(schema_name: str):
    short = schema_name.split(".", 1)[1]
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2"), short)


def _class_from_schema(schema):
    """The protobuf class built from the file's own FileDescriptorSet (what Foxglove does)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)), fds


def _as_dict(msg) -> dict:
    return json_format.MessageToDict(msg, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)


def read_recording(path: Path):
    """topic -> [(log time, message)] (protobuf as dicts, CDR as rosbags objects, JSON as dicts),
    topic -> schema name."""
    topics, schemas, classes = defaultdict(list), {}, {}
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            schemas[channel.topic] = schema.name
            if channel.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                if schema.name not in classes:
                    cls, fds = _class_from_schema(schema)
                    official = _foxglove_type(schema.name).DESCRIPTOR.file
                    proto = descriptor_pb2.FileDescriptorProto()
                    official.CopyToProto(proto)
                    assert proto in list(fds.file), f"{schema.name}: not Foxglove's published descriptor"
                    classes[schema.name] = cls
                m = classes[schema.name].FromString(message.data)
                # and it parses as the official type with nothing left over
                official_msg = _foxglove_type(schema.name).FromString(message.data)
                assert official_msg.SerializeToString() == message.data
                topics[channel.topic].append((message.log_time, _as_dict(m)))
            elif channel.message_encoding == "cdr":
                assert schema.encoding == "ros2msg"
                topics[channel.topic].append((message.log_time, ROS2.deserialize_cdr(message.data, schema.name)))
            else:
                assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
                topics[channel.topic].append((message.log_time, json.loads(message.data)))
    return topics, schemas


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    sc = load_scenario(ROOT / "topologies" / "urus.scenario.toml", duration=36.0)   # outage 32-42 s
    res = run_scenario(sc)
    path = record_mcap(res, tmp_path_factory.mktemp("mcap") / "urus.mcap")
    topics, schemas = read_recording(path)
    return sc, res, topics, schemas


def test_every_foxglove_message_is_a_valid_foxglove_message(recording):
    _, _, topics, schemas = recording
    used = {s for s in schemas.values() if s.startswith("foxglove.")}
    assert used == {"foxglove.PoseInFrame", "foxglove.SceneUpdate"}
    assert schemas["/diagnostics"] == "diagnostic_msgs/msg/DiagnosticArray"
    for topic, schema in schemas.items():
        if not schema.startswith("foxglove.") and topic != "/diagnostics":
            assert schema in ("dfusion/Estimate", "dfusion/Tree")
    assert sum(len(topics[t]) for t, s in schemas.items() if s.startswith("foxglove.")) > 1000


def test_every_estimate_at_every_step_and_the_truth(recording):
    sc, res, topics, _ = recording
    K = len(res.times)
    for name in list(sc.nodes) + ["centralized"]:
        prefix = "/centralized" if name == "centralized" else f"/nodes/{name}"
        est = topics[f"{prefix}/estimate"]
        poses = topics[f"{prefix}/pose"]
        assert len(est) == len(poses) == K
        mean = res.central_mean if name == "centralized" else res.node_mean[name]
        cov = res.central_cov if name == "centralized" else res.node_cov[name]
        got_t = np.array([m["t"] for _, m in est])
        np.testing.assert_allclose(got_t, res.times, atol=1e-12)
        np.testing.assert_allclose([m["mean"] for _, m in est], mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.array([m["covariance"] for _, m in est]).reshape(K, 4, 4), cov, rtol=0, atol=1e-12)
        np.testing.assert_allclose([[m["pose"]["position"]["x"], m["pose"]["position"]["y"]] for _, m in poses],
                                   mean[:, :2], atol=1e-12)
        # log times are the scenario times
        np.testing.assert_array_equal([lt for lt, _ in est], np.round(res.times * 1e9).astype(np.int64))
    truth = topics["/truth"]
    assert len(truth) == K
    np.testing.assert_allclose([[m["pose"]["position"]["x"], m["pose"]["position"]["y"]] for _, m in truth],
                               res.truth[:, :2], atol=1e-12)


def test_ellipses_are_three_sigma(recording):
    _, res, topics, _ = recording
    k = 200
    _, upd = topics["/scene/estimates"][k]
    ent = next(e for e in upd["entities"] if e["id"] == "ellipse/cam_left")
    pts = np.array([[p["x"], p["y"]] for p in ent["lines"][0]["points"]])
    m, P = res.node_mean["cam_left"][k, :2], res.node_cov["cam_left"][k, :2, :2]
    d = pts - m
    md2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(P), d)   # Mahalanobis distance squared, independently
    np.testing.assert_allclose(md2, 9.0, rtol=1e-9)


def test_tree_sensors_and_diagnostics(recording):
    sc, res, topics, _ = recording
    tree = topics["/tree"]
    edges = {frozenset(e) for e in sc.graph.edges}
    assert {frozenset((link["a"], link["b"])) for link in tree[0][1]["links"]} == edges
    assert all(link["up"] for link in tree[0][1]["links"])
    at_outage = [m for lt, m in tree if abs(lt - 32e9) < 1]
    assert at_outage, "the outage at 32 s changes the tree"
    down = [link for link in at_outage[0]["links"] if not link["up"]]
    assert {frozenset((d["a"], d["b"])) for d in down} == {frozenset(("gateway", "cam_left"))}
    diags = [(lt, st) for lt, m in topics["/diagnostics"] for st in m.status]
    down_at = [(lt, st) for lt, st in diags if st.message.startswith(("link gateway - cam_left down",
                                                                       "link cam_left - gateway down"))]
    assert len(down_at) == 1 and down_at[0][0] == 32_000_000_000 and down_at[0][1].level == 1   # WARN
    assert {kv.key: kv.value for kv in down_at[0][1].values}["state"] == "down"
    sensors = topics["/scene/sensors"][0][1]["entities"]
    ids = {e["id"] for e in sensors}
    assert {"footprint/cam_left", "footprint/cam_right", "sensor/wsn", "truth/path"} <= ids
    wsn = next(e for e in sensors if e["id"] == "sensor/wsn")
    np.testing.assert_allclose([[s["pose"]["position"]["x"], s["pose"]["position"]["y"]] for s in wsn["spheres"]],
                               np.asarray(sc.nodes["wsn"].sensor.receivers)[:, :2])
    # a camera detection is drawn where the camera's ray meets the ground
    dets = topics["/detections"]
    assert len(dets) == sum(1 for m in res.world.measurements if m.node.startswith("cam"))


def test_live_view_streams_every_step_as_the_recording_has_it(tmp_path):
    """The live view (run_scenario's on_step) sends each step's messages as they are made;
    here into a list instead of foxglove-sdk's server. They are the recording's messages."""
    from dfusion.viz.foxglove import LiveView, messages_of_result

    sc = load_scenario(ROOT / "topologies" / "urus.scenario.toml", duration=8.0)
    got = []
    live = LiveView(sc, speed=0.0, sink=lambda *m: got.append(m))
    res = run_scenario(sc, on_step=live)
    rec = messages_of_result(res)
    per_topic = defaultdict(list)
    for topic, _, ns, msg in got:
        per_topic[topic].append((ns, msg))
    assert len(per_topic["/nodes/wsn/estimate"]) == len(res.times)
    np.testing.assert_allclose([m["mean"] for _, m in per_topic["/nodes/wsn/estimate"]], res.node_mean["wsn"],
                               atol=1e-12)
    def key(m):
        return (m[0], m[2], json.dumps(m[3], sort_keys=True))
    steps = {"/truth", "/scene/estimates", "/detections"} | {f"/nodes/{n}/estimate" for n in sc.nodes}
    assert sorted(map(key, (m for m in got if m[0] in steps))) == sorted(map(key, (m for m in rec if m[0] in steps)))
    # what the server is given: bytes in the channel's encoding (foxglove-sdk's Channel.log takes bytes, not views)
    from dfusion.viz.foxglove import encode

    assert {m[1] for m in got} >= {"foxglove.SceneUpdate", "diagnostic_msgs/msg/DiagnosticArray", "dfusion/Estimate"}
    assert all(type(encode(m[1], m[3])) is bytes for m in got)


def test_live_view_of_one_node_estimate():
    """dfusion run's monitor hands each node's estimate over as it arrives."""
    from dfusion.viz.foxglove import LiveView

    sc = load_scenario(ROOT / "topologies" / "urus.scenario.toml", duration=2.0)
    got = []
    live = LiveView(sc, speed=0.0, sink=lambda *m: got.append(m))
    n0 = len(got)
    mean, cov = np.array([3.0, 10.0, 0.4, 0.0]), np.diag([0.25, 0.16, 0.01, 0.01])
    live.node_estimate("gateway", 1.5, mean, cov)
    msgs = {m[0]: m for m in got[n0:]}
    assert set(msgs) == {"/nodes/gateway/pose", "/nodes/gateway/estimate", "/scene/estimates"}
    assert all(m[2] == 1_500_000_000 for m in msgs.values())
    assert msgs["/nodes/gateway/estimate"][3]["std"] == pytest.approx([0.5, 0.4, 0.1, 0.1])
    ents = msgs["/scene/estimates"][3]["entities"]
    assert [e["id"] for e in ents] == ["ellipse/gateway"]
    est = msgs["/nodes/gateway/estimate"][3]
    assert est["nees"] is None and est["gap_position_m"] is None   # unknown live: JSON null, not NaN
    json.loads(json.dumps(est, allow_nan=False))
    from dfusion.viz.foxglove import encode

    upd = _foxglove_type("foxglove.SceneUpdate").FromString(encode("foxglove.SceneUpdate", msgs["/scene/estimates"][3]))
    assert [e.id for e in upd.entities] == ["ellipse/gateway"] and upd.entities[0].timestamp.seconds == 1


def test_multi_process_recording_draws_every_delivered_measurement(tmp_path):
    """A ``dfusion run`` result knows of each measurement only whether it reached its node's
    process or was lost while the node was down (``measurement_events``). Its recording draws
    each camera measurement once, at the first step at or after its arrival (checked by brute
    force over the grid), blue when delivered, red with a log line when lost."""
    from dfusion.fusion.channel import time_key
    from dfusion.run.monitor import measurement_events
    from dfusion.viz.foxglove import messages_of_result

    sc = load_scenario(ROOT / "topologies" / "urus.scenario.toml", duration=6.0)
    res = run_scenario(sc)
    cams = [m for m in res.world.measurements if m.node == "cam_left"]
    lost = {("cam_left", time_key(m.t)) for m in cams[:3]}
    res.events = measurement_events(res.world, res.times, lost)
    last = float(res.times[-1])
    inside = [m for m in res.world.measurements if m.arrival <= last + 1e-9]
    assert len(res.events) == len(inside) > 0
    for ev, m in zip(res.events, inside):
        assert ev["t"] == min(float(t) for t in res.times if t >= m.arrival - 1e-9)
        assert ev["outcome"] == (["lost"] if (m.node, time_key(m.t)) in lost else ["delivered"])
    msgs = messages_of_result(res)
    dets = [m for topic, _, _, m in msgs if topic == "/detections"]
    assert len(dets) == sum(1 for m in inside if m.node.startswith("cam"))
    colours = [d["entities"][0]["spheres"][0]["color"] for d in dets]
    red = [c for c in colours if c["r"] > 0.8]
    assert len(red) == 3 and len(colours) - len(red) == sum(1 for c in colours if c["b"] > 0.8)
    logs = [st["message"] for topic, _, _, m in msgs if topic == "/diagnostics" for st in m["status"]
            if "not used" in st["message"]]
    assert len(logs) == 3 and all("lost" in line for line in logs)
