"""What a fusion network costs at scale: bytes on the links, CPU per message, memory per node.

All in one run, every figure beside its reference measured in the same run:

1. **Bytes per link per second** on a simulated random tree of 8 position-sensor nodes
   (5 Hz, 4-dimensional state), for windows of 10, 50 and 200 states, send periods of
   0.1, 0.5 and 1 s and drop rates of 0 to 50 % on every link: the protocol
   (``messages="partial"``), the previous protocol's whole window in every message
   (``messages="full"``, same encoding) and the **information minimum**: per message, the
   size of a message carrying only the blocks that changed since the previous message on
   that link (the new blocks), header included. Nodes send with staggered phases, as
   independent processes do. Goals: without drops, partial / minimum <= 1.5 at every
   window; at 30 % drops <= 3.
2. **CPU per hop** in one process: the sender's ``message_to`` plus the receiver's
   ``receive`` and ``estimate`` for one new measurement in the steady state, against a
   minimal hop with the same payload (msgpack of the same bytes and one 4 x 4 solve per
   side), at windows 10 and 100.
3. **Import time and memory of a node process** per sensor kind: a fresh interpreter
   imports the node program, loads a scenario, builds its node and front end from a
   recording of its measurements (as ``dfusion run`` gives them), opens a Zenoh session,
   runs 200 steps (predict, fuse, messages, publication); its resident memory (VmRSS,
   VmHWM), the modules loaded and whether scipy, matplotlib, networkx, filterpy or the
   simulator are among them. Goals: position kind under 60 MB, camera kind under 80 MB.
4. **A real network** (``--run``): (a) the node processes of ``dfusion run`` of the shipped
   chain (position) and URUS scenario (camera, WSN, relay), one process per node: the peak
   resident memory of each running process, against the same goals; (b) ``dfusion run``
   of random trees of 8, 32 and 128 nodes (:func:`dfusion.scenario.generate.random_tree_scenario`:
   linear scenario, 10 Hz, real time, 60 s), with the host processes used, total resident
   memory, CPU per node-second (process CPU time per node per second of scenario time), the **lag behind
   the clock** at the end and at its worst (real time: at most one send period), blocks that arrived too late
   for the receiver's window, quarantines by the consistency test, and final gaps (``--no-network-check``:
   without that test). Goals: final gaps <= 1e-9, total memory under 8 GB. Real time needs a quiet machine:
   on a shared one compare the CPU column, not the lags.

Usage: python benchmarks/scale.py [--quick] [--run | --only-run [--no-kinds]] [--sizes 8,32,128] [--nodes-per-process N]
       [--no-network-check] [--strict]
Run time: on a quiet 2-core machine sections 1-3 about 10 min (``--quick`` 1-2 min), 4 (``--run``) about 6 min
(``--quick`` 3 min); under a load average of 3-28 the full ``--run`` took 42.5 min (2026-11-25).
The machine is noisy (runs vary by up to 1.6x on a 2-core VM): compare within one run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import msgpack
import numpy as np

from dfusion.fusion import FusionNode
from dfusion.fusion.channel import nonzero_blocks, time_key
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.scenario import load_scenario
from dfusion.sim import run_scenario
from dfusion.topology import random_tree
from dfusion.wire import InfoMessage, encode

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ bytes
def tree_scenario(n: int, window: int, period: float, drop: float, duration: float, seed: int = 1,
                  rate: float = 5.0, latency: float = 0.02) -> dict:
    rng = np.random.default_rng(seed + 100)
    nodes = [{"name": f"n{k}", "sensor": "position", "std": 0.5, "rate": rate, "send_period": period,
              "phase": float(rng.uniform(0, 1.0 / rate))} for k in range(n)]
    links = [{"between": [a, b], "latency": latency, "drop": drop} for a, b in random_tree(n, seed)]
    return {"duration": duration, "dt": 0.1, "seed": seed, "window": window,
            "target": {"motion": "constant_velocity", "q": 0.05, "initial_mean": [0.0, 0.0, 1.0, 0.0],
                       "initial_cov_diag": [1.0, 1.0, 1.0, 1.0]},
            "nodes": nodes, "links": links}


class MinimumMeter:
    """Wraps ``FusionNode.message_to``: the bytes of a message carrying only the new blocks."""

    def __init__(self) -> None:
        self.bytes = 0
        self.messages = 0
        self._orig = FusionNode.message_to

    def __enter__(self) -> "MinimumMeter":
        meter = self

        def message_to(node: FusionNode, neighbor: str, sent_at: float | None = None) -> bytes:
            ch = node.channels[neighbor]
            keys = np.array(sorted(k for k in ch.dirty if k >= time_key(node.filter.oldest_time) - 1),
                            dtype=np.int64)
            info, vec = node._values_for(ch, keys)   # noqa: SLF001  (a measurement, not library code)
            keep = nonzero_blocks(info, vec)
            msg = InfoMessage(node.name, neighbor, node.epoch, ch.seq_out, node.filter.oldest_time,
                              node.filter.latest_time, keys[keep] / 1e9, info[keep], vec[keep],
                              ch.epoch or 0, ch.applied_seq, ch.received_mask(), full=False)
            meter.bytes += len(encode(msg, node.frame_key))
            meter.messages += 1
            return meter._orig(node, neighbor, sent_at)

        FusionNode.message_to = message_to
        return self

    def __exit__(self, *exc) -> None:
        FusionNode.message_to = self._orig


def run_bytes(sc_dict: dict, messages: str) -> tuple[float, float, int, float]:
    """(bytes per link per second, minimum bytes per link per second, messages, worst final gap)."""
    sc = load_scenario(sc_dict)
    orig_init = FusionNode.__init__

    def init(self, *a, **kw):
        kw["messages"] = messages
        orig_init(self, *a, **kw)

    FusionNode.__init__ = init
    try:
        with MinimumMeter() as meter:
            res = run_scenario(sc)
    finally:
        FusionNode.__init__ = orig_init
    links = 2 * len(sc.links)
    m = res.metrics
    seconds = sc.duration
    gap = max(v["final_gap"] for v in m["nodes"].values())
    return m["bytes"] / links / seconds, meter.bytes / links / seconds, m["messages"], gap


def bytes_table(quick: bool) -> list[str]:
    windows = (10, 50, 200)
    periods = (0.5,) if quick else (0.1, 0.5, 1.0)
    drops = (0.0, 0.3) if quick else (0.0, 0.1, 0.3, 0.5)
    duration = 30.0 if quick else 60.0
    failed = []
    print("\n1. Bytes per link per second (random tree of 8 nodes, 5 Hz position sensors, n = 4)")
    print(f"{'window':>6} {'period s':>8} {'drop':>5} | {'full B/s':>9} {'partial B/s':>11} {'minimum B/s':>11} "
          f"| {'partial/min':>11} {'full/min':>8} {'goal':>5} | {'final gap':>9}")
    for w in windows:
        for p in periods:
            for d in drops:
                sc = tree_scenario(8, w, p, d, duration)
                full, _, _, _ = run_bytes(sc, "full")
                part, minimum, _, gap = run_bytes(sc, "partial")
                goal = 1.5 if d == 0 else (3.0 if d <= 0.3 else None)
                ratio = part / minimum
                ok = goal is None or ratio <= goal
                if not ok:
                    failed.append(f"bytes w={w} p={p} drop={d}: {ratio:.2f} > {goal}")
                print(f"{w:>6} {p:>8.1f} {d:>5.0%} | {full:>9.0f} {part:>11.0f} {minimum:>11.0f} | {ratio:>11.2f} "
                      f"{full / minimum:>8.1f} {'' if goal is None else ('PASS' if ok else 'FAIL'):>5} | {gap:>9.1e}")
    return failed


# ------------------------------------------------------------------------------ hop CPU
def steady_pair(window: int) -> tuple[FusionNode, FusionNode, PositionSensor]:
    motion = ConstantVelocity(2, 0.1)
    sensor = PositionSensor(2, 0.5)
    prior = (0.0, np.zeros(4), np.eye(4))
    a = FusionNode("a", ["b"], motion, window=window, prior=prior, epoch=1)
    b = FusionNode("b", ["a"], motion, window=window, prior=prior, epoch=2)
    rng = np.random.default_rng(0)
    for k in range(1, 2 * window + 1):
        t = round(0.1 * k, 9)
        a.predict(t)
        b.predict(t)
        a.update(t, rng.normal(size=2), sensor)
        b.receive(a.message_to("b"))
        a.receive(b.message_to("a"))     # acknowledgements flow: the steady state
    return a, b, sensor


def minimal_hop(payload: bytes) -> None:
    """A hop that does only the unavoidable: pack, unpack, one small solve per side."""
    S = np.eye(4) * 2.0
    data = msgpack.packb([payload, np.linalg.solve(S, np.ones(4)).tobytes()], use_bin_type=True)
    out = msgpack.unpackb(data)
    np.linalg.solve(S, np.frombuffer(out[1]))


def hop_table(quick: bool) -> list[str]:
    print("\n2. CPU per hop in one process (one new measurement, steady state, n = 4), median us")
    print(f"{'window':>6} | {'bytes':>5} {'dfusion hop':>11} {'minimal hop':>11} {'ratio':>6}")
    reps = 200 if quick else 1000
    for window in (10, 100):
        a, b, sensor = steady_pair(window)
        rng = np.random.default_rng(1)
        t = round(0.1 * 2 * window, 9)
        hop, mini, sizes = [], [], []
        for _ in range(reps):
            t = round(t + 0.1, 9)
            a.predict(t)
            b.predict(t)
            a.update(t, rng.normal(size=2), sensor)
            t0 = time.perf_counter()
            data = a.message_to("b")
            b.receive(data)
            b.estimate()
            t1 = time.perf_counter()
            minimal_hop(data)
            t2 = time.perf_counter()
            a.receive(b.message_to("a"))
            hop.append(t1 - t0)
            mini.append(t2 - t1)
            sizes.append(len(data))
        h, m = np.median(hop) * 1e6, np.median(mini) * 1e6
        print(f"{window:>6} | {int(np.median(sizes)):>5} {h:>11.0f} {m:>11.0f} {h / m:>6.1f}")
    return []


# ------------------------------------------------------------------------------ memory per kind
KIND_PROBE = textwrap.dedent("""
    import json, sys, time
    t0 = time.perf_counter()
    from dfusion.run.node_process import NodeProcess  # the node program
    t_import = time.perf_counter() - t0
    from dfusion.run.measurements import load_recording
    from dfusion.scenario import load_scenario
    from dfusion.transport.zenoh import ZenohTransport
    sc = load_scenario(sys.argv[1])
    name = sys.argv[2]
    proc = NodeProcess(sc, name, start=0.0, measurements=load_recording(sys.argv[3], name))
    with ZenohTransport("probe", {name: proc.neighbors}) as tr:
        proc.attach(tr)
        for t in proc.times[1:201]:          # the loop's steps: predict, fuse, messages, estimate, publication
            proc.node.predict(float(t))
            proc._fuse_until(float(t))
            for nb in proc.neighbors:
                proc.node.message_to(nb)
            proc._publish("run", int(round(float(t) / sc.dt)))
        status = {k: int(v.split()[0]) / 1024 for k, v in (line.split(":", 1) for line in open("/proc/self/status"))
                  if k in ("VmRSS", "VmHWM")}
    heavy = ("scipy", "matplotlib", "networkx", "filterpy", "dfusion.sim")
    print(json.dumps({"import_s": t_import, "rss_mb": status["VmRSS"], "hwm_mb": status["VmHWM"],
                      "modules": len(sys.modules),
                      "heavy": sorted({h for h in heavy for m in sys.modules if m == h or m.startswith(h + ".")})}))
