"""Where a node-second goes: CPU per node per simulated second of ``dfusion run``, by component.

Runs ``dfusion run`` of a random tree (:func:`dfusion.scenario.generate.random_tree_scenario`:
position sensors at 10 Hz, steps of 0.1 s, sends every 0.5 s, real time) and prints

* the **CPU per node-second**: every host process's CPU (all threads, from the start of its
  loop to its end: the wait for the start, the run, the final rounds) divided by the nodes and
  the scenario's seconds; the launcher's CPU (monitor, world, result) apart;
* **the components** (the fusion node's predict, own measurements, receive with the
  consistency test and the decoding, sends with the encoding and the Zenoh put, the monitor's
  publications, the scheduler and its wake-ups, liveliness, the arrival checks, Zenoh's
  threads), measured one of three ways:

  - ``--coarse``: every host process (through a ``sitecustomize`` on its ``PYTHONPATH``) times
    those parts with its thread's CPU clock, two clock reads per call (a few percent of
    overhead): the figures of ``docs/processes.md``, "Where a node-second goes";
  - default: cProfile in every host process (``DFUSION_PROFILE``, on the loop thread's CPU
    time) and the CPU of every thread: every function named, but this code's CPU multiplied
    by 3-4 (its many small calls);
  - ``--py-spy HZ``: py-spy samples every host process (``pip install py-spy``); on a loaded
    machine it counts a thread waiting for a core as busy.

Every figure is CPU time, not wall time, so it can be compared across runs on a machine whose
other jobs steal wall time (they inflate CPU a little too, through caches): compare versions
side by side (``--code DIR``: the dfusion in DIR, e.g. an older commit from ``git archive``),
as ratios. ``--per-process 1`` runs one node per process.

Usage: python benchmarks/node_second.py [--nodes 16] [--per-process N] [--duration 20] [--coarse | --py-spy HZ |
       --no-profile] [--code DIR] [--speed 1] [--no-network-check] [--top 25] [--keep DIR] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (label, [(path suffix, function name)], depth): inclusive CPU of the named functions (summed),
#: as a share of the loop thread's CPU; depth 1 are disjoint parts of the loop, depth 2 parts of
#: the part above.
COMPONENTS = [
    ("FusionNode.predict", [("dfusion/fusion/target.py", "predict")], 1),
    ("own measurements (front end, update, log)", [("dfusion/run/node_process.py", "_fuse_until")], 1),
    ("receive (NodeProcess.receive)", [("dfusion/run/node_process.py", "receive")], 1),
    ("decode (dfusion.wire.decode)", [("dfusion/wire.py", "decode")], 2),
    ("consistency test (guard)", [("dfusion/fusion/quarantine.py", "_add_tested")], 2),
    ("sends (send schedule, messages, links, Zenoh put)", [("dfusion/run/node_process.py", "_send_due"),
                                                           ("dfusion/run/node_process.py", "_send_all"),
                                                           ("dfusion/run/links.py", "release_due")], 1),
    ("FusionNode.message_to", [("dfusion/fusion/outgoing.py", "message_to"),
                               ("dfusion/fusion/sending.py", "message_to")], 2),
    ("encode (dfusion.wire.encode)", [("dfusion/wire.py", "encode")], 2),
    ("ZenohTransport.send (put)", [("dfusion/transport/zenoh.py", "send")], 2),
    ("monitor publication (NodeProcess._publish)", [("dfusion/run/node_process.py", "_publish")], 1),
    ("estimate", [("dfusion/fusion/target.py", "estimate")], 2),
    ("counters (NodeProcess.stats)", [("dfusion/run/node_process.py", "stats")], 2),
    ("Status.encode (msgpack, MAC)", [("dfusion/run/common.py", "encode")], 2),
]


def _match(key: tuple[str, int, str], suffix: str, name: str) -> bool:
    return key[0].endswith(suffix) and key[2] == name


def _inclusive(st: pstats.Stats, targets: list[tuple[str, str]]) -> float:
    """Inclusive CPU of the target functions, without counting a target called from another one twice."""
    total = 0.0
    for key, (_cc, _nc, _tt, ct, callers) in st.stats.items():   # type: ignore[attr-defined]
        if not any(_match(key, s, n) for s, n in targets):
            continue
        inner = sum(v[3] for c, v in callers.items() if any(_match(c, s, n) for s, n in targets))
        total += ct - inner
    return total


def _exclusive_in(st: pstats.Stats, path_part: str) -> float:
    return sum(v[2] for k, v in st.stats.items() if path_part in k[0])   # type: ignore[attr-defined]


def profile_table(prof_dir: Path, n: int, seconds: float, top: int) -> dict:
    files = sorted(prof_dir.glob("*.pstats"))
    threads = [json.loads(p.read_text()) for p in sorted(prof_dir.glob("*.threads.json"))]
    if not files or len(threads) != len(files):
        raise RuntimeError(f"no complete profile in {prof_dir}")
    st = pstats.Stats(*[str(f) for f in files])
    proc = sum(t["process_cpu_s"] for t in threads)
    main = sum(t["main_thread_cpu_s"] for t in threads)
    loop = _inclusive(st, [("dfusion/run/node_process.py", "run")])
    ns = 1000.0 / (n * seconds)   # seconds of CPU -> ms per node-second
    print(f"\nCPU per node-second: {proc * ns:.2f} ms (every thread of the host processes; {len(files)} hosts, "
          f"{n} nodes, {seconds:.0f} s)")
    print(f"  loop thread {main * ns:.2f} ms, Zenoh's threads and the rest {(proc - main) * ns:.2f} ms")
    print(f"\n{'component':<56} {'ms/node-s':>9} {'% of process':>12}")
    rows = {}
    part1 = 0.0
    for label, targets, depth in COMPONENTS:
        v = _inclusive(st, targets)
        rows[label] = v * ns
        if depth == 1:
            part1 += v
        print(f"{'  ' * depth}{label:<{56 - 2 * depth}} {v * ns:>9.2f} {100 * v / proc:>11.1f}%")
    liveliness = _inclusive(st, [("dfusion/transport/zenoh.py", "poll")])
    logging_tt = _exclusive_in(st, "/logging/")
    rest = loop - part1
    for label, v in (("scheduler and the rest of the loop (waits, clocks, bookkeeping)", rest),
                     ("  of which liveliness (ZenohTransport.poll, everywhere)", liveliness),
                     ("  of which logging (the logging module, everywhere)", logging_tt),
                     ("loop thread outside the loop (session open and close)", main - loop),
                     ("Zenoh's threads (runtime, callbacks: arrival checks)", proc - main)):
        rows[label.strip()] = v * ns
        print(f"  {label:<54} {v * ns:>9.2f} {100 * v / proc:>11.1f}%")
    names: dict[str, float] = {}
    for t in threads:
        for name, cpu in t["threads"].items():
            names[name] = names.get(name, 0.0) + cpu
    print("\nthreads by name (whole process life, CPU s): "
          + ", ".join(f"{k} {v:.2f}" for k, v in sorted(names.items(), key=lambda kv: -kv[1])[:8]))
    if top:
        print(f"\ntop {top} functions of the loop thread by own CPU (ms/node-s):")
        items = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]   # type: ignore[attr-defined]
        for (path, line, func), (_cc, nc, tt, ct, _c) in items:
            where = f"{Path(path).parent.name}/{Path(path).name}:{line}" if path != "~" else "~"
            print(f"  {tt * ns:>7.3f} own {ct * ns:>7.3f} incl {nc:>8} calls  {func}  {where}")
    return {"cpu_ms_per_node_s": proc * ns, "loop_ms_per_node_s": main * ns, "components": rows,
            "threads": names}


#: py-spy's stacks (outermost first): (label, frame substrings, sub-components (label, substrings));
#: a sample goes to the first component one of whose substrings is in one of its frames below the loop.
SAMPLED = [
    ("logging (the logging module)", ("(logging/",), ()),
    ("liveliness (ZenohTransport.poll)", ("ZenohTransport.poll ", "ZenohTransport.alive "), ()),
    ("FusionNode.predict", ("TargetFusion.predict ", "FusionNode.predict "), ()),
    ("own measurements (front end, update, log)", ("NodeProcess._fuse_until ",), ()),
    ("receive (NodeProcess.receive)", ("NodeProcess.receive ",),
     (("decode (dfusion.wire.decode)", ("decode (dfusion/wire.py",)),
      ("consistency test (guard)", ("_add_tested ",)),
      ("queue (ZenohTransport.receive)", ("ZenohTransport.receive ",)))),
    ("sends (schedule, messages, link emulation, put)", ("NodeProcess._send_due ", "NodeProcess._send_all ",
                                                         "EmulatedLinks.release_due ", "NodeProcess.send_news "),
     (("encode (dfusion.wire.encode)", ("encode (dfusion/wire.py",)),
      ("FusionNode.message_to (without encode)", ("message_to ",)),
      ("ZenohTransport.send (put)", ("ZenohTransport.send ",)))),
    ("monitor publication (NodeProcess._publish)", ("NodeProcess._publish ",),
     (("estimate", ("TargetFusion.estimate ", "FusionNode.estimate ")),
      ("counters (NodeProcess.stats)", ("NodeProcess.stats ",)),
      ("Status.encode (msgpack, MAC)", ("Status.encode ",)),
      ("Publisher.put", ("put (",)))),
]


def sampled_table(raw: Path, rate: float, n: int, seconds: float, host_cpu: float) -> dict:
    """Shares of the host processes' loop thread from py-spy's raw stacks (``py-spy record -f raw``)."""
    import re

    text = raw.read_text()
    counts: dict[str, float] = {}
    for m in re.finditer(r"(.*?) (\d+)\n", text, re.S):
        stack, c = m.group(1), int(m.group(2))
        if "--host" not in stack:
            continue   # the launcher (monitor, world) and the warm standby
        frames = stack.split(";")
        if frames[-1].startswith("Thread.run (threading.py"):
            continue   # a thread waiting in native code (Zenoh's callback threads), seen as active by py-spy
        if "Host._loop " not in stack:
            label = "start-up and shutdown (imports, scenario, session)" if "Thread." not in frames[-1] \
                and not any(f.startswith("Thread.") for f in frames) else "Python threads (callbacks, close)"
            counts[label] = counts.get(label, 0) + c
            continue
        below = frames[next(i for i, f in enumerate(frames) if f.startswith("Host._loop ")) + 1:]
        label = "scheduler and the rest of the loop"
        for name, keys, subs in SAMPLED:
            at = next((i for i, f in enumerate(below) if any(k in f for k in keys)), None)
            if at is None:
                continue
            label = name
            for sub, skeys in subs:
                if any(any(k in f for k in skeys) for f in below[at + 1:]):
                    label = f"{name}|{sub}"
                    break
            break
        counts[label] = counts.get(label, 0) + c
    total = sum(counts.values())
    ns = 1000.0 / (n * seconds)
    print(f"\npy-spy ({rate:g} Hz, active samples of the host processes): {total} samples = {total / rate:.1f} s; "
          f"the hosts' CPU {host_cpu:.1f} s")
    print(f"{'component':<58} {'ms/node-s':>9} {'share':>6}")
    tops: dict[str, float] = {}
    for k, v in counts.items():
        tops[k.split("|")[0]] = tops.get(k.split("|")[0], 0) + v
    rows = {}
    for top in sorted(tops, key=lambda k: -tops[k]):
        v = tops[top]
        rows[top] = v / total * host_cpu * ns
        print(f"  {top:<56} {rows[top]:>9.2f} {100 * v / total:>5.1f}%")
        for k in sorted((k for k in counts if k.startswith(top + "|")), key=lambda k: -counts[k]):
            rows[k] = counts[k] / total * host_cpu * ns
            print(f"    {k.split('|')[1]:<54} {rows[k]:>9.2f} {100 * counts[k] / total:>5.1f}%")
    print("(ms/node-s: the share of the samples times the hosts' measured CPU; Zenoh's native threads are not "
          "sampled: they are in the thread table of the cProfile run)")
    return rows


#: ``sitecustomize.py`` for the host processes of a ``--coarse`` run (found first on PYTHONPATH):
#: wraps the loop's parts with the thread's CPU clock (two clock reads per call: a few percent,
#: against cProfile's factor of 3-4 on this code) and writes their totals when the process exits.
COARSE_SITE = r'''
import atexit, json, os, runpy, sys, threading, time


def _install():
    import dfusion.fusion.node as _node
    import dfusion.fusion.outgoing as _outgoing
    import dfusion.run.links as _links
    import dfusion.run.node_process as _np
    import dfusion.run.common as _common
    import dfusion.transport.zenoh as _zenoh
    main = threading.main_thread().ident
    tot, span = {}, {}
    clock = time.thread_time

    def wrap(owner, name, label):
        f = getattr(owner, name)

        def timed(*a, **kw):
            where = label if threading.get_ident() == main else label + " (Zenoh's threads)"
            c0 = clock()
            try:
                return f(*a, **kw)
            finally:
                t = tot.setdefault(where, [0, 0.0])
                t[0] += 1
                t[1] += clock() - c0
        setattr(owner, name, timed)

    for owner, name, label in (
            (_np.Host, "_loop", "loop"),
            (_node.FusionNode, "predict", "predict"),
            (_np.NodeProcess, "_fuse_until", "own measurements"),
            (_np.NodeProcess, "receive", "receive"),
            (_node, "decode", "receive|decode"),
            (_node.FusionNode, "_add_tested", "receive|consistency test"),
            (_np.NodeProcess, "_send_due", "sends"),
            (_np.NodeProcess, "_send_all", "sends"),
            (_links.EmulatedLinks, "release_due", "sends"),
            (_node.FusionNode, "message_to", "sends|FusionNode.message_to"),
            (_outgoing, "encode", "sends|encode"),
            (_zenoh.ZenohTransport, "send", "sends|ZenohTransport.send"),
            (_np.NodeProcess, "_publish", "monitor"),
            (_np.Host, "flush_monitor", "monitor"),
            (_node.FusionNode, "estimate", "monitor|estimate"),
            (_common.Status, "encode", "monitor|Status.encode"),
            (_np.NodeProcess, "stats", "monitor|counters"),
            (_zenoh.ZenohTransport, "poll", "liveliness"),
            (_zenoh.ZenohTransport, "wait", "waits (ZenohTransport.wait)"),
            (_node.FusionNode, "check_frame", "check on arrival")):
        if hasattr(owner, name):
            wrap(owner, name, label)
    loop = _np.Host._loop

    def spanned(self, tr):
        span.update(p0=time.process_time(), nodes=[p.name for p in self.procs])
        try:
            return loop(self, tr)
        finally:
            span.update(p1=time.process_time())
    _np.Host._loop = spanned

    @atexit.register
    def dump():
        path = os.path.join(os.environ["DFUSION_COARSE_DIR"], f"coarse-{os.getpid()}.json")
        with open(path, "w") as f:
            json.dump({"span": span, "totals": tot, "threads": getattr(_np, "thread_cpu", dict)()}, f)
    return _np


if os.environ.get("DFUSION_COARSE_DIR"):
    _run_module = runpy.run_module

    def run_module(name, run_name=None, alter_sys=False, **kw):
        # dfusion run starts its hosts with runpy: run the imported (and instrumented) module's main instead
        if name == "dfusion.run.node_process" and run_name == "__main__":
            sys.exit(_install().main())
        return _run_module(name, run_name=run_name, alter_sys=alter_sys, **kw)
    runpy.run_module = run_module
'''


def coarse_table(coarse_dir: Path, n: int, seconds: float) -> dict:
    """The CPU of the loop's parts in every host process (``COARSE_SITE``)."""
    runs = [json.loads(p.read_text()) for p in sorted(coarse_dir.glob("coarse-*.json"))]
    runs = [r for r in runs if r["span"].get("p1") is not None]
    if not runs:
        raise RuntimeError(f"no coarse profile in {coarse_dir}")
    tot: dict[str, list] = {}
    for r in runs:
        for k, (c, t) in r["totals"].items():
            v = tot.setdefault(k, [0, 0.0])
            v[0] += c
            v[1] += t
    proc = sum(r["span"]["p1"] - r["span"]["p0"] for r in runs)
    ns = 1000.0 / (n * seconds)
    loop = tot.get("loop", [0, 0.0])[1]
    print(f"\ncoarse profile of {len(runs)} host processes (the loop's parts timed on the thread's CPU clock):")
    print(f"CPU per node-second during the loop: {proc * ns:.2f} ms (every thread); the loop's thread {loop * ns:.2f} ms")
    print(f"{'component':<52} {'calls/node-s':>12} {'ms/node-s':>9} {'share':>6}")
    rows = {}
    level1 = 0.0
    order = ["predict", "own measurements", "receive", "sends", "monitor"]
    for top in order:
        c, t = tot.get(top, [0, 0.0])
        level1 += t
        rows[top] = t * ns
        print(f"  {top:<50} {c / n / seconds:>12.1f} {t * ns:>9.2f} {100 * t / proc:>5.1f}%")
        for k in sorted(k for k in tot if k.startswith(top + "|")):
            c, t = tot[k]
            rows[k] = t * ns
            print(f"    {k.split('|')[1]:<48} {c / n / seconds:>12.1f} {t * ns:>9.2f} {100 * t / proc:>5.1f}%")
    rest = loop - level1
    rows["scheduler"] = rest * ns
    print(f"  {'scheduler and the rest of the loop':<50} {'':>12} {rest * ns:>9.2f} {100 * rest / proc:>5.1f}%")
    for k in ("liveliness", "waits (ZenohTransport.wait)", "check on arrival", "check on arrival (Zenoh's threads)"):
        if k in tot:
            c, t = tot[k]
            rows[k] = t * ns
            label = "of which " + k if k in ("liveliness", "waits (ZenohTransport.wait)") else k
            print(f"    {label:<48} {c / n / seconds:>12.1f} {t * ns:>9.2f} {100 * t / proc:>5.1f}%")
    other = proc - loop - tot.get("check on arrival (Zenoh's threads)", [0, 0.0])[1]
    rows["other threads"] = other * ns
    print(f"  {'other threads (Zenoh runtime, ...)':<50} {'':>12} {other * ns:>9.2f} {100 * other / proc:>5.1f}%")
    rows["cpu_ms_per_node_s_loop"] = proc * ns
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nodes", type=int, default=16)
    ap.add_argument("--per-process", type=int, default=None, help="nodes per host process (default: all in one)")
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-network-check", action="store_true")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--py-spy", type=float, default=None, metavar="HZ",
                    help="sample with py-spy at HZ instead of cProfile (pip install py-spy): a small overhead")
    ap.add_argument("--coarse", action="store_true",
                    help="time the loop's parts with the thread's CPU clock (a few percent of overhead) instead of "
                         "cProfile")
    ap.add_argument("--no-profile", action="store_true",
                    help="only the CPU per node-second, without the profiler (which slows Python code down)")
    ap.add_argument("--keep", default=None, metavar="DIR", help="keep the run directory and profiles here")
    ap.add_argument("--json", default=None, metavar="OUT", help="write the figures as JSON")
    ap.add_argument("--code", default=str(ROOT), metavar="DIR",
                    help="run the dfusion in DIR (e.g. an older commit from git archive), to compare in the same "
                         "conditions (default: this checkout)")
    args = ap.parse_args()
    from dfusion.scenario.generate import random_tree_scenario, scenario_toml

    per = args.per_process or args.nodes
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        raw = random_tree_scenario(args.nodes, seed=args.seed, duration=args.duration)
        if args.no_network_check:
            raw["protection"] = {"network_check": False}
        sc_path = base / f"tree{args.nodes}.scenario.toml"
        sc_path.write_text(scenario_toml(raw))
        prof = base / "profile"
        out_json = base / "run.json"
        env = dict(os.environ, PYTHONPATH=os.path.abspath(args.code))
        if args.coarse:
            site = base / "site"
            site.mkdir(exist_ok=True)
            (site / "sitecustomize.py").write_text(COARSE_SITE)
            prof.mkdir(parents=True, exist_ok=True)
            env.update(PYTHONPATH=f"{site}{os.pathsep}{env['PYTHONPATH']}", DFUSION_COARSE_DIR=str(prof))
        elif not args.no_profile and args.py_spy is None:
            env["DFUSION_PROFILE"] = str(prof)
        spy = ["py-spy", "record", "--subprocesses", "-r", f"{args.py_spy:g}", "-f", "raw", "-o",
               str(base / "py-spy.txt"), "--"] if args.py_spy else []
        load0 = os.getloadavg()[0]
        t0 = time.monotonic()
        done = subprocess.run([*spy, sys.executable, "-m", "dfusion.cli", "run", str(sc_path), "--run-dir",
                               str(base / "run"), "--json", str(out_json), "--quiet", "--speed", str(args.speed),
                               "--nodes-per-process", str(per)], cwd=args.code, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            print(done.stderr[-3000:], file=sys.stderr)
            return 1
        m = json.loads(out_json.read_text())
        run = m["run"]
        gap = max(v["final_gap"] for v in m["nodes"].values())
        lag = max(v["max_lag_wall_s"] for v in run["nodes"].values())
        host_cpu = sum(v["host_cpu_s"] for v in run["nodes"].values())
        print(f"{args.nodes} nodes, {-(-args.nodes // per)} host processes of up to {per}, {args.duration:.0f} s at "
              f"speed {args.speed:g}; consistency test {'off' if args.no_network_check else 'on'}; wall "
              f"{time.monotonic() - t0:.0f} s; load average {load0:.1f}-{os.getloadavg()[0]:.1f}; final gap "
              f"{gap:.1e}; largest lag {lag:.2f} s; launcher CPU {run.get('launcher_cpu_s', 0.0):.1f} s")
        print(f"CPU per node-second (the nodes' reports: their host's CPU from their start to their end): "
              f"{1000 * host_cpu / args.nodes / args.duration:.2f} ms")
        if args.coarse:
            res = coarse_table(prof, args.nodes, args.duration)
        elif args.py_spy:
            res = sampled_table(base / "py-spy.txt", args.py_spy, args.nodes, args.duration, host_cpu)
        else:
            res = {} if args.no_profile else profile_table(prof, args.nodes, args.duration, args.top)
        res.update(reported_cpu_ms_per_node_s=1000 * host_cpu / args.nodes / args.duration, final_gap=gap, max_lag_s=lag, load=(load0, os.getloadavg()[0]))
        if args.json:
            Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
