"""The tree fields of the message body (tree_term, tree_root, parent) and the BEACON flag
(dfusion.wire, docs/wire-format.md): round trips, the earlier 14-field layout refused with a
clear reason, every bad value refused cleanly, and a node with the tree rule fed fuzzed tree
fields either refuses the message and is exactly as before or stays sound."""
from __future__ import annotations

import dataclasses
import pickle
import struct
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import MessageError
from dfusion.fusion import FusionNode
from dfusion.fusion.tree import SpanningTree, TreeEpoch
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.wire import BEACON, FULL, KEYED, NAIVE, VERSION, FrameKey, InfoMessage, decode, encode

KEY = FrameKey(b"tree-fields-key-0123", "net", "run")


def message(**changes) -> InfoMessage:
    fields = dict(src="b", dst="a", epoch=7, seq=3, start=0.5, sent_at=1.0, times=np.array([1.0]),
                  info=np.array([[[4.0, 0.0], [0.0, 2.0]]]), vec=np.array([[1.0, -2.0]]), dst_epoch=9, ack=5,
                  ack_mask=3, full=False, tree_term=4, tree_root="r", parent="a")
    fields.update(changes)
    return InfoMessage(**fields)


def body_of(data: bytes, keyed: bool) -> list:
    end = len(data) - 4 - (16 if keyed else 0)
    return msgpack.unpackb(data[4:end], raw=False)


def frame(body: list, flags: int, key: FrameKey | None = None) -> bytes:
    """A frame around any body (encode's framing without its checks)."""
    data = b"DF" + bytes((VERSION, flags | (KEYED if key else 0))) + msgpack.packb(body, use_bin_type=True)
    data += struct.pack("<I", zlib.crc32(data))
    return data + key.mac(data) if key else data


def reason(data: bytes, key=None) -> str | None:
    try:
        decode(data, key)
    except MessageError as exc:
        return exc.reason
    return None


@settings(max_examples=200, deadline=None)
@given(term=st.integers(0, 2**63 - 1), root=st.text(min_size=1, max_size=60), parent=st.text(max_size=60),
       src=st.text(min_size=1, max_size=60), keyed=st.booleans())
def test_tree_fields_round_trip(term, root, parent, src, keyed):
    if len(root.encode()) > 256 or len(parent.encode()) > 256 or len(src.encode()) > 256:
        return
    if parent == src or (not parent) != (root == src):
        return      # invalid combinations: tested below
    msg = message(src=src, tree_term=term, tree_root=root, parent=parent)
    key = KEY if keyed else None
    out = decode(encode(msg, key), key)
    assert (out.tree_term, out.tree_root, out.parent, out.beacon) == (term, root, parent, False)
    beacon = message(src=src, tree_term=term, tree_root=root, parent=parent, times=np.zeros(0),
                     info=np.zeros((0, 2, 2)), vec=np.zeros((0, 2)), beacon=True)
    out = decode(encode(beacon, key), key)
    assert out.beacon and len(out) == 0 and (out.tree_term, out.tree_root, out.parent) == (term, root, parent)


def test_a_fixed_tree_message_has_empty_tree_fields():
    out = decode(encode(message(tree_term=0, tree_root="", parent="")))
    assert (out.tree_term, out.tree_root, out.parent, out.beacon) == (0, "", "", False)


@pytest.mark.parametrize("keyed", [False, True])
def test_the_layout_before_the_tree_fields_is_refused_with_its_reason(keyed):
    key = KEY if keyed else None
    data = encode(message(), key)
    body = body_of(data, keyed)[:14]
    with pytest.raises(MessageError, match="14 fields.*before the tree fields"):
        decode(frame(body, data[3] & ~KEYED, key), key)
    assert reason(frame(body, data[3] & ~KEYED, key), key) == "malformed"


BAD = {
    "term-negative": dict(tree_term=-1),
    "term-too-large": dict(tree_term=2**63),
    "term-bool": dict(tree_term=True),
    "term-float": dict(tree_term=1.0),
    "term-str": dict(tree_term="1"),
    "root-bytes": dict(tree_root=b"r"),
    "root-int": dict(tree_root=3),
    "root-too-long": dict(tree_root="r" * 257),
    "root-too-long-utf8": dict(tree_root="\u00e9" * 129),
    "parent-none": dict(parent=None),
    "parent-bytes": dict(parent=b"a"),
    "parent-too-long": dict(parent="p" * 257),
    "parent-is-sender": dict(parent="b"),
    "no-parent-not-root": dict(parent=""),
    "root-with-parent": dict(tree_root="b"),
    "fixed-with-term": dict(tree_root="", parent="", tree_term=3),
    "fixed-with-parent": dict(tree_root="", parent="a", tree_term=0),
}


@pytest.mark.parametrize("keyed", [False, True])
@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_tree_fields_are_refused(case, keyed):
    key = KEY if keyed else None
    data = encode(message(), key)
    body = body_of(data, keyed)
    for name, value in BAD[case].items():
        body[{"tree_term": 14, "tree_root": 15, "parent": 16}[name]] = value
    bad = frame(body, data[3] & ~KEYED, key)
    assert reason(bad, key) == "malformed", case


