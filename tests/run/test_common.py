"""Security options of a run (dfusion.scenario.security, dfusion.run.common): the [security] table, TLS files, the network key."""
from __future__ import annotations

import stat
import time

import pytest

from dfusion.errors import ValidationError
from dfusion.run.common import generate_network_key, load_network_key, new_run_id
from dfusion.scenario.security import SecurityOptions, security_options


def test_security_table_is_parsed_strictly_with_paths_relative_to_the_scenario(tmp_path):
    sec = security_options({"network_key_file": "secrets/net.key", "tls": {"dir": "certs", "ca": "/etc/ca.pem"}},
                           tmp_path)
    assert sec == SecurityOptions(str(tmp_path / "secrets/net.key"), str(tmp_path / "certs"), "/etc/ca.pem")
    assert sec.tls and not SecurityOptions().tls
    assert security_options(None) == SecurityOptions()
    for table, match in [({"tsl": {}}, r"security\.tsl: unknown key"),
                         ({"tls": {"dir": "c", "crt": "x"}}, r"security\.tls\.crt: unknown key"),
                         ({"tls": {}}, "empty"),
                         ({"tls": "certs"}, r"\[security\.tls\]"),
                         ({"network_key_file": 3}, "network_key_file must be"),
                         ({"tls": {"ca": ""}}, "ca must be")]:
        with pytest.raises(ValidationError, match=match):
            security_options(table, tmp_path)


def test_tls_files_per_process_shared_or_missing(tmp_path):
    for name in ("ca.pem", "a.pem", "a.key", "node.pem", "node.key"):
        (tmp_path / name).write_text("-----BEGIN X-----\n")
    sec = SecurityOptions(tls_dir=str(tmp_path))
    a, b = sec.tls_files("a"), sec.tls_files("b")
    assert (a.ca, a.cert, a.key) == (str(tmp_path / "ca.pem"), str(tmp_path / "a.pem"), str(tmp_path / "a.key"))
    assert (b.cert, b.key) == (str(tmp_path / "node.pem"), str(tmp_path / "node.key"))   # the shared one
    assert SecurityOptions().tls_files("a") is None
    with pytest.raises(ValidationError, match="private key"):
        SecurityOptions(tls_ca=str(tmp_path / "ca.pem"), tls_cert=str(tmp_path / "a.pem")).tls_files("a")
    (tmp_path / "node.key").unlink()
    with pytest.raises(ValidationError, match="node.key"):
        sec.tls_files("b")
    # the command line over the scenario: the key file where the command line has none, TLS as a whole
    cli = SecurityOptions(tls_ca="x", tls_cert="y", tls_key="z")
    scen = SecurityOptions("k", tls_dir=str(tmp_path))
    assert cli.over(scen) == SecurityOptions("k", None, "x", "y", "z")
    assert SecurityOptions().over(scen) == scen


def test_generated_network_key_is_private_and_random(tmp_path):
    k1 = generate_network_key(tmp_path / "k1")
    k2 = generate_network_key(tmp_path / "k2")
    assert stat.S_IMODE((tmp_path / "k1").stat().st_mode) == 0o600
    assert len(k1) == 64 and k1 != k2 and bytes.fromhex(k1.decode())
    assert load_network_key(tmp_path / "k1") == k1
    assert new_run_id() != new_run_id() and len(new_run_id()) == 16
    # a file (or a symlink planted there) is replaced, never written through
    victim = tmp_path / "victim"
    victim.write_bytes(b"keep")
    (tmp_path / "k3").symlink_to(victim)
    generate_network_key(tmp_path / "k3")
    assert victim.read_bytes() == b"keep" and not (tmp_path / "k3").is_symlink()
    assert stat.S_IMODE((tmp_path / "k3").stat().st_mode) == 0o600


