"""ZenohTransport on loopback: delivery, rates, liveliness, endpoints, closing."""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from dfusion.errors import ValidationError  # noqa: E402
from dfusion.transport.zenoh import TlsFiles, ZenohConfig, ZenohTransport  # noqa: E402
from dfusion.transport.zenoh import free_tcp_endpoints, link_key, open_session  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
_count = iter(range(10**6))


def network() -> str:
    return f"t{os.getpid()}n{next(_count)}"


def wait_for(cond, timeout=5.0, step=0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


@pytest.fixture
def pair():
    """Two transports, a <-> b, joined by explicit loopback endpoints; always closed."""
    net = network()
    ea, eb = free_tcp_endpoints(2)
    made = []
    try:
        a = ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea]))
        made.append(a)
        b = ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea]))
        made.append(b)
        assert wait_for(lambda: a.alive("b") and b.alive("a")), "the two sessions never saw each other"
        yield a, b, (net, ea, eb)
    finally:
        for t in made:
            t.close()


def test_delivery_both_ways(pair):
    a, b, _ = pair
    a.send("a", "b", b"hello", 1.5)
    b.send("b", "a", bytes(range(256)) * 300, 2.5)   # 76.8 kB: more than the lowlatency limit
    assert wait_for(lambda: b.pending("b") == 1 and a.pending("a") == 1)
    (d,) = b.receive("b")
    assert (d.src, d.dst, d.data, d.t_sent) == ("a", "b", b"hello", 1.5)
    (e,) = a.receive("a")
    assert e.data == bytes(range(256)) * 300 and e.t_sent == 2.5 and e.src == "b"
    assert b.receive("b") == []   # each copy is returned once
    assert a.stats.links[("a", "b")].sent == 1 and b.stats.links[("a", "b")].delivered == 1
    assert b.stats.total.bytes_delivered == 5


def test_receive_until_uses_the_clock():
    net = network()
    ea, eb = free_tcp_endpoints(2)
    now = [10.0]
    with ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea])) as a, \
            ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea]), clock=lambda: now[0]) as b:
        assert wait_for(lambda: a.alive("b"))
        a.send("a", "b", b"x", 0.0)
        assert wait_for(lambda: b.pending("b") == 1)
        assert b.receive("b", until=9.0) == []
        (d,) = b.receive("b", until=10.0)
        assert d.t_arrival == 10.0


def test_no_loss_on_loopback_at_a_moderate_rate(pair):
    """300 messages of 7 kB (a 100-state window) at about 300 per second, 150 times what a
    node sends on a link: all arrive, in order (at 1000/s a CPU-starved CI machine can drop)."""
    a, b, _ = pair
    n, rate = 300, 300.0
    payloads = [i.to_bytes(4, "little") + bytes(7000) for i in range(n)]
    got = []
    t0 = time.monotonic()
    for i, p in enumerate(payloads):
        a.send("a", "b", p, float(i))
        while time.monotonic() < t0 + (i + 1) / rate:
            got += b.receive("b")
            time.sleep(0.0002)
    assert wait_for(lambda: b.pending("b") + len(got) >= n, timeout=5)
    got += b.receive("b")
    assert [d.data for d in got] == payloads
    assert a.stats.total.dropped == 0


def test_wait_wakes_on_arrival(pair):
    a, b, _ = pair
    # Liveliness events may still be arriving after the fixture saw both tokens (b's own
    # token, a's token from the subscriber and from the initial query): each wakes wait()
    # too. Once they are applied and nothing else is coming, wait() times out.
    assert wait_for(lambda: (b.poll(), b.wait(0.01))[1] is False), "wait() never timed out"
    a.send("a", "b", b"ping", 0.0)
    t0 = time.monotonic()
    assert b.wait(10.0) is True
    # woken by the arrival, not by the timeout (generous bound: CI machines are loaded)
    assert time.monotonic() - t0 < 5.0
    assert len(b.receive("b")) == 1


