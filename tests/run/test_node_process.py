"""The node program (dfusion.run.node_process): what it imports, and several nodes in one process (a host).

The import contract is checked in fresh interpreters (``sys.modules`` after the node program
has loaded a scenario, built its node and run steps). The host is a real process on loopback.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

from dfusion.run.measurements import nodes_measurements, save_recording  # noqa: E402
from dfusion.run.monitor import centralized_reference  # noqa: E402
from dfusion.scenario import load_scenario  # noqa: E402
from dfusion.sim.world import simulate_world  # noqa: E402
from tests.run.test_processes import CHAIN3, ROOT  # noqa: E402

#: What a node program must not load (plotting, the simulator, scipy and the libraries that pull it in).
HEAVY = ("scipy", "matplotlib", "networkx", "filterpy", "dfusion.sim", "dfusion.viz", "dfusion.estimation.centralized")

PROBE = textwrap.dedent("""
    import json, sys
    from dfusion.run.node_process import NodeProcess
    from dfusion.run.measurements import load_recording
    from dfusion.scenario import load_scenario
    sc = load_scenario(sys.argv[1])
    name = sys.argv[2]
    names = [name, *sc.neighbors(name)]   # the node and its neighbours, each with its own measurements
    procs = {n: NodeProcess(sc, n, start=0.0, measurements=load_recording(f"{sys.argv[3]}/{n}.jsonl", n))
             for n in names}
    proc = procs[name]
    for k, t in enumerate(proc.times[1:101]):   # the loop's predict and fuse, and messages both ways
        for p in procs.values():
            p.node.predict(float(t))
            p._fuse_until(float(t))
        if k % 5 == 4:
            for nb in proc.neighbors:
                procs[nb].node.receive(proc.node.message_to(nb))
                proc.node.receive(procs[nb].node.message_to(name))   # tested by the node's guard, if any
    proc.node.estimate()
    assert proc.counters["measurements_fused"] > 0
    guard = proc.node.guard
    tested = sum(guard.links[nb].tests for nb in proc.neighbors) if guard is not None else None
    print(json.dumps({"modules": sorted(sys.modules), "guard_tests": tested}))
