"""Supervision of the node processes of ``dfusion run`` (dfusion.run.supervision and the launcher).

Real processes on loopback. The launcher's own ``finally`` stops every node; tests that
start processes themselves kill them by pid in a ``finally``.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from dfusion.run.launcher import Launcher, RunOptions  # noqa: E402
from dfusion.run.monitor import run_table  # noqa: E402
from dfusion.run.supervision import (  # noqa: E402
    EXIT_ALREADY_RUNNING,
    EXIT_NO_LAUNCHER,
    FileLock,
    LauncherWatch,
    RestartPolicy,
    lock_holder,
)

from tests.run.test_processes import CHAIN3, ROOT, kill_pids, node_pids, pid_alive, start_cli_run  # noqa: E402


def scenario(tmp_path: Path, duration: float, *, dt: float = 0.1, window: int = 200) -> Path:
    """The 3-node chain of test_processes (linear: exact re-convergence), its window spanning the run."""
    path = tmp_path / "chain3.scenario.toml"
    path.write_text(CHAIN3.format(duration=duration, window=window).replace("dt = 0.1", f"dt = {dt}"))
    return path


def start_in_thread(launcher: Launcher) -> tuple[threading.Thread, dict]:
    box: dict = {}

    def target():
        try:
            box["result"] = launcher.run()
        except BaseException as exc:   # reported by the test
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, box


def wait_until(cond, timeout: float, what: str, thread: threading.Thread | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert thread is None or thread.is_alive(), f"the launcher stopped while waiting for {what}"
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_restart_policy_backoff_doubles_up_to_its_maximum():
    pol = RestartPolicy(backoff=0.5, backoff_max=3.0)
    assert [pol.delay(n) for n in range(1, 6)] == [0.5, 1.0, 2.0, 3.0, 3.0]
    with pytest.raises(Exception):
        RestartPolicy(max_restarts=-1)
    with pytest.raises(Exception):
        RestartPolicy(backoff=2.0, backoff_max=1.0)


def test_locks_follow_their_holders_life(tmp_path):
    """A lock is held while its holder lives and free once it is SIGKILLed (the kernel releases it);
    a second holder is refused meanwhile; the launcher watch sees the same."""
    path = tmp_path / "launcher.lock"
    holder = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from dfusion.run.supervision import FileLock
lock = FileLock({str(path)!r})
assert lock.acquire()
print("held", flush=True)
time.sleep(60)
"""], stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert holder.stdout.readline().strip() == "held"
        assert lock_holder(path) == holder.pid
        watch = LauncherWatch(tmp_path)
        assert watch.alive() and watch.launcher_pid() == holder.pid
        assert not FileLock(path).acquire(timeout=0.1)
        holder.kill()
        holder.wait()
        assert lock_holder(path) is None
        time.sleep(0.15)   # the watch looks at most every 0.1 s
        assert not watch.alive()
        watch.close()
        with FileLock(path) as again:
            assert again.acquire() and lock_holder(path) == os.getpid()   # flock: per open file, even in one process
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
    assert not LauncherWatch(tmp_path / "nowhere").alive()