def test_liveliness_loss_and_return_are_detected_and_logged(caplog):
    net = network()
    ea, eb = free_tcp_endpoints(2)
    events = []
    a = ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea]))
    b = None
    try:
        a.on_liveliness(lambda name, up: events.append((name, up)))
        b = ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea]))
        assert wait_for(lambda: a.alive("b"))
        with caplog.at_level(logging.INFO, logger="dfusion.transport.zenoh"):
            b.close()
            assert wait_for(lambda: not a.alive("b"), timeout=3), "loss of b not detected"
            b = ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea]))
            assert wait_for(lambda: a.alive("b"), timeout=5), "return of b not detected"
        assert ("b", False) in events and events[-1] == ("b", True)
        text = caplog.text
        assert "neighbour b lost" in text and "neighbour b is back" in text
        assert any(r.levelno == logging.WARNING and "lost" in r.getMessage() for r in caplog.records)
    finally:
        a.close()
        if b is not None:
            b.close()


def test_two_sessions_joined_only_by_explicit_endpoints():
    """The documented example: A listens on tcp/127.0.0.1:P, B connects to it; scouting is off.

    A third session with the default configuration (loopback, no connect) discovers
    neither: nothing is found by multicast or gossip.
    """
    net = network()
    (ep,) = free_tcp_endpoints(1)
    cfg_a = ZenohConfig(listen=[ep])                  # listens only
    cfg_b = ZenohConfig(listen=[], connect=[ep])      # connects only (listens on a free loopback port)
    assert cfg_a.to_zenoh().get_json("scouting/multicast/enabled") == "false"
    assert cfg_a.to_zenoh().get_json("transport/unicast/lowlatency") == "false"
    with ZenohTransport(net, {"a": ["b"]}, cfg_a) as a, ZenohTransport(net, {"b": ["a"]}, cfg_b) as b, \
            ZenohTransport(net, {"c": ["a"]}, ZenohConfig()) as c:
        assert wait_for(lambda: a.alive("b") and b.alive("a"))
        a.send("a", "b", b"to b", 0.0)
        b.send("b", "a", b"to a", 0.0)
        assert wait_for(lambda: a.pending("a") == 1 and b.pending("b") == 1)
        time.sleep(0.2)
        assert not c.alive("a") and not a.alive("c")
        assert [d.data for d in a.receive("a")] == [b"to a"]
        assert [d.data for d in b.receive("b")] == [b"to b"]


def test_close_does_not_hang_with_a_frozen_peer_and_reconnects_in_flight():
    """A peer process is frozen (SIGSTOP) and another endpoint never answers: close() is quick."""
    net = network()
    ea, eb, dead = free_tcp_endpoints(3)
    code = textwrap.dedent(f"""
        import sys, time
        from dfusion.transport.zenoh import ZenohTransport, ZenohConfig
        with ZenohTransport({net!r}, {{"b": ["a"]}}, ZenohConfig(listen=[{eb!r}], connect=[{ea!r}])) as t:
            print("up", flush=True)
            time.sleep(60)
    """)
    peer = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    a = None
    try:
        a = ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea], connect=[eb, dead]))
        assert peer.stdout.readline().strip() == "up"
        assert wait_for(lambda: a.alive("b"), timeout=10)
        os.kill(peer.pid, signal.SIGSTOP)
        for i in range(50):
            a.send("a", "b", bytes(20000), float(i))   # never blocks, even towards a frozen peer
        t0 = time.monotonic()
        a.close()
        assert time.monotonic() - t0 < 2.0
    finally:
        if a is not None:
            a.close()
        os.kill(peer.pid, signal.SIGKILL)
        peer.wait(5)


def test_a_process_with_an_open_transport_exits_when_it_closes_it():
    net = network()
    code = textwrap.dedent(f"""
        from dfusion.transport.zenoh import ZenohTransport
        t = ZenohTransport({net!r}, {{"a": ["b"]}})
        t.send("a", "b", b"x", 0.0)
        t.close()
        print("done", flush=True)
    """)
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0 and "done" in out.stdout, out.stderr
    assert time.monotonic() - t0 < 15


def test_stranger_on_the_key_space_is_only_delivered_as_bytes(pair):
    """The transport does not judge content: a stranger's put on a link key reaches the node,
    which must authenticate it (tested with real nodes in test_run_processes)."""
    a, b, (net, ea, _) = pair
    with open_session(ZenohConfig(connect=[ea])) as z:
        assert wait_for(lambda: a.alive("b"))
        time.sleep(0.2)
        z.put(link_key(net, "b", "a"), b"forged")
        assert wait_for(lambda: a.pending("a") == 1)
    (d,) = a.receive("a")
    assert d.data == b"forged" and d.src == "b"
    assert d.t_sent != d.t_sent   # no attachment: NaN