def test_a_restarted_nodes_epoch_is_strictly_newer_even_if_the_clock_went_back(tmp_path, monkeypatch):
    """claim_epoch: max(clock, last + 1), recorded in the state dir before it is used; and the node
    program takes its epoch from it."""
    from dfusion.run import measurements
    from dfusion.run.measurements import claim_epoch

    first = claim_epoch(tmp_path, "b", now_ns=5_000_000_000_000)
    assert first == 5_000_000_000_000 and (tmp_path / "b.epoch").read_text().strip() == str(first)
    assert claim_epoch(tmp_path, "b", now_ns=4_000_000_000_000) == first + 1          # the clock went back 1000 s
    assert claim_epoch(tmp_path, "b", now_ns=first) == first + 2                       # the same clock reading
    assert claim_epoch(tmp_path, "b", now_ns=6_000_000_000_000) == 6_000_000_000_000   # the clock is ahead again
    assert claim_epoch(tmp_path, "c", now_ns=1) == 1                                   # per node
    (tmp_path / "d.epoch").write_text("not a number")
    assert claim_epoch(tmp_path, "d", now_ns=7) == 7                                   # unreadable: the clock
    with pytest.raises(Exception):
        claim_epoch(tmp_path, "e", now_ns=2**63)

    # the node program: two incarnations of b with the wall clock set back 1 hour between them
    from dfusion.run.node_process import NodeProcess
    from dfusion.scenario import load_scenario
    from tests.run.test_processes import chain3

    sc = load_scenario(chain3(tmp_path))
    state = tmp_path / "state"
    real = time.time_ns()
    monkeypatch.setattr(measurements.time, "time_ns", lambda: real)
    one = NodeProcess(sc, "b", state_dir=state, run_id="r", measurements=[])
    monkeypatch.setattr(measurements.time, "time_ns", lambda: real - 3600 * 10**9)
    two = NodeProcess(sc, "b", state_dir=state, run_id="r", measurements=[])
    assert one.node.epoch == real and two.node.epoch == real + 1


def test_monitor_publications_are_keyed_for_the_network_and_the_run_and_validated():
    """Status's MAC covers the run and the network (a publication of another run with the same
    network key is rejected), and every field is validated (never an exception but MessageError)."""
    import msgpack
    import numpy as np

    from dfusion.errors import MessageError
    from dfusion.run.common import MAX_STATUS_BYTES, Status
    from dfusion.wire import FrameKey

    key = b"k" * 32
    mine = FrameKey(key, "net", "run-1")
    st = Status("a", 7, "run", 3, 0.3, np.arange(4.0), np.eye(4), stats={"messages_sent": 2})
    back = Status.decode(st.encode(mine), mine, 4)
    assert (back.node, back.epoch, back.k) == ("a", 7, 3) and np.array_equal(back.mean, st.mean)

    def reason(data, key=mine, dim=4):
        with pytest.raises(MessageError) as info:
            Status.decode(data, key, dim)
        return info.value.reason

    assert reason(st.encode(FrameKey(key, "net", "run-2"))) == "unauthenticated"    # another run, same key
    assert reason(st.encode(FrameKey(key, "other", "run-1"))) == "unauthenticated"  # another network
    assert reason(st.encode(FrameKey(b"x" * 32, "net", "run-1"))) == "unauthenticated"
    assert reason(st.encode(None)) == "unauthenticated"                              # no MAC
    assert reason(st.encode(mine), None) == "unauthenticated"                       # a MAC but no key
    assert reason(st.encode(mine), mine, 6) == "dimension"
    assert reason(b"\x00" * 10) == "malformed" and reason(b"\x00" * (MAX_STATUS_BYTES + 1)) == "oversized"
    old = msgpack.packb({"v": 1, "body": b"", "mac": None})
    assert reason(old) == "version"
    for bad in (Status("a", 0, "run", 3, 0.3, np.zeros(4), np.eye(4)),            # epoch 0
                Status("a", 7, "dance", 3, 0.3),                                    # phase
                Status("a", 7, "run", 3, float("nan"), np.zeros(4), np.eye(4)),     # time
                Status("a", 7, "run", 3, 0.3, np.zeros(4), np.eye(4) + np.triu(np.ones((4, 4)), 1)),  # asymmetric
                Status("a", 7, "run", 3, 0.3, np.full(4, np.inf), np.eye(4))):      # non-finite
        assert reason(bad.encode(mine)) == "malformed", bad


def test_a_node_process_reports_its_consistency_test_and_quarantines(tmp_path):
    """A node process publishes the totals of its consistency test of the neighbours'
    information (docs/clutter.md) with its counters; the monitor sums them per node and `dfusion
    run` prints a line for a node that quarantined a neighbour."""
    from types import SimpleNamespace

    from dfusion.run.monitor import run_table
    from dfusion.run.node_process import NodeProcess
    from dfusion.scenario import load_scenario
    from tests.run.test_processes import chain3

    proc = NodeProcess(load_scenario(chain3(tmp_path)), "b", start=0.0, measurements=[])
    guard = proc.node.guard
    assert guard is not None   # the network check is on by default
    rec = guard.links["a"]
    rec.tests, rec.failures, rec.quarantines = 12, 4, 1
    stats = proc.stats()
    assert (stats["guard_tests"], stats["guard_failures"], stats["quarantines"]) == (12, 4, 1)

    node = {"incarnations": 1, "measurements_replayed": 0, "measurements_lost": 0, "messages_rejected": 0,
            "liveliness_losses": 0, "finished": True, "guard_tests": 12, "guard_failures": 4, "quarantines": 1}
    text = run_table(SimpleNamespace(metrics={"run": {"nodes": {"b": node}}}))
    assert "b: 1 quarantines of a neighbour by the consistency test (4 of 12 tests failed)" in text


