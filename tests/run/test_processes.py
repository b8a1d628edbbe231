"""Fusion nodes as real OS processes over Zenoh on loopback (dfusion run).

Every test cleans up its processes in a ``finally`` (the launcher's own
``finally`` kills every node group; tests that start processes themselves kill
them by pid). Scenarios are short and played faster than real time.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

from dfusion.cli import main  # noqa: E402
from dfusion.fusion import FusionNode  # noqa: E402
from dfusion.run.launcher import Launcher, Restart, RunOptions  # noqa: E402
from dfusion.sim import run_scenario  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402
from dfusion.transport.zenoh import link_key, open_session, ZenohConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

CHAIN3 = """
duration = {duration}
dt = 0.1
seed = 3
window = {window}

[target]
motion = "constant_velocity"
q = 0.05
initial_mean = [0.0, 0.0, 1.0, 0.0]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]

[[nodes]]
name = "a"
sensor = "position"
std = 0.5
rate = 5.0
send_period = 0.5

[[nodes]]
name = "b"
sensor = "position"
std = 1.0
rate = 2.0
send_period = 0.5
delay = 0.3

[[nodes]]
name = "c"
sensor = "position"
std = 0.8
rate = 5.0
send_period = 0.5

[[links]]
between = ["a", "b"]
latency = 0.02

[[links]]
between = ["b", "c"]
latency = 0.02
"""


def chain3(tmp_path: Path, duration: float = 4.0, window: int = 100) -> Path:
    path = tmp_path / "chain3.scenario.toml"
    path.write_text(CHAIN3.format(duration=duration, window=window))
    return path


def pid_alive(pid: int) -> bool:
    """True for a running process (a zombie counts as gone)."""
    try:
        import psutil
    except ImportError:
        from dfusion.run.supervision import pid_running

        return pid_running(pid)
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def start_cli_run(scenario: Path, run_dir: Path, timeout: float = 90.0, args: tuple[str, ...] = ()) -> subprocess.Popen:
    """``dfusion run SCENARIO --run-dir RUN_DIR [ARGS]`` as a process, returned once the run has started
    (every node up, the start time written). The caller kills it in a ``finally``."""
    launcher = subprocess.Popen([sys.executable, "-m", "dfusion.cli", "run", str(scenario), "--run-dir", str(run_dir),
                                 "--quiet", *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        deadline = time.monotonic() + timeout
        while not (run_dir / "start").exists():
            assert launcher.poll() is None, launcher.communicate()
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.05)
    except BaseException:
        launcher.kill()
        launcher.wait()
        raise
    return launcher


def node_pids(run_dir: Path) -> dict[str, int]:
    """Every process of the run but the launcher (nodes, and the warm standby once started)."""
    return {n: p for n, p in json.loads((run_dir / "pids.json").read_text()).items() if n != "launcher"}


def kill_pids(pids) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def test_run_ends_where_simulate_ends(tmp_path, capsys):
    """3-node chain without drops: every process's final estimate is the centralized one (and simulate's).
    Its stderr is not a terminal: the progress comes as lines (one at the end at least), as simulate's."""
    scenario = chain3(tmp_path)
    out_json, out_png = tmp_path / "run.json", tmp_path / "run.png"
    t0 = time.monotonic()
    rc = main(["run", str(scenario), "--speed", "4", "--json", str(out_json), "--plot", str(out_png),
               "--run-dir", str(tmp_path / "run")])
    wall = time.monotonic() - t0
    cap = capsys.readouterr()
    printed = cap.out
    assert rc == 0, printed
    steps = load_scenario(scenario).steps
    assert f"progress: {steps}/{steps} steps (100 %)" in cap.err and ", alive " in cap.err, cap.err
    assert cap.err.count(f"progress: {steps}/{steps} steps") == 1
    got = json.loads(out_json.read_text())
    ref = run_scenario(load_scenario(scenario)).metrics
    # run has no front-end counters (measurements_detail); --json adds the per-step series
    assert set(got) == (set(ref) - {"measurements_detail"}) | {"run", "series"}
    tr = got["traffic"]["network"]   # the counts add up for run too
    assert tr["sent"] + tr["duplicated"] == tr["delivered"] + tr["dropped"] + tr["in_flight"]
    assert got["traffic"]["fused"] + got["traffic"]["rejected"] + got["traffic"]["ignored"] == tr["delivered"]
    assert set(got["nodes"]) == set(ref["nodes"]) == {"a", "b", "c"}
    for name, v in got["nodes"].items():
        assert set(v) == set(ref["nodes"][name])
        assert v["final_gap"] < 1e-6, (name, v["final_gap"])
        assert ref["nodes"][name]["final_gap"] < 1e-6
        # real timing (loopback, about 1 ms) differs from the simulated links' (20 ms, and sends on the
        # step grid), so the path differs, not the end; on a 4 s run the start dominates the RMSE
        assert 0.5 < v["rmse"] / ref["nodes"][name]["rmse"] < 2.0
        assert v["messages"] > 0 and v["rejected"] == 0
    assert got["centralized"] == ref["centralized"]   # the same world, the same EKF
    assert got["measurements"] == ref["measurements"]
    assert got["run"]["measurements_lost"] == 0
    for name, v in got["run"]["nodes"].items():   # the byte bounds' counters, none hit on a calm run
        assert v["log_lines_dropped"] == 0 and v["blocks_too_far_ahead"] == 0 and v["receive_queue_shed"] == 0, v
    assert "node" in printed and "centralized" in printed and out_png.stat().st_size > 1000
    print(f"run ends where simulate ends: {wall:.1f} s wall; RMSE run/simulate: "
          + ", ".join(f"{n} {v['rmse']:.3f}/{ref['nodes'][n]['rmse']:.3f}" for n, v in got["nodes"].items()))


