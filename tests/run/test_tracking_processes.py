"""``dfusion run`` of a multi-target scenario: a process per TrackingNode over Zenoh, in lockstep.

The reference is ``dfusion simulate`` of the same scenario (one process, the simulated network):
the lockstep makes every node's tracks at every step equal to it (docs/processes.md)."""
from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import pytest

from dfusion.cli import main
from dfusion.errors import MessageError
from dfusion.run.tracking import decode_frame, encode_frame, history_difference
from dfusion.scenario import load_scenario
from dfusion.sim.tracking_runner import run_tracking_scenario
from dfusion.tracking.history import TrackHistory
from dfusion.tracking.track import TrackId
from tests.scenario.test_loader import write
from tests.scenario.test_multi_target_loader import MULTI

pytest.importorskip("zenoh")

#: MULTI over 8 s (its outage of the link cam_e - wsn from 5 s to 7 s inside), and the link
#: cam_w - cam_e with drops, duplicates and reordering besides its fixed latency (drawn per link).
#: Both links into cam_e have the same fixed latency: bundles sent at one step arrive at one time
#: (and so do a duplicate's copies), and the order of those ties is simulate's too.
SHORT = (MULTI.replace("duration = 12.0", "duration = 8.0")
         .replace('between = ["cam_w", "cam_e"]\nlatency = 0.05\n',
                  'between = ["cam_w", "cam_e"]\nlatency = 0.05\ndrop = 0.1\nduplicate = 0.15\nreorder = 0.2\n'
                  'reorder_delay = 0.15\n'))


def _pids(run_dir) -> list[int]:
    return [json.loads(p.read_text())["pid"] for p in (run_dir / "endpoints").glob("*.json")]


def _track_id(text: str) -> TrackId:
    origin, serial = text.rsplit("#", 1)
    return TrackId(origin, int(serial))


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_dfusion_run_of_a_multi_target_scenario_equals_simulate_per_node(tmp_path, capsys):
    assert "reorder = 0.2" in SHORT and "outages = [[5.0, 7.0]]" in SHORT
    path = write(tmp_path, SHORT)
    out, run_dir = tmp_path / "run.json", tmp_path / "rd"
    assert main(["run", str(path), "-q", "--json", str(out), "--run-dir", str(run_dir)]) == 0
    text = capsys.readouterr().out
    assert "GOSPA [m]" in text and "0 lags" in text and "the tracks are simulate's" in text
    ran = json.loads(out.read_text())
    sim = run_tracking_scenario(load_scenario(path))
    ref = sim.metrics
    assert set(ran["nodes"]) == {"cam_e", "cam_w", "wsn"}
    assert sum(ran["run"]["lags"].values()) == 0 and ran["run"]["processes"] == 3
    # the links did drop and duplicate, and the copies add up as simulate's do
    assert ref["traffic"]["dropped"] > 0 and ref["traffic"]["duplicated"] > 0
    for k in ("sent", "duplicated", "delivered", "dropped", "in_flight"):
        assert ran["traffic"][k] == ref["traffic"][k], k
    history = TrackHistory()
    for node, recs in ran["series"].items():
        for rec in recs:
            history.record(node, rec["t"], [(_track_id(r["id"]), np.array(r["mean"]), np.array(r["cov"]))
                                            for r in rec["tracks"]])
    for node, v in ran["nodes"].items():
        r = ref["nodes"][node]
        assert v["gospa"] == r["gospa"] and v["idf1"] == r["idf1"] and v["switches"] == r["switches"], node
        assert v["births"] == r["births"] and v["merges"] == r["merges"] and v["deletions"] == r["deletions"], node
        assert v["bundles"] == r["bundles"], node   # the same bundles (longer by their MAC: bytes differ)
        # the final tracks: same identities, means within 1e-12 (and every step's tracks, covariances too)
        (t_run, last_run), (t_sim, last_sim) = history.nodes[node][-1], sim.history.nodes[node][-1]
        assert t_run == t_sim and [e[0] for e in last_run] == [e[0] for e in last_sim] and last_run, node
        for (_, m_run, _), (_, m_sim, _) in zip(last_run, last_sim):
            assert np.max(np.abs(m_run - m_sim)) <= 1e-12, node
        assert history_difference(history, sim.history, node) <= 1e-12, node
    assert ran["label_agreement"] == ref["label_agreement"]
    pids = _pids(run_dir)
    assert len(pids) == 3 and all(_gone(p) for p in pids)   # no process left behind