def test_status_limit_holds_the_longest_genuine_publication_and_nothing_of_a_mebibyte(tmp_path):
    """The largest publication a node of the chain can make (final phase: both estimates, every
    counter, a tree listing every node, every measurement time of the node lost) fits under
    status_limit; a 1 MiB one does not."""
    import numpy as np

    from dfusion.run.common import MAX_STATUS_BYTES, Status, TreeStatus, status_limit
    from dfusion.scenario import load_scenario
    from dfusion.wire import FrameKey
    from tests.run.test_processes import chain3

    sc = load_scenario(chain3(tmp_path, duration=30.0))
    n, names = sc.target.motion.dim, sorted(sc.nodes)
    lost = [float(t) for t in np.arange(0, sc.duration, 1 / max(s.rate for s in sc.nodes.values()))]
    stats = {f"counter_number_{i:02d}_of_a_long_name": 2**62 for i in range(60)}
    st = Status("a" * 20, 2**62, "final", sc.steps, sc.duration, np.random.default_rng(0).normal(size=n), np.eye(n),
                1e9, stats, lost, ("fused-output", np.ones(n), np.eye(n)),
                TreeStatus(2**40, names[0], names[1], tuple(names), tuple(names)))
    size = len(st.encode(FrameKey(b"k" * 32, "net", "run")))
    assert size < status_limit(sc) < 1 << 20 <= MAX_STATUS_BYTES, (size, status_limit(sc))


class _Sample:
    """What Zenoh hands a subscriber callback (key expression, payload, kind)."""

    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(data)


class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


def test_monitor_queue_is_bounded_in_bytes_and_forged_publications_take_no_space(tmp_path, monkeypatch):
    """Genuine publications beyond the byte bound push the oldest out (counted); forged and
    oversized ones are counted on arrival and never queued; the next poll reports them all."""
    import numpy as np

    from dfusion.run import monitor as mon_mod
    from dfusion.run.common import Status
    from dfusion.run.monitor import Monitor
    from dfusion.scenario import load_scenario
    from dfusion.wire import FrameKey
    from tests.run.test_processes import chain3

    sc = load_scenario(chain3(tmp_path))
    key, net = b"k" * 32, "net"
    data = Status("a", 7, "run", 3, 0.3, np.arange(4.0), np.eye(4), stats={"x": 1}).encode(FrameKey(key, net, "r"))
    monkeypatch.setattr(mon_mod, "MAX_PENDING_BYTES", 10 * len(data))
    with Monitor(sc, net, network_key=key, run="r") as mon:
        for _ in range(25):
            mon._on_sample(_Sample(f"dfusion/{net}/monitor/a", data))
            mon._on_sample(_Sample(f"dfusion/{net}/monitor/a", data[:-1] + bytes([data[-1] ^ 1])))   # forged
        mon._on_sample(_Sample(f"dfusion/{net}/monitor/a", bytes(1 << 20)))
        assert len(mon._queue) == 10 and mon._queued_bytes == 10 * len(data)
        q = mon.queue
        assert (q["shed"], q["shed_bytes"], q["peak_bytes"]) == (15, 15 * len(data), 10 * len(data))
        assert (q["oversized"], q["oversized_bytes"]) == (1, 1 << 20)
        assert mon.poll() == 10
        assert mon.rejections == {"queue-full": 15, "unauthenticated": 25, "oversized": 1}
        assert mon._queued_bytes == 0 and mon.records["a"].have[3]


def test_monitor_computes_one_hmac_per_publication(tmp_path, monkeypatch):
    """The MAC of a publication is checked once, on arrival: polling reads the authenticated body
    (it was computed twice, once in the callback and again in Status.decode)."""
    import numpy as np

    from dfusion.run import common
    from dfusion.run.common import Status
    from dfusion.run.monitor import Monitor
    from dfusion.scenario import load_scenario
    from dfusion.wire import FrameKey
    from tests.run.test_processes import chain3

    sc = load_scenario(chain3(tmp_path))
    key, net = b"k" * 32, "net"
    pubs = [Status("a", 7, "run", k, 0.1 * k, np.arange(4.0), np.eye(4)).encode(FrameKey(key, net, "r"))
            for k in range(5)]
    calls = []
    real = common._status_mac
    monkeypatch.setattr(common, "_status_mac", lambda k, body: calls.append(body) or real(k, body))
    with Monitor(sc, net, network_key=key, run="r") as mon:
        for data in pubs:
            mon._on_sample(_Sample(f"dfusion/{net}/monitor/a", data))
        assert mon.poll() == 5 and mon.rejected == 0
        assert len(calls) == 5 and mon.records["a"].have[:5].all()