def test_sigkilled_node_restarts_and_the_network_reconverges(tmp_path):
    """b is SIGKILLed at t=2 s and started again (new epoch): its log is replayed, the neighbours
    see it go and come back, and every node ends on the centralized estimate of what was measured."""
    scenario = chain3(tmp_path, duration=12.0, window=200)   # the window spans the run: exact re-convergence
    run_dir = tmp_path / "run"
    opts = RunOptions(scenario=str(scenario), speed=2.0, run_dir=str(run_dir), restarts=[Restart("b", 2.0)])
    result = Launcher(opts).run()
    assert result is not None
    m = result.metrics
    b = m["run"]["nodes"]["b"]
    assert b["incarnations"] == 2, m["run"]
    assert b["measurements_replayed"] > 0
    for name, v in m["nodes"].items():
        assert v["final_gap"] < 1e-6, (name, v["final_gap"], m["run"])
    logs = {n: (run_dir / "logs" / f"{n}.log").read_text() for n in "abc"}
    for n in "ac":   # the neighbours detected the loss and the return (liveliness)
        assert "neighbour b lost" in logs[n] and "neighbour b is back" in logs[n], logs[n]
    assert "replayed" in logs["b"] and "incarnation 2" in logs["b"]
    state = (run_dir / "state" / "b.measurements.jsonl").read_text().splitlines()
    assert json.loads(state[0])["node"] == "b" and len(state) > 1 + b["measurements_replayed"]


def test_sigterm_to_the_launcher_stops_everything_within_2s(tmp_path):
    scenario = chain3(tmp_path, duration=60.0)
    run_dir = tmp_path / "run"
    launcher = start_cli_run(scenario, run_dir)
    pids: list[int] = []
    try:
        time.sleep(0.5)
        pids = list(node_pids(run_dir).values())
        assert len(pids) >= 3 and all(pid_alive(p) for p in pids)
        t0 = time.monotonic()
        launcher.send_signal(signal.SIGTERM)
        launcher.wait(timeout=10)
        deadline = t0 + 2.0
        while any(pid_alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.01)
        elapsed = time.monotonic() - t0
        assert elapsed < 2.0, f"stopping took {elapsed:.2f} s"
        assert not any(pid_alive(p) for p in pids)
        assert launcher.returncode == 128 + signal.SIGTERM
        for n in "abc":   # the nodes themselves stopped on SIGTERM (closing their sessions)
            assert "stopping: SIGTERM" in (run_dir / "logs" / f"{n}.log").read_text()
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        kill_pids(pids)


def test_authenticated_network_rejects_a_stranger(tmp_path):
    """With a network key, nodes fuse each other's messages; a stranger publishing forged,
    unauthenticated messages on a link key is rejected and changes nothing. (The nodes also
    take their measurements from a recording here.)"""
    scenario = chain3(tmp_path, duration=6.0)
    key_file = tmp_path / "network.key"
    key_file.write_bytes(os.urandom(32).hex().encode() + b"\n")
    # the nodes read their measurements from one recording (JSON lines, every node's), not the world
    from dfusion.run.measurements import save_recording, world_measurements

    sc = load_scenario(scenario)
    recording = tmp_path / "all.jsonl"
    recording.write_text("".join(save_recording(tmp_path / f"{n}.jsonl", n, world_measurements(sc, n)).read_text()
                                 for n in sorted(sc.nodes)))
    opts = RunOptions(scenario=str(scenario), speed=3.0, run_dir=str(tmp_path / "run"),
                      network_key_file=str(key_file), node_args=["--measurements", str(recording)],
                      emulate_links=False)   # the real network only (the default emulates the links)
    launcher = Launcher(opts)
    box: dict = {}
    thread = threading.Thread(target=lambda: box.setdefault("result", launcher.run()), daemon=True)
    thread.start()
    forged_sent = 0
    try:
        deadline = time.monotonic() + 60
        while launcher.start is None or launcher.now() < 0.5:
            assert thread.is_alive(), "the launcher stopped early"
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.02)
        # a stranger pretending to be b, without the key, with an absurdly confident "measurement"
        fake = FusionNode("b", ["a", "c"], sc.target.motion, window=100,
                          prior=(0.0, sc.target.initial_mean, sc.target.initial_cov))
        fake.predict(1.0)
        fake.update(1.0, [100.0, -100.0], sc.nodes["b"].sensor)
        with open_session(ZenohConfig(connect=[launcher.endpoints["a"]])) as z:
            time.sleep(0.3)
            for _ in range(5):
                z.put(link_key(launcher.network, "b", "a"), fake.message_to("a"))
                forged_sent += 1
                time.sleep(0.05)
        thread.join(timeout=60)
        assert not thread.is_alive()
    finally:
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    result = box["result"]
    assert result is not None
    m = result.metrics
    assert m["nodes"]["a"]["rejected"] >= 1, m["run"]
    assert m["run"]["nodes"]["a"]["messages_rejected"] >= 1
    for name, v in m["nodes"].items():
        assert v["final_gap"] < 1e-6, (name, v["final_gap"])
        assert v["messages"] > 0
    assert forged_sent == 5
    assert m["run"]["links_emulated"] is False and m["run"]["network_key"] == "given"
    assert m["run"]["nodes"]["b"]["measurements_fused"] == len(world_measurements(sc, "b"))