def test_five_random_sigkills_are_restarted_and_the_network_reconverges(tmp_path):
    """A node process (chosen at random) is SIGKILLed at a random time, five times in one run; the
    launcher restarts it each time, and every node ends on the centralized estimate of what was
    measured (final gap <= 1e-9: linear chain, window spanning the run). No process outlives the run."""
    rng = random.Random(14)
    path = scenario(tmp_path, duration=44.0, dt=0.2, window=250)
    opts = RunOptions(scenario=str(path), speed=2.0, run_dir=str(tmp_path / "run"),
                      supervision=RestartPolicy(backoff=0.1, backoff_max=0.4))
    launcher = Launcher(opts)
    thread, box = start_in_thread(launcher)
    seen: set[int] = set()
    kills = []
    try:
        wait_until(lambda: launcher.start is not None and launcher.now() > 2.0, 90, "the start", thread)
        for _ in range(5):
            name = rng.choice(sorted(launcher.procs))
            p, rec = launcher.procs[name], launcher.monitor.records[name]
            before = len(rec.epochs)
            # the node runs (its current incarnation has published a step) ...
            wait_until(lambda: p.popen is not None and p.popen.poll() is None and p.waiting_back is None
                       and rec.phase == "run" and len(rec.epochs) >= before, 30, f"{name} running", thread)
            time.sleep(rng.uniform(0.2, 1.2))   # ... then a random moment
            assert launcher.now() < 36.0, f"too slow: only {len(kills)} kills before the end ({kills})"
            pid = p.popen.pid
            seen.update(pp.popen.pid for pp in launcher.procs.values() if pp.popen is not None)
            os.kill(pid, signal.SIGKILL)
            kills.append((name, round(launcher.now(), 2)))
            wait_until(lambda: p.popen.pid != pid, 30, f"{name} restarted", thread)
            wait_until(lambda: len(rec.epochs) > before and rec.phase == "run", 30, f"{name} back", thread)
        thread.join(timeout=120)
        assert not thread.is_alive()
    finally:
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    seen.update(pp.popen.pid for pp in launcher.procs.values() if pp.popen is not None)
    seen.update(launcher.spawned)   # the warm standby processes too
    assert "error" not in box, box.get("error")
    result = box["result"]
    assert result is not None
    m = result.metrics
    sup = m["run"]["supervision"]
    killed = {n: sum(1 for k, _ in kills if k == n) for n in launcher.procs}
    for name, v in sup["nodes"].items():
        assert v["restarts"] == killed[name], (name, sup)
        assert v["exits"] == ["killed by SIGKILL"] * killed[name]
        assert len(v["back_after_s"]) == killed[name]
        assert m["run"]["nodes"][name]["incarnations"] == killed[name] + 1
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"], kills)
    assert not launcher.failures
    assert not [pid for pid in seen if pid_alive(pid)], "a node process outlived the launcher"
    logs = "".join((tmp_path / "run" / "logs" / f"{n}.log").read_text() for n in launcher.procs)
    assert "(warm standby)" in logs   # restarts use the standby process kept ready
    backs = [b for v in sup["nodes"].values() for b in v["back_after_s"]]
    print(f"5 random SIGKILLs {kills}: restarted each time, back after {min(backs):.2f}-{max(backs):.2f} s wall; "
          f"final gaps {max(v['final_gap'] for v in m['nodes'].values()):.1e}")


def test_sigkilled_launcher_leaves_no_process(tmp_path):
    """SIGKILL to the launcher: every node (and the warm standby) stops by itself (parent-death
    signal, launcher lock), and a node started by hand afterwards refuses to run."""
    path = scenario(tmp_path, duration=60.0)
    run_dir = tmp_path / "run"
    launcher = start_cli_run(path, run_dir)
    pids: list[int] = []
    try:
        wait_until(lambda: "standby" in node_pids(run_dir), 30, "the warm standby")
        pids = list(node_pids(run_dir).values())
        assert len(pids) == 4 and all(pid_alive(p) for p in pids)   # a, b, c and the warm standby
        t0 = time.monotonic()
        launcher.kill()
        launcher.wait()
        while any(pid_alive(p) for p in pids) and time.monotonic() < t0 + 5.0:
            time.sleep(0.01)
        elapsed = time.monotonic() - t0
        assert not any(pid_alive(p) for p in pids), "node processes outlived the launcher"
        assert elapsed < 3.0, f"the nodes took {elapsed:.2f} s to stop"
        for n in "abc":
            text = (run_dir / "logs" / f"{n}.log").read_text()
            assert "stopping: SIGTERM" in text or "the launcher is gone" in text, text[-2000:]
        # the documented restart by hand, now that the launcher is gone: refused at once
        late = subprocess.run(["sh", str(run_dir / "commands" / "b.sh")], capture_output=True, text=True, timeout=60)
        assert late.returncode == EXIT_NO_LAUNCHER, late.stderr
        assert "no dfusion run launcher runs" in late.stderr
        print(f"launcher SIGKILLed: the 3 nodes and the standby stopped within {elapsed:.2f} s")
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        kill_pids(pids)