def test_a_killed_node_process_ends_the_run_non_zero_in_one_line(tmp_path, capsys):
    """Multi-target nodes are not restarted: the launcher stops the others and says which one died."""
    path = write(tmp_path, MULTI.replace("duration = 12.0", "duration = 120.0"))
    run_dir = tmp_path / "rd"
    killed = []

    def kill_wsn():
        end = time.monotonic() + 60
        while time.monotonic() < end and not (run_dir / "start").exists():
            time.sleep(0.02)
        time.sleep(0.3)
        entry = run_dir / "endpoints" / "wsn.json"
        if entry.exists():
            pid = json.loads(entry.read_text())["pid"]
            os.kill(pid, 9)
            killed.append(pid)

    th = threading.Thread(target=kill_wsn)
    th.start()
    try:
        code = main(["run", str(path), "-q", "--run-dir", str(run_dir), "--lag-timeout", "30"])
    finally:
        th.join()
    assert killed and code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "node process wsn" in err and "killed by SIGKILL" in err and "not restarted" in err, err
    pids = _pids(run_dir)
    assert len(pids) == 3 and all(_gone(p) for p in pids)


def test_step_frames_are_authenticated_per_run_and_link():
    key, copies = b"k" * 32, [(0.15, 0, b"bundle"), (0.17, 1, b"copy")]
    data = encode_frame(key, "net", "run", "a", "b", 7, copies)
    assert decode_frame(key, "net", "run", "a", "b", data) == (7, copies)
    with pytest.raises(MessageError, match="HMAC"):
        decode_frame(b"x" * 32, "net", "run", "a", "b", data)          # another key
    with pytest.raises(MessageError, match="HMAC"):
        decode_frame(key, "net", "run", "b", "a", data)                # replayed on the other direction
    with pytest.raises(MessageError, match="HMAC"):
        decode_frame(key, "net", "other", "a", "b", data)              # of another run
    with pytest.raises(MessageError, match="HMAC"):
        decode_frame(key, "net", "run", "a", "b", data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(MessageError, match="HMAC"):
        decode_frame(key, "net", "run", "a", "b", b"short")
    # with the key, still no copy that is not [finite time, integer, bytes] (an integer would become
    # that many zero bytes; a NaN arrival time would never be delivered)
    import msgpack

    from dfusion.run.tracking import _frame_tag
    for bad in ([[float("nan"), 0, b"x"]], [[0.1, 0, 10**6]], [[0.1, True, b"x"]], [[0.1, 0, "text"]]):
        body = msgpack.packb([1, bad], use_bin_type=True)
        with pytest.raises(MessageError, match="malformed"):
            decode_frame(key, "net", "run", "a", "b", body + _frame_tag(key, "net", "run", "a", "b", body))


def test_a_step_frame_again_is_ignored_and_counted():
    from dfusion.run.tracking import _Inbox
    inbox = _Inbox("b", ("a",), {"a": 0, "b": 1})
    inbox.add("a", 0, [(0.1, 0, b"x")])
    inbox.add("a", 0, [(0.1, 0, b"x")])       # a replay of the same step
    assert inbox.frames_repeated == 1 and len(inbox.pending) == 1


def test_flags_that_do_not_apply_to_a_multi_target_run_are_refused_in_one_line(tmp_path, capsys):
    path = write(tmp_path, MULTI)
    assert main(["run", str(path), "-q", "--nodes-per-process", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--nodes-per-process is not available for a multi-target scenario" in err, err
    assert main(["run", str(path), "-q", "--speed", "10"]) == 2     # lockstep: no real-time pacing to speed up
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--speed is not available for a multi-target scenario" in err, err


def test_a_stalled_neighbour_costs_one_lag_timeout_not_one_per_step():
    """A neighbour alive but silent: the first step waits lag_timeout and counts a lag; the next
    steps do not wait for it again until its frames catch up (then it is waited for again)."""
    import time as _time

    from dfusion.run.tracking import _Inbox, _NodeProcess

    class Silent:                      # a transport on which the neighbour is alive and sends nothing
        def receive(self, node):
            return []

        def take_rejections(self, node):
            return {}, ""

        def alive(self, node):
            return True

        def wait(self, seconds):
            _time.sleep(seconds)

    p = object.__new__(_NodeProcess)
    p.name, p.lags, p.lagging, p.lag_timeout = "b", 0, set(), 0.3
    p.inbox = _Inbox("b", ("a",), {"a": 0, "b": 1})
    t0 = _time.monotonic()
    p._wait_for(Silent(), 0, "step 0")
    first = _time.monotonic() - t0
    t0 = _time.monotonic()
    for k in range(1, 6):
        p._wait_for(Silent(), k, f"step {k}")
    later = _time.monotonic() - t0
    assert first >= 0.3 and later < 0.3 and p.lags == 1 and p.lagging == {"a"}
    p.inbox.add("a", 5, [])            # its frames catch up: waited for again
    p._wait_for(Silent(), 5, "step 5")
    assert p.lagging == set()