PAIR = """
duration = 60.0
dt = 0.1
seed = 5
[target]
initial_mean = [0.0, 0.0, 1.0, 0.0]
[[nodes]]
name = "a"
sensor = "position"
rate = 5.0
[[nodes]]
name = "b"
sensor = "position"
rate = 5.0
[[links]]
between = ["a", "b"]
"""


def test_node_program_stops_on_sigterm_even_with_a_frozen_neighbour(tmp_path):
    """The node program (python -m dfusion.run.node_process): SIGTERM stops the node within 2 s with status 0 although its
    neighbour is frozen (SIGSTOP). (A close blocked by a full send queue towards a frozen
    peer is tested in test_zenoh_transport.)"""
    from dfusion.transport.zenoh import free_tcp_endpoints

    scenario = tmp_path / "pair.scenario.toml"
    scenario.write_text(PAIR)
    ea, eb = free_tcp_endpoints(2)
    start = time.time() + 3.0
    procs = {}
    logs = {}
    try:
        for name, me, other in (("a", ea, eb), ("b", eb, ea)):
            logs[name] = (tmp_path / f"{name}.log").open("w")
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "dfusion.run.node_process", "--scenario", str(scenario), "--node", name,
                 "--network", f"pair{os.getpid()}", "--listen", me, "--connect", other, "--start-time", repr(start),
                 "--speed", "5"],
                stdout=logs[name], stderr=subprocess.STDOUT, start_new_session=True)
        while time.time() < start + 1.0:   # both running, exchanging messages
            assert all(p.poll() is None for p in procs.values()), (tmp_path / "a.log").read_text()
            time.sleep(0.05)
        os.kill(procs["b"].pid, signal.SIGSTOP)
        time.sleep(1.0)   # a keeps sending to b (its liveliness lasts the 3 s lease)
        t0 = time.monotonic()
        procs["a"].send_signal(signal.SIGTERM)
        rc = procs["a"].wait(timeout=10)
        elapsed = time.monotonic() - t0
        assert rc == 0
        assert elapsed < 2.0, f"node a took {elapsed:.2f} s to stop"
        assert "stopping: SIGTERM" in (tmp_path / "a.log").read_text()
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()


def test_recordings_and_the_state_log(tmp_path):
    """Recordings (.jsonl, .npz) hold the world's measurements exactly; the state log survives a
    torn last line and starts afresh for another run."""
    from dfusion.run.measurements import load_recording, MeasurementLog, save_recording, world_measurements

    sc = load_scenario(chain3(tmp_path))
    ref = world_measurements(sc, "b")
    assert ref and all(m.arrival >= m.t for m in ref)
    for suffix in (".jsonl", ".npz"):
        back = load_recording(save_recording(tmp_path / f"b{suffix}", "b", ref), "b")
        assert [(m.t, m.arrival) for m in back] == [(m.t, m.arrival) for m in ref]
        assert all(np.array_equal(x.z, y.z) for x, y in zip(back, ref))
    with MeasurementLog(tmp_path / "state", "b", "run-1") as log:
        for m in ref[:3]:
            log.append(m)
    with (tmp_path / "state" / "b.measurements.jsonl").open("a") as f:
        f.write('{"t": 9.9, "z": [1.0')   # the process died while writing
    again = MeasurementLog(tmp_path / "state", "b", "run-1")
    assert [m.t for m in again.entries] == [m.t for m in ref[:3]]
    again.append(ref[3])
    again.close()
    with MeasurementLog(tmp_path / "state", "b", "run-1") as third:
        assert [m.t for m in third.entries] == [m.t for m in ref[:4]]
    other = MeasurementLog(tmp_path / "state", "b", "run-2")
    assert other.entries == []
    other.close()