def test_a_node_restarted_by_hand_with_its_command_line_joins_the_run(tmp_path):
    """Supervision off: b is SIGKILLed and started again by hand with RUN_DIR/commands/b.sh; the
    launcher follows it, a second copy is refused, and every node ends on the centralized estimate."""
    path = scenario(tmp_path, duration=20.0)
    run_dir = tmp_path / "run"
    opts = RunOptions(scenario=str(path), speed=2.0, run_dir=str(run_dir),
                      supervision=RestartPolicy(enabled=False))
    launcher = Launcher(opts)
    thread, box = start_in_thread(launcher)
    procs: list[subprocess.Popen] = []
    try:
        wait_until(lambda: launcher.start is not None and launcher.now() > 2.0, 90, "the start", thread)
        b = launcher.procs["b"]
        os.kill(b.popen.pid, signal.SIGKILL)
        wait_until(lambda: b.gave_up, 10, "the launcher to see b go", thread)
        # twice at once, as two hurried operators would: one copy joins the run, the other is refused
        logs = [(tmp_path / f"b-by-hand-{i}.log").open("w") for i in range(2)]
        for out in logs:
            procs.append(subprocess.Popen(["sh", str(run_dir / "commands" / "b.sh")], stdout=out,
                                          stderr=subprocess.STDOUT, start_new_session=True))
        wait_until(lambda: b.external is not None, 60, "the launcher to follow b started by hand", thread)
        thread.join(timeout=120)
        assert not thread.is_alive()
        codes = sorted(p.wait(timeout=10) for p in procs)
        for out in logs:
            out.close()
        texts = [(tmp_path / f"b-by-hand-{i}.log").read_text() for i in range(2)]
        assert codes == [0, EXIT_ALREADY_RUNNING], texts
        assert any("already runs" in t for t in texts) and any("joined the run" in t for t in texts)
    finally:
        launcher.request_stop("test finished")
        thread.join(timeout=10)
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    assert "error" not in box, box.get("error")
    result = box["result"]
    assert result is not None
    m = result.metrics
    sup = m["run"]["supervision"]["nodes"]["b"]
    assert sup == {**sup, "restarts": 0, "started_by_hand": 1, "exits": ["killed by SIGKILL"], "gave_up": False}
    assert len(sup["back_after_s"]) == 1
    assert m["run"]["nodes"]["b"]["incarnations"] == 2 and m["run"]["nodes"]["b"]["finished"]
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
    assert not launcher.failures
    print(f"b restarted by hand: back after {sup['back_after_s'][0]:.2f} s wall; final gaps "
          f"{max(v['final_gap'] for v in m['nodes'].values()):.1e}")


#: The 3-node chain's settings (dt 0.2, a window spanning the run) for a tree of six nodes
TREE6 = CHAIN3.split("[[nodes]]")[0].format(duration=24.0, window=150).replace("dt = 0.1", "dt = 0.2") + "".join(f"""
[[nodes]]
name = "{n}"
sensor = "position"
std = {0.5 + 0.1 * i}
rate = 2.5
send_period = 0.6
""" for i, n in enumerate("abcdef")) + "".join(f"""
[[links]]
between = ["{a}", "{b}"]
latency = 0.02
drop = {drop}
""" for a, b, drop in (("a", "b", 0.0), ("b", "c", 0.2), ("b", "d", 0.0), ("d", "e", 0.0), ("d", "f", 0.2)))