@pytest.mark.parametrize("flags", [BEACON, BEACON | FULL, BEACON | NAIVE])
def test_a_beacon_carries_nothing_else(flags):
    data = encode(message())
    body = body_of(data, False)
    assert reason(frame(body, flags)) == "malformed"           # it has a block
    body[10] = body[11] = body[12] = b""
    ok = reason(frame(body, flags))
    assert ok == (None if flags == BEACON else "malformed")
    body[13] = struct.pack("<q", 2_000_000_000)             # clears a time
    assert reason(frame(body, BEACON)) == "malformed"
    fixed = body_of(encode(message(times=np.zeros(0), info=np.zeros((0, 2, 2)), vec=np.zeros((0, 2)),
                                   tree_term=0, tree_root="", parent="")), False)
    assert reason(frame(fixed, BEACON)) == "malformed"          # a fixed-tree beacon


# ---------------------------------------------------------------- a node fed fuzzed tree fields
MOTION = ConstantVelocity(2, 0.3)
PRIOR = (0.0, np.zeros(4), np.eye(4) * 4.0)
E = TreeEpoch(1, "a")


def build_chain():
    """a - b - c with the tree rule (a the root), a few exchanges; a's fresh message to b."""
    known = {"a": (E, None), "b": (E, "a"), "c": (E, "b")}

    def node(name, links, parent, inc):
        tree = SpanningTree(name, links, epoch=E, parent=parent, known={j: known[j] for j in links})
        return FusionNode(name, links, MOTION, window=50, prior=PRIOR, tree=tree, epoch=inc)

    nodes = {"a": node("a", ["b"], None, 11), "b": node("b", ["a", "c"], "a", 22), "c": node("c", ["b"], "b", 33)}
    sensor = PositionSensor(2, 0.5)
    rng = np.random.default_rng(3)
    for k in range(1, 5):
        for x in nodes.values():
            x.predict(0.1 * k)
        for x in nodes.values():
            x.update(0.1 * k, rng.normal(size=2), sensor)
        for src in "abc":
            for dst, data in nodes[src].outgoing():
                nodes[dst].receive(data)
    nodes["a"].update(0.4, [1.0, 1.0], sensor)
    return nodes, nodes["a"].message_to("b")


NODES, VALID = build_chain()
PICKLED_B = pickle.dumps(NODES["b"])


def snapshot(node: FusionNode) -> tuple:
    stats = dataclasses.asdict(node.stats)
    del stats["messages_rejected"], stats["rejections"]
    mean, cov = node.estimate()
    channels = {j: (ch.keys.copy(), ch.info.copy(), ch.last_seq, ch.seq_out) for j, ch in node.channels.items()}
    return (mean, cov, node.tree.snapshot(), dict(node.incarnations), stats, channels, node.neighbors)


def same(x, y) -> bool:
    if isinstance(x, np.ndarray):
        return np.array_equal(x, y)
    if isinstance(x, dict):
        return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
    if isinstance(x, (tuple, list)):
        return len(x) == len(y) and all(same(a, b) for a, b in zip(x, y))
    return x == y


def test_the_valid_message_is_fused():
    b = pickle.loads(PICKLED_B)
    assert b.receive(VALID) > 0


names = st.one_of(st.sampled_from(["", "a", "b", "c", "r", "x" * 256]), st.text(max_size=8),
                  st.integers(-2, 2), st.binary(max_size=3), st.none())


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(term=st.one_of(st.integers(-2, 2**64 - 1), st.booleans(), st.floats(allow_nan=True), st.none()),
       root=names, parent=names, beacon=st.booleans(), empty=st.booleans())
def test_fuzzed_tree_fields_are_refused_cleanly_or_leave_the_node_sound(term, root, parent, beacon, empty):
    body = body_of(VALID, False)
    body[14], body[15], body[16] = term, root, parent
    flags = VALID[3]
    if empty:
        body[10] = body[11] = body[12] = body[13] = b""
    if beacon:
        flags = (flags | BEACON) & ~FULL
    b = pickle.loads(PICKLED_B)
    before = snapshot(b)
    rejected = b.stats.messages_rejected
    try:
        b.receive(frame(body, flags))
    except MessageError:
        assert b.stats.messages_rejected == rejected + 1
        assert same(snapshot(b), before)
        return
    mean, cov = b.estimate()
    assert np.all(np.isfinite(mean)) and np.array_equal(cov, cov.T)
    assert np.linalg.eigvalsh(cov)[0] > 0


def test_the_worked_example_of_the_format_page_is_what_encode_makes():
    """docs/wire-format.md's example frame, byte for byte (the hex block and its size)."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "wire-format.md").read_text()
    block = page.split("Without a key, ")[1]
    size = int(block.split(" bytes")[0])
    hexdigits = "".join(re.findall(r"^[0-9a-f]+$", block.split("```")[1], flags=re.M))
    msg = InfoMessage(src="a", dst="b", epoch=7, seq=3, start=0.5, sent_at=1.0, times=np.array([1.0]),
                      info=np.array([[[4.0, 0.0], [0.0, 2.0]]]), vec=np.array([[1.0, -2.0]]), dst_epoch=9, ack=5,
                      ack_mask=3, full=False)
    data = encode(msg)
    assert data.hex() == hexdigits and len(data) == size
    keyed = encode(msg, FrameKey(b"0123456789abcdef", "demo", "run-1"))
    assert f"{len(keyed)} bytes: the flags" in page
