"""Ports that cannot be taken (dfusion.run.endpoints): a squatter with a plain socket never stops a run.

Real processes on loopback. The squatter is what any local user can do: read every command
line, the run directory's files and the registry as soon as they appear, and bind every
port it finds there; and bind a node's port the moment the node is SIGKILLed.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from dfusion.run.endpoints import EndpointRegistry  # noqa: E402
from dfusion.run.launcher import Launcher, RunOptions  # noqa: E402
from dfusion.run.supervision import RestartPolicy  # noqa: E402

from tests.run.test_supervision import scenario, start_in_thread, wait_until  # noqa: E402

PORT = re.compile(r"127\.0\.0\.1:(\d+)")


class Squatter:
    """Binds (and listens on) every loopback port it sees advertised, with ``SO_REUSEADDR`` as a
    determined squatter would; remembers which it could take."""

    def __init__(self, launcher: Launcher) -> None:
        self.launcher = launcher
        self.taken: dict[int, socket.socket] = {}
        self.refused: set[int] = set()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._watch, daemon=True)

    def grab(self, port: int) -> bool:
        if port in self.taken or port in self.refused:
            return port in self.taken
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen(8)
        except OSError:
            s.close()
            self.refused.add(port)
            return False
        self.taken[port] = s
        return True

    def _advertised(self) -> set[int]:
        text = []
        run_dir = self.launcher.run_dir
        for pid in list(self.launcher.spawned):
            try:
                text.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
            except OSError:
                pass
        for path in [run_dir / "run.json", *(run_dir / "commands").glob("*.sh"),
                     *(run_dir / "endpoints").glob("*.json")]:
            try:
                text.append(path.read_text())
            except OSError:
                pass
        return {int(p) for t in text for p in PORT.findall(t)}

    def _watch(self) -> None:
        while not self.stop.is_set():
            for port in self._advertised():
                self.grab(port)
            time.sleep(0.005)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        for s in self.taken.values():
            s.close()


def test_squatted_ports_before_the_start_and_after_a_crash(tmp_path):
    """Every port a node or the monitor advertises is bound already (the squatter takes none
    before or during the run); b SIGKILLed, its old port squatted at once: the supervisor
    restarts it on a fresh port and every node ends exact (linear chain, window over the run)."""
    run_dir = tmp_path / "run"
    launcher = Launcher(RunOptions(scenario=str(scenario(tmp_path, 8.0)), speed=2.0, run_dir=str(run_dir),
                                   supervision=RestartPolicy(backoff=0.3)))
    squatter = Squatter(launcher)
    squatter.thread.start()
    thread, box = start_in_thread(launcher)
    registry = EndpointRegistry(run_dir)
    try:
        wait_until(lambda: launcher.start is not None and launcher.now() > 1.5, 90, "the run", thread)
        assert not squatter.taken, f"advertised ports were free: {sorted(squatter.taken)}"
        old = registry.endpoint("b")
        old_port = int(old.rsplit(":", 1)[1])
        assert old_port in squatter.refused   # seen, and already bound when seen
        pid = launcher.procs["b"].popen.pid
        os.kill(pid, signal.SIGKILL)   # a crash
        deadline = time.monotonic() + 5
        while not squatter.grab(old_port):   # bound the moment the kernel frees it
            squatter.refused.discard(old_port)
            assert time.monotonic() < deadline, "b's old port never became free"
            time.sleep(0.001)
        wait_until(lambda: registry.endpoint("b") not in (None, old), 60, "b's fresh endpoint", thread)
        thread.join(120)
        assert not thread.is_alive(), "the run did not end"
    finally:
        squatter.close()
        if thread.is_alive():
            launcher.request_stop("test cleanup")
            thread.join(30)
    assert "error" not in box, box.get("error")
    result = box["result"]
    assert result is not None
    run = result.metrics["run"]
    taken_while_live = set(squatter.taken) - {old_port}
    assert not taken_while_live, f"the squatter took live ports {sorted(taken_while_live)}"
    hosts = run["endpoints"]["hosts"]
    assert hosts["b"][0] == old and len(hosts["b"]) == 2 and hosts["b"][1] != old, hosts
    assert run["endpoints"]["fresh_endpoints"] == 1 and run["endpoints"]["monitor"]
    b = run["supervision"]["nodes"]["b"]
    assert b["exits"] == ["killed by SIGKILL"] and b["restarts"] == 1 and b["back_after_s"], b
    assert run["nodes"]["b"]["incarnations"] == 2
    assert not run["failures"], run["failures"]
    for name, v in result.metrics["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
    info = json.loads((run_dir / "run.json").read_text())
    assert info["monitor_endpoint"] == run["endpoints"]["monitor"]


def test_a_taken_listen_port_is_a_one_line_error(tmp_path):
    """A node given an explicit ``--listen`` port someone holds exits with status 2 and one clear line
    (no traceback)."""
    import subprocess
    import sys

    from tests.run.test_processes import ROOT

    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    port = s.getsockname()[1]
    try:
        proc = subprocess.run([sys.executable, "-m", "dfusion.run.node_process", "--scenario",
                               str(scenario(tmp_path, 2.0)), "--node", "a", "--listen", f"tcp/127.0.0.1:{port}"],
                              capture_output=True, text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    finally:
        s.close()
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert f"127.0.0.1:{port}" in proc.stderr and "Address already in use" in proc.stderr, proc.stderr


def test_registry_entries_and_a_lock_held_too_long(tmp_path, caplog):
    """Entries are read back as written (a missing or torn one is None); a registry lock held by
    a frozen process does not stop a node: after the timeout it registers without it, with a warning."""
    from dfusion.run.supervision import FileLock

    reg = EndpointRegistry(tmp_path)
    assert reg.endpoint("a") is None
    reg.register("host0", ["a", "b"], "tcp/127.0.0.1:4242")
    assert reg.endpoints(["a", "b", "c"]) == {"a": "tcp/127.0.0.1:4242", "b": "tcp/127.0.0.1:4242"}
    assert reg.entry("a")["host"] == "host0" and reg.entry("a")["pid"] == os.getpid()
    (reg.dir / "c.json").write_text('{"endpoint": ')   # torn
    assert reg.endpoint("c") is None
    frozen = FileLock(reg.lock_path)
    assert frozen.acquire()
    try:
        t0 = time.monotonic()
        with caplog.at_level("WARNING", logger="dfusion.run.endpoints"), reg.lock(timeout=0.3) as lock:
            assert not lock.held and time.monotonic() - t0 >= 0.3
        assert "registering without the lock" in caplog.text
    finally:
        frozen.release()
    with reg.lock(timeout=0.3) as lock:
        assert lock.held