""")

KINDS = (("position", "topologies/chain3.scenario.toml", "a", 60.0),
         ("camera", "topologies/urus.scenario.toml", "cam_left", 80.0),
         ("wsn_rssi", "topologies/urus.scenario.toml", "wsn", None),
         ("relay (none)", "topologies/urus.scenario.toml", "gateway", None))


def kinds_table() -> list[str]:
    """3. A fresh interpreter per kind: the node program's imports, its node built from a recording (as
    ``dfusion run`` gives it), a Zenoh session, 200 steps; then the resident memory of that process."""
    from dfusion.run.measurements import nodes_measurements, save_recording

    print("\n3. A node program per sensor kind (fresh interpreter: imports, node from a recording, Zenoh session, "
          "200 steps)")
    print(f"{'kind':<14} {'import s':>8} {'RSS MB':>7} {'peak MB':>7} {'modules':>7}  {'heavy modules loaded':<22} "
          f"{'goal MB':>9}")
    failed = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, scenario, node, goal in KINDS:
            sc = load_scenario(ROOT / scenario)
            rec = save_recording(Path(tmp) / f"{node}.jsonl", node, nodes_measurements(sc, None, [node])[node])
            out = subprocess.run([sys.executable, "-c", KIND_PROBE, str(ROOT / scenario), node, str(rec)],
                                 capture_output=True, text=True, timeout=600, cwd=ROOT)
            if out.returncode != 0:
                print(f"{kind:<14} failed: {out.stderr.strip().splitlines()[-1:]}")
                failed.append(f"{kind}: probe failed")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            ok = goal is None or r["hwm_mb"] <= goal
            if not ok:
                failed.append(f"{kind}: {r['hwm_mb']:.0f} MB > {goal} MB")
            if r["heavy"]:
                failed.append(f"{kind}: loads {r['heavy']}")
            print(f"{kind:<14} {r['import_s']:>8.2f} {r['rss_mb']:>7.0f} {r['hwm_mb']:>7.0f} {r['modules']:>7}  "
                  f"{', '.join(r['heavy']) or 'none':<22} {'' if goal is None else (f'{goal:.0f} ' + ('PASS' if ok else 'FAIL')):>9}")
    return failed


# ------------------------------------------------------------------------------ dfusion run
def run_sampled(scenario: Path, args: list[str], run_dir: Path) -> dict:
    """``dfusion run SCENARIO ARGS`` as a process; every second the peak resident memory (VmHWM) of each of
    its processes (``RUN_DIR/pids.json``: hosts, the warm standby, the launcher). Returns the run's JSON with
    ``peak_mb`` (process -> MB) and the load averages before and after."""
    out_json = run_dir.with_suffix(".json")
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "dfusion.cli", "run", str(scenario), "--run-dir", str(run_dir),
                             "--json", str(out_json), "--quiet", *args], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    peak: dict[tuple[str, int], float] = {}
    try:
        while proc.poll() is None:
            try:
                pids = json.loads((run_dir / "pids.json").read_text())
            except (OSError, ValueError):
                pids = {}
            for name, pid in pids.items():
                try:
                    text = Path(f"/proc/{pid}/status").read_text()
                    hwm = int(text.split("VmHWM:")[1].split()[0]) / 1024
                except (OSError, IndexError, ValueError):
                    continue
                peak[(name, pid)] = max(peak.get((name, pid), 0.0), hwm)
            time.sleep(0.5)
    finally:
        if proc.poll() is None:
            proc.kill()
        err = proc.communicate()[1]
    if proc.returncode != 0 or not out_json.exists():
        raise RuntimeError(f"dfusion run failed ({proc.returncode}): {err[-2000:]}")
    m = json.loads(out_json.read_text())
    m["peak_mb"] = {f"{n}:{pid}": v for (n, pid), v in peak.items()}
    m["load"] = (load0, os.getloadavg()[0])
    m["bench_wall_s"] = time.monotonic() - t0
    return m


def running_kinds_table(tmp: Path, quick: bool) -> list[str]:
    """4a. The same kinds in a real ``dfusion run`` (one process per node): their peak resident memory."""
    print("\n4a. Node processes of a dfusion run, one per node (peak resident memory of the running process, VmHWM; "
          "CPU per node-second: the process's CPU, every thread, per second of scenario time)")
    print(f"{'kind':<14} {'node':<9} {'peak MB':>7} {'goal MB':>9} {'CPU ms/node-s':>13}")
    failed = []
    runs = {}
    durations = {}
    for scenario, args in (("topologies/chain3.scenario.toml", ["--speed", "4", "--duration", "20" if quick else "40"]),
                           ("topologies/urus.scenario.toml", ["--speed", "2", "--duration", "10" if quick else "20"])):
        runs[scenario] = run_sampled(ROOT / scenario, args, tmp / Path(scenario).stem)
        durations[scenario] = float(args[-1])
    for kind, scenario, node, goal in KINDS:
        peak = max(v for k, v in runs[scenario]["peak_mb"].items() if k.split(":")[0] == node)
        cpu = 1000 * runs[scenario]["run"]["nodes"][node]["host_cpu_s"] / durations[scenario]
        ok = goal is None or peak <= goal
        if not ok:
            failed.append(f"running {kind}: {peak:.0f} MB > {goal} MB")
        print(f"{kind:<14} {node:<9} {peak:>7.0f} {'' if goal is None else (f'{goal:.0f} ' + ('PASS' if ok else 'FAIL')):>9} "
              f"{cpu:>13.1f}")
    return failed


def run_table(quick: bool, sizes: tuple[int, ...], per_process: str, network_check: bool = True,
              kinds: bool = True) -> list[str]:
    """4b. ``dfusion run`` of random trees: hosts, memory, CPU, lag and final gaps."""
    from dfusion.scenario.generate import random_tree_scenario, scenario_toml

    failed = []
    with tempfile.TemporaryDirectory() as tmp:
        if kinds:
            failed += running_kinds_table(Path(tmp), quick)
        duration = 20.0 if quick else 60.0
        print(f"\n4b. dfusion run of random trees (linear scenario: position sensors at 10 Hz, steps of 0.1 s, sends every "
              f"0.5 s, {duration:.0f} s in real time; consistency test of neighbours' messages "
              f"{'on' if network_check else 'off'})")
        print(f"{'nodes':>5} {'diam':>4} {'window':>6} {'hosts':>5} {'per host':>8} | {'RSS hosts MB':>12} {'launcher MB':>11} "
              f"{'total MB':>8} | {'CPU ms/node-s':>13} {'loop ms':>7} {'launcher s':>10} | {'lag end s':>9} {'lag max s':>9} "
              f"{'real time':>9} | {'late':>5} {'quar':>4} {'final gap':>9} {'wall s':>6} {'load':>9}")
        for n in sizes:
            raw = random_tree_scenario(n, seed=1, duration=duration)
            if not network_check:
                raw["protection"] = {"network_check": False}
            path = Path(tmp) / f"tree{n}.scenario.toml"
            path.write_text(scenario_toml(raw))
            per = max(1, -(-n // 8)) if per_process == "auto" else int(per_process)
            m = run_sampled(path, ["--nodes-per-process", str(per)], Path(tmp) / f"run{n}")
            run = m["run"]
            hosts_mb = sum(v for k, v in m["peak_mb"].items() if k.split(":")[0] not in ("launcher", "standby"))
            launcher_mb = max((v for k, v in m["peak_mb"].items() if k.split(":")[0] == "launcher"), default=0.0)
            standby_mb = sum(v for k, v in m["peak_mb"].items() if k.split(":")[0] == "standby")
            total = hosts_mb + launcher_mb + standby_mb
            gap = max(v["final_gap"] for v in m["nodes"].values())
            lag = max(v["max_lag_wall_s"] for v in run["nodes"].values())
            lag_end = max(v.get("lag_at_end_wall_s", math.nan) for v in run["nodes"].values())
            cpu = 1000 * sum(v["host_cpu_s"] for v in run["nodes"].values()) / n / duration
            loop_cpu = 1000 * sum(v["cpu_s"] for v in run["nodes"].values()) / n / duration
            period = raw["nodes"][0]["send_period"]
            real_time = "yes" if lag <= period else "no"
            late = sum(v.get("blocks_outside_window", 0) for v in run["nodes"].values())
            quarantines = sum(v.get("quarantines", 0) or 0 for v in m["nodes"].values())
            diam = load_scenario(raw).tree.diameter()
            ok = gap <= 1e-9 and total <= 8192
            if not ok:
                failed.append(f"run of {n}: gap {gap:.1e}, {total:.0f} MB")
            print(f"{n:>5} {diam:>4} {raw['window']:>6} {run['hosts']:>5} {per:>8} | {hosts_mb:>12.0f} {launcher_mb:>11.0f} "
                  f"{total:>8.0f} | {cpu:>13.1f} {loop_cpu:>7.1f} "
                  f"{run['launcher_cpu_s']:>10.1f} | {lag_end:>9.2f} {lag:>9.2f} {real_time:>9} | {late:>5} {quarantines:>4} "
                  f"{gap:>9.1e} {m['bench_wall_s']:>6.0f} {m['load'][0]:>4.1f}-{m['load'][1]:<4.1f}")
    print("RSS: peak resident memory (VmHWM) of every host process (total), the launcher (monitor, world, result) and "
          "the warm standby;\nCPU: every host process's CPU (all threads, Zenoh's included) from the start to the end, "
          "per node per second of\nscenario time (process CPU time, not wall time: comparable on a busy machine); loop: "
          "the nodes' own work in their hosts' loops;\nlag end / max: how far the slowest node was behind the clock at "
          "its last step, and at its worst; real time: the\nlargest lag at most one send period; late: blocks for "
          "times older than the receiver's window, ignored (resends\nof blocks it already held count too); quar: "
          "quarantines by the consistency test; final gap: largest distance\nof a node's final estimate to the "
          "centralized EKF's; load: load average before and after (other jobs)")
    return failed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer configurations and repetitions, shorter runs")
    ap.add_argument("--run", action="store_true", help="also dfusion run networks of 8, 32 and 128 nodes (4b.) and the "
                                                       "node processes of a run per kind (4a.)")
    ap.add_argument("--only-run", action="store_true", help="only 4a. and 4b.")
    ap.add_argument("--sizes", default="8,32,128", help="network sizes of 4b. (default 8,32,128; the issue's real-time "
                                                        "goal: 8,32,128,256 on a quiet machine)")
    ap.add_argument("--nodes-per-process", default="auto",
                    help="dfusion run --nodes-per-process of 4b. (default auto: ceil(n / 8), i.e. 8 host processes)")
    ap.add_argument("--no-network-check", action="store_true",
                    help="4b. without the consistency test of neighbours' messages ([protection] network_check = false)")
    ap.add_argument("--no-kinds", action="store_true", help="--only-run without 4a.")
    ap.add_argument("--strict", action="store_true", help="exit status 1 when a goal is not met")
    args = ap.parse_args()
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    failed = [] if args.only_run else bytes_table(args.quick) + hop_table(args.quick) + kinds_table()
    if args.run or args.only_run:
        failed += run_table(args.quick, tuple(int(x) for x in args.sizes.split(",")), args.nodes_per_process,
                            network_check=not args.no_network_check, kinds=not args.no_kinds)
    if failed:
        print("\ngoals not met: " + "; ".join(failed))
    return 1 if (args.strict and failed) else 0


if __name__ == "__main__":
    sys.exit(main())