def test_a_sigkilled_host_comes_back_with_all_its_nodes_and_the_network_reconverges(tmp_path):
    """Six nodes in two host processes (--nodes-per-process 3). SIGKILL of a host mid-run: the launcher
    restarts it (from the warm standby), each of its three nodes comes back as a new incarnation and
    replays its log, and every node ends on the centralized estimate of what was measured (final gap
    <= 1e-9: linear, window spanning the run). Nodes of one host exchange their messages through Zenoh
    (their transport counters), and no process outlives the run."""
    path = tmp_path / "tree6.scenario.toml"
    path.write_text(TREE6)
    run_dir = tmp_path / "run"
    opts = RunOptions(scenario=str(path), speed=2.0, run_dir=str(run_dir), nodes_per_process=3,
                      supervision=RestartPolicy(backoff=0.1, backoff_max=0.4))
    launcher = Launcher(opts)
    assert launcher.hosts == {"host0": ["a", "b", "c"], "host1": ["d", "e", "f"]}   # depth-first: neighbours together
    thread, box = start_in_thread(launcher)
    seen: set[int] = set()
    try:
        wait_until(lambda: launcher.start is not None and launcher.now() > 6.0, 90, "the run", thread)
        host = launcher.procs["host1"]
        recs = [launcher.monitor.records[n] for n in host.nodes]
        wait_until(lambda: "standby" in node_pids(run_dir), 30, "the warm standby", thread)
        pid = host.popen.pid
        seen.update(node_pids(run_dir).values())
        os.kill(pid, signal.SIGKILL)
        killed_at = launcher.now()
        wait_until(lambda: host.popen.pid != pid, 30, "host1 restarted", thread)
        wait_until(lambda: all(len(r.epochs) == 2 and r.phase == "run" for r in recs), 30, "host1's nodes back", thread)
        thread.join(timeout=120)
        assert not thread.is_alive()
    finally:
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    seen.update(launcher.spawned)
    assert "error" not in box, box.get("error")
    result = box["result"]
    assert result is not None
    m = result.metrics
    run = m["run"]
    assert run["hosts"] == 2 and run["nodes_per_process"] == 3
    assert run["host_nodes"] == {"host0": ["a", "b", "c"], "host1": ["d", "e", "f"]}
    sup = run["supervision"]["nodes"]
    assert sup["host1"]["restarts"] == 1 and sup["host1"]["exits"] == ["killed by SIGKILL"]
    assert sup["host0"]["restarts"] == 0 and sup["host0"]["exits"] == []
    for name in "abcdef":
        v = run["nodes"][name]
        assert v["incarnations"] == (2 if name in "def" else 1), (name, v)
        assert v["finished"]
        assert v["messages_received"] > 0
        if name in "def":
            assert v["measurements_replayed"] > 0
    # a's and c's only neighbour (b) runs in their host: what they fused came through the session
    assert run["nodes"]["a"]["messages_received"] > 0 and run["nodes"]["c"]["messages_received"] > 0
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
    assert not launcher.failures
    assert not [p for p in seen if pid_alive(p)], "a process outlived the launcher"
    log = (run_dir / "logs" / "host1.log").read_text()
    assert "incarnation 2 (warm standby)" in log and "host host1: nodes d, e, f" in log
    assert (run_dir / "commands" / "host1.sh").exists()
    assert "processes: 2 host processes for 6 nodes (up to 3 per process)" in run_table(result)
    print(f"host1 (d, e, f) SIGKILLed at t={killed_at:.1f} s: back after {sup['host1']['back_after_s'][0]:.2f} s "
          f"wall; final gaps {max(v['final_gap'] for v in m['nodes'].values()):.1e}")


def test_an_exit_seen_first_by_another_look_is_still_handled_and_restarted(tmp_path):
    """The race behind a flaky five-kills run: a node dies between the launcher's exit check and
    its look at what still runs (``_running``, ``_supervise`` call ``Popen.poll``, which reaps the
    process and sets ``returncode``). The exit check used to skip a process whose returncode was
    set, so that exit was never handled: no restart, and the run ended without the node's final
    estimate. Here the process is reaped before the exit check runs."""
    launcher = Launcher(RunOptions(scenario=str(scenario(tmp_path, 4.0)), run_dir=str(tmp_path / "run")))
    p = launcher.procs["a"]
    p.popen = subprocess.Popen([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])
    p.started = time.monotonic()
    launcher.start = time.time()
    p.popen.wait()                              # reaped by someone else's look: returncode is set
    assert p.popen.returncode == -signal.SIGKILL
    assert "a" in launcher._running()           # not handled yet: it still counts, so the run goes on
    launcher._check_exits()
    assert p.exit_codes == [-signal.SIGKILL] and p.restart_at is not None
    assert launcher.events[-1]["reason"].startswith("killed by SIGKILL"), launcher.events
    launcher._check_exits()                     # handled once only
    assert p.exit_codes == [-signal.SIGKILL] and len(launcher.events) == 1
    assert "a" in launcher._running()           # due to restart
