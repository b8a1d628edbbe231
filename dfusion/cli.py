"""The ``dfusion`` command line.

``dfusion simulate SCENARIO [--seed N] [--fusion channel|naive] [--duration S] [--json OUT] [--plot OUT.png]
[--no-protection]`` runs a scenario in one process and prints per-node RMSE, ANEES and the gap to
the centralized EKF, with message counts and the consistency diagnostics (``docs/clutter.md``).

``dfusion run SCENARIO [--speed X] [--nodes-per-process N] [--json OUT] [--plot OUT.png] [--restart NAME@T[+D]] ...``
runs the same scenario with one OS process per node (or N nodes per process) over Zenoh
and prints the same table (``docs/processes.md``).

``dfusion replay SCENARIO BAG --topic TOPIC=NODE ... [--truth TOPIC] [--arrival stamp|record]``
runs the scenario's nodes on the measurements of a ROS 1 or ROS 2 bag instead of the
simulated world (``docs/ros.md``). ``dfusion replay BAG --detections TOPIC=SENSOR ... [--truth
TOPIC ...] [--association jpda|gnn]`` tracks the bag's detection arrays with the multi-target
tracker instead (``docs/multi-target.md``).

Outputs of all three: ``--json`` (the figures and the per-step series), ``--csv``
(the series), ``--plot`` (error plots), ``--topdown`` (the top-down figure),
``--mcap`` (a recording for Foxglove, ``docs/ros.md``); ``simulate --frames`` (the tree over
time, for scenarios whose links change: ``docs/dynamic-topology.md``).
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from dfusion.errors import DfusionError


def _simulate(args: argparse.Namespace) -> int:
    from dfusion.scenario.loader import load_scenario
    from dfusion.sim.runner import run_scenario

    sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration, plugins=args.plugin,
                       protection=False if args.no_protection else None, sends=args.sends,
                       min_send_interval=args.min_send_interval)
    if sc.multi_target:
        return _simulate_tracking(sc, args)
    live = None
    if args.foxglove is not None:
        from dfusion.viz.foxglove import LiveView

        live = LiveView(sc, port=args.foxglove, speed=args.speed)
        print(f"Foxglove live view on ws://127.0.0.1:{args.foxglove} (scenario time x{args.speed:g})", flush=True)
    try:
        result = run_scenario(sc, progress=not args.quiet and live is None, on_step=live)
    finally:
        if live is not None:
            live.close()
    print(result.table())
    _outputs(result, args)
    return 0


def _simulate_tracking(sc, args: argparse.Namespace, world=None) -> int:
    """``dfusion simulate`` of a multi-target scenario ([[targets]]): a TrackingNode per node
    (:mod:`dfusion.sim.tracking_runner`); ``--json``, ``--topdown`` (every node's tracks),
    ``--plot`` (the identity timelines), ``--mcap``."""
    for flag in ("csv", "frames", "foxglove"):
        if getattr(args, flag, None) is not None:
            raise DfusionError(f"--{flag} is not available for a multi-target scenario yet (--json, --topdown, "
                               f"--plot and --mcap are)")
    from dfusion.sim.tracking_runner import run_tracking_scenario

    result = run_tracking_scenario(sc, progress=not args.quiet, world=world)
    print(result.table())
    _tracking_outputs(sc, result, args)
    return 0


def _tracking_outputs(sc, result, args: argparse.Namespace) -> None:
    """``--json``, ``--topdown``, ``--plot``, ``--mcap`` of a multi-target run (simulate, run, replay)."""
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json(series=True))
        print(f"wrote {args.json}")
    if args.topdown or args.plot or args.mcap:
        from dfusion.sim.target_world import node_view
        from dfusion.viz.tracks import plot_identity_timeline, plot_tracks_topdown

        views = [v for v in (node_view(spec) for _, spec in sorted(sc.nodes.items())) if v is not None]
        nodes = sorted(result.metrics["nodes"]) + ["central"]
        name = Path(sc.path).stem
        if args.topdown:
            path = plot_tracks_topdown(result.history, result.world.truth, args.topdown, nodes=nodes, views=views,
                                       region=sc.tracking.region, title=f"{name}: every node's tracks and the truth")
            print(f"wrote {path}")
        if args.plot:
            path, _ = plot_identity_timeline(result.history, result.world.truth, args.plot,
                                             nodes=sorted(result.metrics["nodes"]),
                                             threshold=sc.tracking.match,
                                             title=f"{name}: identity timeline per node")
            print(f"wrote {path}")
        if args.mcap:
            from dfusion.viz.foxglove import record_tracks_mcap

            print(f"wrote {record_tracks_mcap(result.history, args.mcap, result.world.truth, views=views)} "
                  f"(open it in Foxglove)")


def _replay_tracking(sc, args: argparse.Namespace) -> int:
    """``dfusion replay SCENARIO BAG --topic TOPIC=CAMERA_NODE ... [--truth TOPIC ...]`` of a
    multi-target scenario: the camera nodes' scans are the bag's detection arrays
    (:func:`dfusion.sim.target_world.world_from_bag`), the rest as ``simulate``."""
    from dfusion.bags import msgdefs_from_files
    from dfusion.sim.replay import parse_topic_input
    from dfusion.sim.target_world import world_from_bag

    if not args.truth:
        raise DfusionError("a replay of a multi-target scenario needs --truth TOPIC (one per target, or a "
                           "Detection3DArray with ids): its figures are measured against it")
    inputs = [parse_topic_input(t) for t in args.topic]
    world = world_from_bag(sc, args.bag, [(i.topic, i.node, i.convert) for i in inputs], truth_topics=args.truth,
                           origin_ns=args.origin_ns, msgdefs=msgdefs_from_files(args.msg))
    c = world.counts
    print(f"read {c.scans} scans, {c.detections} detections from {args.bag} "
          f"({', '.join(f'{i.topic} -> {i.node}' for i in inputs)}); truth: {len(world.truth.paths)} targets")
    return _simulate_tracking(sc, args, world=world)


def _outputs(result, args: argparse.Namespace, *, title: str | None = None) -> None:
    """``--json``, ``--csv``, ``--plot`` (with ``title``), ``--topdown``, ``--mcap`` of a result."""
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json(series=True))
        print(f"wrote {args.json}")
    if getattr(args, "csv", None):
        from dfusion.sim.runner import write_series_csv

        write_series_csv(result, args.csv)
        print(f"wrote {args.csv}")
    if args.plot:
        from dfusion.viz import plot_result

        print(f"wrote {plot_result(result, args.plot, title=title)}")
    if getattr(args, "frames", None):
        from dfusion.viz.treeframes import plot_tree_frames

        print(f"wrote {plot_tree_frames(result, args.frames)}")
    if getattr(args, "topdown", None):
        from dfusion.viz.topdown import plot_topdown

        print(f"wrote {plot_topdown(result, args.topdown)}")
    if getattr(args, "mcap", None):
        from dfusion.viz.foxglove import record_mcap

        print(f"wrote {record_mcap(result, args.mcap, start_ns=getattr(args, 'start_ns', 0))} (open it in Foxglove)")


def _replay(args: argparse.Namespace) -> int:
    if args.detections:
        return _replay_detections(args)
    from dfusion.scenario.loader import load_scenario
    from dfusion.sim.replay import parse_topic_input, replay_scenario

    if len(args.paths) != 2:
        print("dfusion: error: replay takes SCENARIO BAG with --topic TOPIC=NODE, or BAG with --detections "
              "TOPIC=SENSOR", file=sys.stderr)
        return 2
    args.scenario, args.bag = args.paths
    if not args.topic:
        print("dfusion: error: map at least one bag topic to a node with --topic TOPIC=NODE", file=sys.stderr)
        return 2
    from dfusion.bags import msgdefs_from_files, read_bag

    sc = load_scenario(args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration, plugins=args.plugin)
    if sc.multi_target:
        return _replay_tracking(sc, args)
    if len(args.truth) > 1:
        print("dfusion: error: a scenario replay takes one --truth topic (the target's)", file=sys.stderr)
        return 2
    truth = args.truth[0] if args.truth else None
    if args.plot and truth is None:
        print("dfusion: error: --plot draws errors against the truth: give --truth TOPIC (or leave --plot out)",
              file=sys.stderr)
        return 2
    inputs = [parse_topic_input(t) for t in args.topic]
    bag = read_bag(args.bag, [i.topic for i in inputs] + ([truth] if truth else []),
                   msgdefs=msgdefs_from_files(args.msg))
    result = replay_scenario(sc, bag, inputs, truth_topic=truth, arrival=args.arrival,
                             origin_ns=args.origin_ns, progress=not args.quiet)
    print(result.table())
    if truth is None:
        print("(no --truth topic: RMSE and ANEES are unknown)")
    args.start_ns = result.world.origin_ns   # the recording in the bag's time (overlays the source bag)
    _outputs(result, args)
    return 0


def _replay_detections(args: argparse.Namespace) -> int:
    """``dfusion replay BAG --detections ...``: the multi-target tracker on recorded detections (docs/ros.md)."""
    from dfusion.bags import msgdefs_from_files
    from dfusion.sim.track_replay import TrackerSettings, parse_detection_topic, replay_tracks

    if len(args.paths) != 1:
        print("dfusion: error: with --detections, replay takes the BAG only (the tracker's settings are options), "
              f"got {len(args.paths)} paths", file=sys.stderr)
        return 2
    refused = [o for o in ("topic", "plot", "csv", "topdown", "mcap", "plugin", "fusion", "seed") if getattr(args, o)]
    if refused or args.arrival != "stamp":
        what = f"--{refused[0]}" if refused else "--arrival record"
        print(f"dfusion: error: {what} does not apply to --detections (the tracker takes the scans in stamp order; "
              f"its output is --json)", file=sys.stderr)
        return 2
    m, _, n = args.confirm.partition("/")
    try:
        confirm = (int(m), int(n))
    except ValueError:
        print(f"dfusion: error: --confirm wants M/N (e.g. 3/5), got {args.confirm!r}", file=sys.stderr)
        return 2
    topics = [parse_detection_topic(t, std=args.std, detection_probability=args.detection_probability,
                                    clutter_density=args.clutter_density) for t in args.detections]
    settings = TrackerSettings(association=args.association, q=args.process_noise,
                               velocity_std=args.velocity_std or None, confirm=confirm, max_age=args.max_age, max_misses=args.max_misses or None)
    result = replay_tracks(args.paths[0], topics, settings=settings, frame=args.frame, truth_topics=args.truth,
                           origin_ns=args.origin_ns, duration=args.duration, msgdefs=msgdefs_from_files(args.msg))
    print(result.table())
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(result.to_json())
        print(f"wrote {args.json}")
    return 0


def _launch(make_launcher):
    """Make a launcher and run it, SIGTERM and SIGINT stopping it (every node within 2 s):
    ``(launcher, result, None)``, or ``(launcher, None, exit status)`` when stopped."""
    import signal

    stop: list[str] = []
    launcher = None

    def on_signal(signum, frame):   # only sets a flag; the launcher stops every node
        stop.append(signal.Signals(signum).name)
        if launcher is not None:
            launcher.request_stop(stop[0])

    codes = {"SIGTERM": 128 + signal.SIGTERM, "SIGINT": 128 + signal.SIGINT}
    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        launcher = make_launcher()
        if stop:
            return launcher, None, codes.get(stop[0], 1)
        result = launcher.run()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if result is None:
        print(f"dfusion: stopped ({launcher.stop_reason}); every node process was stopped", file=sys.stderr)
        return launcher, None, codes.get(launcher.stop_reason or "", 1)
    return launcher, result, None


def _run(args: argparse.Namespace) -> int:
    from dfusion.scenario.loader import load_scenario

    sc = load_scenario(args.scenario, seed=args.seed, duration=args.duration, plugins=args.plugin)
    if sc.multi_target:
        return _run_tracking(sc, args)

    def make_launcher():
        from dfusion.run.common import security_from_args
        from dfusion.run.launcher import Launcher, Restart, RunOptions
        from dfusion.run.supervision import RestartPolicy

        policy = RestartPolicy(enabled=not args.no_supervise, max_restarts=args.max_restarts,
                               backoff=args.restart_backoff, backoff_max=max(args.restart_backoff, 8.0))
        return Launcher(RunOptions(
            scenario=args.scenario, seed=args.seed, fusion=args.fusion, duration=args.duration, speed=args.speed,
            run_dir=args.run_dir, network=args.network, network_key_file=args.network_key_file,
            restarts=[Restart.parse(r) for r in args.restart], emulate_links=args.emulate_links,
            round_timeout=args.round_timeout, progress=not args.quiet,
            startup_timeout=args.startup_timeout, keep_run_dir=args.run_dir is not None, plugins=list(args.plugin),
            security=security_from_args(args), supervision=policy, foxglove=args.foxglove,
            nodes_per_process=args.nodes_per_process, sends=args.sends, min_send_interval=args.min_send_interval,
            chaos_dir=args.chaos_dir,
        ))

    launcher, result, code = _launch(make_launcher)
    if result is None:
        return code
    from dfusion.run.launcher import supervision_lines
    from dfusion.run.monitor import run_table

    print(result.table())
    print(run_table(result))
    print(supervision_lines(result))
    if args.compare:
        from dfusion.sim.runner import run_scenario

        ref = run_scenario(launcher.sc).metrics
        print("\nagainst dfusion simulate (same scenario and seed):")
        print(f"{'node':<10} {'RMSE run':>9} {'RMSE sim':>9} {'diff':>9} {'gap run':>9} {'gap sim':>9}")
        for name, v in result.metrics["nodes"].items():
            r = ref["nodes"][name]
            print(f"{name:<10} {v['rmse']:9.4f} {r['rmse']:9.4f} {v['rmse'] - r['rmse']:+9.4f} "
                  f"{v['final_gap']:9.1e} {r['final_gap']:9.1e}")
    run = result.metrics["run"]
    title = (f"{Path(launcher.sc.path).name} as processes at x{run['speed']:g}: estimate − truth per node vs "
             f"centralized EKF\n{run['links']}; {'mutual TLS' if run['tls'] else 'no TLS'}")
    _outputs(result, args, title=title)
    return 1 if launcher.failures else 0


#: ``dfusion run`` flags that do not apply to a multi-target scenario, and their defaults.
_NOT_FOR_TRACKING = {"fusion": None, "sends": None, "min_send_interval": None, "nodes_per_process": 1, "restart": [],
                     "foxglove": None, "emulate_links": True, "no_supervise": False, "chaos_dir": None, "csv": None,
                     "tls_dir": None, "tls_ca": None, "tls_cert": None, "tls_key": None, "speed": 1.0}


def _run_tracking(sc, args: argparse.Namespace) -> int:
    """``dfusion run`` of a multi-target scenario: a process per TrackingNode in lockstep
    (:mod:`dfusion.run.tracking`); ``--compare`` also runs ``simulate`` and compares per node."""
    given = [k for k, default in _NOT_FOR_TRACKING.items() if getattr(args, k, default) != default]
    if given:
        raise DfusionError(f"--{given[0].replace('_', '-')} is not available for a multi-target scenario "
                           f"(dfusion run runs every tracking node in lockstep; docs/processes.md)")
    from dfusion.run.tracking import TrackingLauncher, TrackingRunOptions

    launcher, result, code = _launch(lambda: TrackingLauncher(TrackingRunOptions(
        scenario=args.scenario, seed=args.seed, duration=args.duration, run_dir=args.run_dir, network=args.network,
        network_key_file=args.network_key_file, plugins=list(args.plugin), startup_timeout=args.startup_timeout,
        lag_timeout=args.lag_timeout, keep_run_dir=args.run_dir is not None)))
    if result is None:
        return code
    print(result.table())
    run = result.metrics["run"]
    lags = sum(run["lags"].values())
    print(f"run: {run['processes']} processes over Zenoh in lockstep, {run['wall_s']:.1f} s after a start-up of "
          f"{run['startup_s']:.1f} s; {lags} lags (a neighbour's frame not there within {run['lag_timeout']:g} s)"
          + ("" if lags else ": the tracks are simulate's"))
    if args.compare:
        from dfusion.run.tracking import compare_with_simulate

        print(compare_with_simulate(result))
    _tracking_outputs(sc, result, args)
    return 1 if launcher.failures else 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dfusion", description="Decentralized sensor fusion on trees of fusion nodes.")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="run a scenario in one process against the centralized EKF")
    s.add_argument("scenario", help="scenario TOML file (see docs/scenarios.md)")
    s.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    s.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    s.add_argument("--duration", type=float, default=None, help="override the scenario's duration (seconds)")
    _output_options(s)
    _send_options(s)
    s.add_argument("--frames", metavar="OUT.png", help="links that change: write top-down frames of the fusion tree "
                                                       "over time, with the robots and the person "
                                                       "(docs/dynamic-topology.md)")
    s.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable; docs/new-sensor-kind.md)")
    s.add_argument("--no-protection", action="store_true",
                   help="no clutter model (cameras: hard gate only) and no consistency test of neighbours "
                        "(protection.enabled = false; docs/clutter.md)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("--foxglove", type=int, default=None, metavar="PORT",
                   help="serve the run live to Foxglove on this port (needs pip install 'dfusion[live]'; docs/ros.md)")
    s.add_argument("--speed", type=float, default=1.0,
                   help="with --foxglove: scenario seconds per wall-clock second (default 1)")
    s.set_defaults(func=_simulate)

    r = sub.add_parser("run", help="run a scenario with one OS process per node, over Zenoh (docs/processes.md)")
    r.add_argument("scenario", help="scenario TOML file (see docs/scenarios.md)")
    r.add_argument("--speed", type=float, default=1.0, help="scenario seconds per wall-clock second (default 1: real time)")
    r.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    r.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    r.add_argument("--duration", type=float, default=None, help="override the scenario's duration (seconds)")
    _output_options(r)
    _send_options(r)
    r.add_argument("--nodes-per-process", type=int, default=1, metavar="N",
                   help="run up to N nodes in each OS process, over one Zenoh session (default 1: a process per "
                        "node; docs/processes.md)")
    r.add_argument("--restart", action="append", default=[], metavar="NAME@T[+D]",
                   help="SIGKILL node NAME (its process: with --nodes-per-process, its host and every node in it) at "
                        "scenario time T and start it again D seconds later (repeatable)")
    r.add_argument("--network-key-file", default=None,
                   help="authenticate every message with this key (or set $DFUSION_NETWORK_KEY_FILE / "
                        "$DFUSION_NETWORK_KEY; default: a random key for this run)")
    r.add_argument("--emulate-links", dest="emulate_links", action="store_true", default=True,
                   help="apply the scenario's links (latency, jitter, drops, duplicates, reordering, outages) at the "
                        "senders (the default)")
    r.add_argument("--foxglove", type=int, default=None, metavar="PORT",
                   help="serve the nodes' estimates live over Foxglove's WebSocket protocol (pip install 'dfusion[live]')")
    r.add_argument("--no-emulate-links", dest="emulate_links", action="store_false",
                   help="send over the real network only, ignoring the scenario's link settings")
    r.add_argument("--no-supervise", action="store_true",
                   help="do not restart node processes that exit before their final estimate")
    r.add_argument("--max-restarts", type=int, default=10, metavar="N",
                   help="restarts per node at most (default 10)")
    r.add_argument("--restart-backoff", type=float, default=0.5, metavar="S",
                   help="seconds before a restart; doubles with every quick failure in a row, up to 8 s (default 0.5)")
    r.add_argument("--round-timeout", type=float, default=10.0,
                   help="seconds a node waits for a live neighbour's message of a final-phase round")
    r.add_argument("--run-dir", default=None, help="keep logs, state logs and results here (default: a temporary directory)")
    r.add_argument("--network", default=None, help="Zenoh network name (default: unique per run)")
    r.add_argument("--startup-timeout", type=float, default=60.0, help="seconds to wait for every node to be ready")
    r.add_argument("--compare", action="store_true", help="also run simulate and compare RMSE and final gaps "
                                                          "(multi-target: every node's metrics and tracks)")
    r.add_argument("--lag-timeout", type=float, default=10.0, metavar="S",
                   help="multi-target lockstep: seconds a node waits for a neighbour's step frame before it goes on "
                        "(a counted lag; default 10)")
    r.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable; every node process loads it too)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.add_argument("--chaos-dir", default=None, metavar="DIR",
                   help="testing only (benchmarks/chaos.py): the nodes apply the one-sided link lapses requested in "
                        "DIR (docs/chaos.md); off by default")
    from dfusion.run.common import add_tls_arguments

    add_tls_arguments(r)
    r.set_defaults(func=_run)

    b = sub.add_parser("replay", help="run a scenario's nodes on the measurements of a ROS bag, or track the "
                                      "detections of a bag (docs/ros.md)")
    b.add_argument("paths", nargs="+", metavar="PATH",
                   help="SCENARIO BAG with --topic: a scenario TOML file (the nodes, their sensor kinds, the tree) and "
                        "a ROS 1 .bag file or ROS 2 bag directory (sqlite3 or MCAP); BAG alone with --detections")
    b.add_argument("--topic", action="append", default=[], metavar="TOPIC=NODE[:FILE.py:FUNC]",
                   help="feed NODE from TOPIC (standard message types, or a function f(msg, t) -> z); repeatable")
    b.add_argument("--detections", action="append", default=[], metavar="TOPIC=SENSOR[:FILE.py:FUNC][,KEY=VALUE]",
                   help="track the detection arrays of TOPIC (PoseArray, vision_msgs Detection3DArray, "
                        "Detection2DArray with homography=FILE, or a function f(msg, t) -> (k, 2) positions) with the "
                        "multi-target tracker; keys std, pd, clutter, homography, ground_frame; repeatable "
                        "(docs/ros.md, docs/multi-target.md)")
    b.add_argument("--truth", action="append", default=[], metavar="TOPIC",
                   help="ground truth (Odometry, PoseStamped, ...); with --detections one topic per target, or a "
                        "Detection3DArray of every target named by its id (repeatable)")
    b.add_argument("--arrival", choices=("stamp", "record"), default="stamp",
                   help="when a message reaches its node: at its header stamp (default) or at its record time "
                        "(late messages are then late measurements)")
    b.add_argument("--msg", action="append", default=[], metavar="FILE.msg",
                   help="a message definition (.../PKG/msg/TYPE.msg or PKG/msg/TYPE=FILE) for bags that store none "
                        "(Humble sqlite3); repeatable")
    b.add_argument("--origin-ns", type=int, default=None,
                   help="header stamp (ns) of scenario time 0 (default: the earliest stamp of the topics read)")
    b.add_argument("--seed", type=int, default=None, help="override the scenario's seed (particle filters)")
    b.add_argument("--fusion", choices=("channel", "naive"), default=None, help="override the fusion mode")
    b.add_argument("--duration", type=float, default=None, help="override the scenario's duration (seconds)")
    t = b.add_argument_group("the tracker of --detections (docs/multi-target.md; defaults: benchmarks/multi_target.py)")
    t.add_argument("--frame", default="map", help="fixed frame of the tracks; detections in other frames are moved "
                                                  "into it with /tf_static (default map)")
    t.add_argument("--association", choices=("jpda", "gnn"), default="jpda", help="data association (default jpda)")
    t.add_argument("--std", type=float, default=0.3,
                   help="noise std (m) of a detection whose message states no covariance (default 0.3)")
    t.add_argument("--detection-probability", type=float, default=0.9, help="P_D of a target in view (default 0.9)")
    t.add_argument("--clutter-density", type=float, default=0.0025,
                   help="false detections per m^2 per message (default 0.0025: 3 per frame on 40 x 30 m)")
    t.add_argument("--process-noise", type=float, default=0.05,
                   help="acceleration noise spectral density q of the tracks (m^2/s^3, default 0.05)")
    t.add_argument("--velocity-std", type=float, default=1.5,
                   help="prior std (m/s) of a new track's velocity; 0: none (default 1.5)")
    t.add_argument("--confirm", default="3/5", metavar="M/N", help="confirm a track after M hits in N scans (3/5)")
    t.add_argument("--max-age", type=float, default=0.45, help="delete a track without a hit for this long (s, 0.45)")
    t.add_argument("--max-misses", type=int, default=0,
                   help="also delete after this many consecutive misses in view (0: off; only when every sensor "
                        "sees the whole area)")
    _output_options(b)
    b.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                   help="load sensor kinds / policies from this module or .py file (repeatable)")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    b.set_defaults(func=_replay)
    return p


def _send_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sends", choices=("event", "periodic"), default=None,
                   help="override when nodes send: 'event' (news at once, rate-limited per link, plus the periodic "
                        "heartbeat) or 'periodic' (every send period only; the default); docs/dynamic-topology.md")
    p.add_argument("--min-send-interval", type=float, default=None, metavar="S",
                   help="override the least seconds between two messages of a node on one link (event sends; "
                        "default 0.05)")


def _output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", metavar="OUT", help="write the figures and the per-step series as JSON")
    p.add_argument("--csv", metavar="OUT.csv", help="write the per-step series (truth, estimates, variances, NEES, "
                                                    "gaps per node) as CSV")
    p.add_argument("--plot", metavar="OUT.png", help="write a PNG of every node's error against the centralized EKF")
    p.add_argument("--topdown", metavar="OUT.png", help="write the top-down figure (truth, estimates with 3-sigma "
                                                        "ellipses, sensors, the tree)")
    p.add_argument("--mcap", metavar="OUT.mcap", help="write an MCAP recording to open in Foxglove (docs/ros.md)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except DfusionError as exc:
        print(f"dfusion: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"dfusion: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