def test_a_check_drops_garbage_in_the_callback_before_the_queue(pair):
    """With a node's cheap check registered (FusionNode.check_frame), garbage, forged and oversized
    copies never reach the queue (so a flood cannot push genuine messages out of it) and are not
    delivered: they are counted by reason; genuine messages pass."""
    from dfusion.fusion import FusionNode
    from dfusion.models import ConstantVelocity

    a, b, (net, ea, _) = pair
    key = b"k" * 32

    def node(name, other, k=key):
        return FusionNode(name, [other], ConstantVelocity(2, 0.1), window=20,
                          prior=(0.0, [0.0] * 4, [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]),
                          network_key=k, network=net, run="r")

    na, nb, stranger = node("a", "b"), node("b", "a"), node("b", "a", b"x" * 32)
    a.set_check("a", na.check_frame, max_bytes=1000)
    with open_session(ZenohConfig(connect=[ea])) as z:
        time.sleep(0.2)
        for frame in [b"garbage"] * 5 + [stranger.message_to("a")] * 3 + [b"DF" + bytes(2000)]:
            z.put(link_key(net, "b", "a"), frame)
        b.send("b", "a", nb.message_to("a"), 0.0)
        assert wait_for(lambda: a.pending("a") == 1 and sum(a._rejected["a"].values()) == 9)
    counts, detail = a.take_rejections("a")
    assert counts == {"malformed": 5, "unauthenticated": 3, "oversized": 1}, counts
    assert a.take_rejections("a") == ({}, "")   # taken once
    (d,) = a.receive("a")
    assert d.checked   # the check ran on these bytes: the node need not compute the MAC again
    assert na.receive(d.data, checked=d.checked) == 0 and na.stats.messages_received == 1   # the genuine one
    na.count_rejections(counts, detail)
    assert na.stats.rejections == counts and na.stats.rejected_on_arrival == na.stats.messages_rejected == 9
    assert a.stats.total.delivered == 1
    a.set_check("a", None)   # without a check a copy arrives unchecked (the node's receive checks it all)
    b.send("b", "a", b"unchecked", 0.0)
    assert wait_for(lambda: a.pending("a") == 1)
    (d,) = a.receive("a")
    assert not d.checked


@pytest.mark.parametrize("bad", ["", "a/b", "x*", "alive", "monitor", "has space"])
def test_names_are_checked(bad):
    with pytest.raises(ValidationError):
        ZenohTransport(bad or "", {"a": ["b"]}) if bad in ("", "a/b") else ZenohTransport("net", {bad: ["b"]})


def test_lowlatency_is_refused():
    with pytest.raises(ValidationError, match="lowlatency"):
        ZenohConfig(extra={"transport/unicast/lowlatency": True})


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    from tests.helpers.pki import make_pki

    return make_pki(tmp_path_factory.mktemp("pki"))


def test_tls_settings_are_checked(pki, tmp_path):
    tls = pki.member("a")
    cfg = ZenohConfig(tls=tls).to_zenoh()
    assert cfg.get_json("listen/endpoints") == '["tls/127.0.0.1:0"]'
    assert cfg.get_json("transport/link/tls/enable_mtls") == "true"
    assert cfg.get_json("transport/link/tls/connect_certificate") == f'"{tls.cert}"'
    with pytest.raises(ValidationError, match="nothing in clear"):
        ZenohConfig(listen=["tcp/127.0.0.1:0"], tls=tls)
    with pytest.raises(ValidationError, match="nothing in clear"):
        ZenohConfig(listen=["tls/127.0.0.1:0"], connect=["tcp/127.0.0.1:7447"], tls=tls)
    with pytest.raises(ValidationError, match="not extra"):
        ZenohConfig(tls=tls, extra={"transport/link/tls/enable_mtls": False})
    with pytest.raises(ValidationError, match="No such file"):
        TlsFiles(str(tmp_path / "missing.pem"), tls.cert, tls.key)
    (tmp_path / "junk.pem").write_text("not a certificate")
    with pytest.raises(ValidationError, match="not PEM"):
        TlsFiles(tls.ca, str(tmp_path / "junk.pem"), tls.key)
    assert free_tcp_endpoints(1, scheme="tls")[0].startswith("tls/127.0.0.1:")