""")


def run_node_program(scenario: Path, node: str, tmp_path: Path) -> dict:
    """``sys.modules`` after the node program ran (``modules``), and the messages its guard tested."""
    sc = load_scenario(scenario)
    names = [node, *sc.neighbors(node)]
    rec = tmp_path / "recordings"
    rec.mkdir()
    for n, meas in nodes_measurements(sc, None, names).items():
        save_recording(rec / f"{n}.jsonl", n, meas)
    out = subprocess.run([sys.executable, "-c", PROBE, str(scenario), node, str(rec)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY)]


def test_a_position_node_program_loads_no_scipy_plotting_simulator_or_networkx(tmp_path):
    """Also once its guard has tested neighbours' messages: the test's chi-square thresholds come from
    dfusion.linalg, not scipy.stats (whose import, 1-4 s on a loaded machine, once stalled every node's
    loop at its first message, and a node SIGKILLed then had logged no measurement to replay)."""
    scenario = tmp_path / "chain3.scenario.toml"
    scenario.write_text(CHAIN3.format(duration=20.0, window=100))
    out = run_node_program(scenario, "b", tmp_path)
    modules = out["modules"]
    assert "dfusion.run.node_process" in modules and "zenoh" in modules and "numpy" in modules
    assert out["guard_tests"] is not None and out["guard_tests"] >= 10, out["guard_tests"]
    assert heavy(modules) == []
    print(f"position node program: {len(modules)} modules, none of {', '.join(HEAVY)}; "
          f"{out['guard_tests']} messages tested by its guard")


def test_a_camera_node_program_loads_no_scipy_plotting_simulator_or_networkx(tmp_path):
    scenario = ROOT / "topologies" / "urus.scenario.toml"
    out = run_node_program(scenario, "cam_left", tmp_path)
    assert "dfusion.models.camera" in out["modules"]
    assert heavy(out["modules"]) == []
    print(f"camera node program: guard tests {out['guard_tests']}")


def test_three_nodes_in_one_host_process_end_on_the_centralized_estimate(tmp_path):
    """``python -m dfusion.run.node_process --node a --node b --node c``: one process, one Zenoh
    session, three nodes with their own loops and results; their messages go through Zenoh (each
    node's transport counters), and each final estimate is the centralized EKF's (<= 1e-9). The
    host sends its nodes' step publications to the monitor together (batches on
    ``monitor/FIRST/batch``): the monitor records every step of every node."""
    from dfusion.run.monitor import Monitor
    from dfusion.transport.zenoh import ZenohConfig, free_tcp_endpoints

    scenario = tmp_path / "chain3.scenario.toml"
    scenario.write_text(CHAIN3.format(duration=4.0, window=100))
    sc = load_scenario(scenario)
    results = tmp_path / "results"
    # the start leaves the process time to import and open its session on a busy machine
    # (with 2 s it sometimes started late and dropped the first measurements as lost while down)
    start = time.time() + 8.0
    log = tmp_path / "host.log"
    net = f"host{os.getpid()}"
    (endpoint,) = free_tcp_endpoints(1)
    batches = []
    with Monitor(sc, net, ZenohConfig(listen=[endpoint])) as mon, log.open("w") as out:
        mon.session.declare_subscriber(f"dfusion/{net}/monitor/*/batch", lambda sample: batches.append(1))
        proc = subprocess.run(
            [sys.executable, "-m", "dfusion.run.node_process", "--scenario", str(scenario), "--node", "a", "--node", "b",
             "--node", "c", "--host", "h", "--network", net, "--start-time", repr(start), "--connect", endpoint,
             "--speed", "4", "--result", str(results), "--state-dir", str(tmp_path / "state")],
            stdout=out, stderr=subprocess.STDOUT, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
        time.sleep(0.2)
        mon.poll()
        assert mon.rejected == 0, mon.rejections
        for name in "abc":   # every step of every node, from the host's batches
            assert mon.records[name].have.all(), (name, np.flatnonzero(~mon.records[name].have))
        assert 0 < len(batches) <= sc.steps + 1
    text = log.read_text()
    assert proc.returncode == 0, text
    assert "[h]" in text and "host h: nodes a, b, c" in text
    _, _, c_final = centralized_reference(sc, simulate_world(sc))
    epochs = set()
    for name in "abc":
        st = json.loads((results / f"{name}.json").read_text())
        assert st["phase"] == "final" and st["node"] == name
        assert np.max(np.abs(np.asarray(st["mean"]) - c_final)) <= 1e-9, (name, st["mean"], c_final)
        s = st["stats"]
        assert s["messages_received"] > 0 and s["delivered"] >= s["messages_received"] and s["published"] > 0
        assert 0 <= s["lag_ms"] <= s["max_lag_ms"]   # behind the clock at the last step, and at its worst
        epochs.add(st["epoch"])
        assert (tmp_path / "state" / f"{name}.measurements.jsonl").exists()
    assert len(epochs) == 3   # three incarnations, one per node


def test_the_node_program_refuses_twice_the_same_node_and_record_of_several(tmp_path):
    scenario = tmp_path / "chain3.scenario.toml"
    scenario.write_text(CHAIN3.format(duration=4.0, window=100))
    base = [sys.executable, "-m", "dfusion.run.node_process", "--scenario", str(scenario)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    twice = subprocess.run(base + ["--node", "a", "--node", "a"], capture_output=True, text=True, env=env, timeout=60)
    assert twice.returncode == 2 and "named twice" in twice.stderr
    record = subprocess.run(base + ["--node", "a", "--node", "b", "--record", str(tmp_path / "x.jsonl")],
                            capture_output=True, text=True, env=env, timeout=60)
    assert record.returncode == 2 and "one --node" in record.stderr
