"""A live node whose node file gives mutual TLS and a network key: reachable only with a certificate of the CA."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import zenoh
from rosbags.typesys import Stores, get_typestore

from dfusion.transport.zenoh import TlsFiles, ZenohConfig
from tests.ros2.scenarios import TWO_NODES

ROOT = Path(__file__).resolve().parents[2]
TS = get_typestore(Stores.ROS2_JAZZY)
def test_a_node_file_with_mutual_tls_and_a_network_key(tmp_path):
    certs = tmp_path / "certs"
    subprocess.run([sys.executable, "-m", "dfusion.run.certs", str(certs), "base", "viewer"], check=True,
                   env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True)
    (tmp_path / "network.key").write_bytes(os.urandom(32))
    (tmp_path / "s.toml").write_text(TWO_NODES.format(duration=3.0))
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    (tmp_path / "base.node.toml").write_text(f"""name = "base"
kind = "relay"
scenario = "s.toml"
duration = 3.0
start = {time.time() + 2.0!r}
[zenoh]
listen = ["tls/127.0.0.1:{port}"]
[security]
network_key_file = "network.key"
tls_ca = "certs/ca.pem"
tls_cert = "certs/base.pem"
tls_key = "certs/base.key"
[ros]
convention = "ros2dds"
[outputs]
diagnostics = "/diagnostics"
""")
    node = subprocess.Popen([sys.executable, str(ROOT / "nodes" / "relay.py"), str(tmp_path / "base.node.toml")],
                            env=dict(os.environ, PYTHONPATH=str(ROOT)), stderr=subprocess.PIPE, text=True)
    got: list[bytes] = []
    sessions = []
    try:
        tls = TlsFiles(str(certs / "ca.pem"), str(certs / "viewer.pem"), str(certs / "viewer.key"))
        viewer = zenoh.open(ZenohConfig(connect=(f"tls/127.0.0.1:{port}",), tls=tls).to_zenoh())
        sessions.append(viewer)
        sub = viewer.declare_subscriber("diagnostics", lambda s: got.append(s.payload.to_bytes()))
        clear = zenoh.open(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)).to_zenoh())   # no certificate
        sessions.append(clear)
        leaked: list[bytes] = []
        sub2 = clear.declare_subscriber("diagnostics", lambda s: leaked.append(s.payload.to_bytes()))
        _, err = node.communicate(timeout=30)
        assert node.returncode == 0, err[-2000:]
        time.sleep(0.2)
        sub.undeclare()
        sub2.undeclare()
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
        for s in sessions:
            s.close()
    diags = [TS.deserialize_cdr(b, "diagnostic_msgs/msg/DiagnosticArray") for b in got]
    assert len(diags) >= 3 and diags[-1].status[0].name == "dfusion/base"
    assert {kv.key: kv.value for kv in diags[-1].status[0].values}["phase"] == "final"
    assert leaked == []