def test_mutual_tls_refuses_strangers(pki):
    """Two members (certificates of the run's CA) talk over tls/ endpoints. A stranger with only the
    CA certificate, or with a certificate of another CA, or speaking plain TCP to the same port,
    hears nothing (no liveliness token, no message) and its forged message reaches nobody; a
    third member connecting the same way hears both (the control)."""
    from tests.helpers.pki import listen_in, strangers

    net = network()
    ea, eb = free_tcp_endpoints(2, scheme="tls")
    with ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea], tls=pki.member("a"))) as a, \
            ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea], tls=pki.member("b"))) as b:
        assert wait_for(lambda: a.alive("b") and b.alive("a")), "the two members never saw each other"
        stop = False

        def chatter():
            while not stop:
                a.send("a", "b", b"secret", 1.0)
                time.sleep(0.05)

        import threading

        th = threading.Thread(target=chatter, daemon=True)
        th.start()
        try:
            heard = {}
            for label, cfg in strangers(pki).items():
                heard[label] = listen_in([ea, eb], net, 1.0, forge=(link_key(net, "b", "a"), b"forged"), **cfg)
            heard["plain TCP to the TLS ports"] = listen_in([ea.replace("tls/", "tcp/"), eb.replace("tls/", "tcp/")],
                                                            net, 1.0, forge=(link_key(net, "b", "a"), b"forged"))
            member = listen_in([ea], net, 1.0, tls=pki.member("member"))
        finally:
            stop = True
            th.join()
        assert {k: v for k, v in heard.items() if v} == {}
        assert f"alive dfusion/{net}/alive/a" in member and f"data {link_key(net, 'a', 'b')}" in member
        got = a.receive("a")
        assert [d.data for d in got if d.data == b"forged"] == [], "a stranger's message reached a member"


def test_receive_queue_is_bounded_in_bytes(monkeypatch):
    """Copies nobody receives pile up to MAX_QUEUE_BYTES, then the oldest go (counted in the link's
    dropped and the node's queue report); what is left is the newest, in order."""
    from dfusion.transport import zenoh as zmod

    net = network()
    ea, eb = free_tcp_endpoints(2)
    size, bound = 10_000, 50_000
    monkeypatch.setattr(zmod, "MAX_QUEUE_BYTES", bound)
    with ZenohTransport(net, {"a": ["b"]}, ZenohConfig(listen=[ea])) as a, \
            ZenohTransport(net, {"b": ["a"]}, ZenohConfig(listen=[eb], connect=[ea])) as b:
        assert wait_for(lambda: a.alive("b") and b.alive("a"))
        for i in range(20):
            a.send("a", "b", i.to_bytes(4, "little") + bytes(size - 4), float(i))
            time.sleep(0.005)
        assert wait_for(lambda: b.queue_report("b")["shed"] == 15)
        rep = b.queue_report("b")
        assert rep == {"queued_bytes": 5 * size, "peak_bytes": 5 * size, "shed": 15, "shed_bytes": 15 * size}
        got = b.receive("b")
        assert [int.from_bytes(d.data[:4], "little") for d in got] == list(range(15, 20))
        assert b.stats.links[("a", "b")].dropped == 15 and b.queue_report("b")["queued_bytes"] == 0


def test_line_budget_holds_back_a_flapping_name_and_says_so():
    from dfusion.transport.base import LineBudget

    now = [0.0]
    budget = LineBudget(1.0, clock=lambda: now[0])
    assert budget.allow("b:lost") == (True, 0) and budget.allow("b:back") == (True, 0)   # a loss and a return
    for _ in range(50):   # a flapping token: 50 more losses within the second
        now[0] += 0.01
        assert budget.allow("b:lost") == (False, 0)
    now[0] = 1.5
    assert budget.allow("b:lost") == (True, 50) and budget.held_back == 50
    assert LineBudget.suffix(50) == " (50 earlier changes not logged)" and LineBudget.suffix(0) == ""