def test_log_byte_cap_drops_and_counts_past_its_cap_but_keeps_errors():
    """A node process's log output is capped in bytes (``LogByteCap``): past the cap one line says
    so, lines below ERROR are dropped and counted, errors still written; the bytes are counted
    from the stream itself here, not from the filter's own counter."""
    import io
    import logging

    from dfusion.run.common import LogByteCap

    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    cap = LogByteCap(handler, max_bytes=1000)
    handler.addFilter(cap)
    logger = logging.getLogger("dfusion.test.logcap")
    logger.propagate = False
    logger.setLevel(logging.INFO)
    logger.addHandler(handler)
    try:
        for k in range(200):
            logger.info("rejected a message from b: %04d", k)   # 37 bytes a line with its newline
        logger.error("the node stopped")
    finally:
        logger.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    infos = [line for line in lines if line.startswith("INFO ")]
    assert len(infos) == 28                        # ceil(1000 / 37) lines: the cap is checked before a line
    assert sum(len(line) + 1 for line in infos) == 28 * 37
    assert cap.dropped == 200 - 28
    assert sum("reached its cap of 1000 bytes" in line for line in lines) == 1
    assert lines[-1] == "ERROR the node stopped"


def test_a_hosts_batch_of_publications_is_checked_one_by_one(tmp_path):
    """A host process sends its nodes' step publications together (one Zenoh put, on
    ``monitor/FIRST/batch``): each is authenticated and validated alone, a forged one is counted and
    dropped without its neighbours in the batch, the first must be the key's node, garbage and an
    oversized batch are refused on arrival."""
    import numpy as np

    from dfusion.run.common import MAX_STATUS_BATCH, Status, encode_status_batch, split_status_batch
    from dfusion.run.monitor import Monitor
    from dfusion.scenario import load_scenario
    from dfusion.wire import FrameKey
    from tests.run.test_processes import chain3

    sc = load_scenario(chain3(tmp_path))
    key, net = b"k" * 32, "net"
    fk = FrameKey(key, net, "r")
    pub = {(name, k): Status(name, 7, "run", k, 0.1 * k, np.arange(4.0) + k, np.eye(4)).encode(fk)
           for name in ("a", "b", "c") for k in range(3)}
    with pytest.raises(ValidationError):
        encode_status_batch([])
    with pytest.raises(ValidationError):
        encode_status_batch([b"x"] * (MAX_STATUS_BATCH + 1))
    assert split_status_batch(encode_status_batch([pub["a", 0], pub["b", 0]]), 4096) == [pub["a", 0], pub["b", 0]]
    forged = pub["c", 1][:-1] + bytes([pub["c", 1][-1] ^ 1])
    with Monitor(sc, net, network_key=key, run="r") as mon:
        limit = mon.max_status_bytes
        for k in range(3):
            mon._on_sample(_Sample(f"dfusion/{net}/monitor/a/batch",
                                   encode_status_batch([pub["a", k], pub["b", k], forged if k == 1 else pub["c", k]])),
                           batch=True)
        mon._on_sample(_Sample(f"dfusion/{net}/monitor/c/batch", encode_status_batch([pub["a", 2]])), batch=True)
        mon._on_sample(_Sample(f"dfusion/{net}/monitor/a/batch", b"\x93garbage"), batch=True)
        mon._on_sample(_Sample(f"dfusion/{net}/monitor/a/batch", bytes(limit * (MAX_STATUS_BATCH + 1) + 1)),
                       batch=True)
        mon._on_sample(_Sample(f"dfusion/{net}/monitor/a/batch", encode_status_batch([bytes(limit + 1)])), batch=True)
        assert mon.poll() == 8
        assert mon.rejections == {"unauthenticated": 1, "forged-sender": 1, "malformed": 1, "oversized": 2}, \
            mon.rejections
        assert mon.records["a"].have[:3].all() and mon.records["b"].have[:3].all()
        assert list(mon.records["c"].have[:3]) == [True, False, True]
        assert np.array_equal(mon.records["b"].mean[2], np.arange(4.0) + 2)
