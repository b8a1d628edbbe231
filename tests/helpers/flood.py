"""A flood of publications at a ``dfusion run`` launcher's monitor, and the launcher's memory meanwhile.

Used by ``tests/run/test_monitor_flood.py`` (a short flood) and ``benchmarks/monitor_flood.py``
(the 20 s measurement). The flooder is a process of its own (in the test's process it would
share the GIL with what it floods); it connects to the monitor's endpoint (``run.json``) as
any local program can, and publishes payloads of ``size`` bytes on
``dfusion/NET/monitor/NODE`` as fast as Zenoh takes them (``CongestionControl.BLOCK``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

FLOODER = """
import sys, time, zenoh
from dfusion.transport.zenoh import ZenohConfig, open_session, close_session
endpoint, key, size, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
payload = bytes(size)
z = open_session(ZenohConfig(connect=(endpoint,)))
pub = z.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
time.sleep(0.5)
sent, t0 = 0, time.monotonic()
while time.monotonic() - t0 < seconds:
    pub.put(payload)
    sent += 1
print(sent, time.monotonic() - t0, flush=True)
close_session(z)
"""


def rss_mb(pid: int) -> tuple[float, float]:
    """``(VmRSS, VmHWM)`` of process ``pid`` in MB (its resident memory now, and its peak)."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024
    return fields["VmRSS"], fields["VmHWM"]


@dataclass
class FloodRun:
    """What :func:`run_with_flood` saw."""

    metrics: dict
    rss_before_mb: float           # the launcher's resident memory just before the flood
    rss_peak_mb: float             # its peak (VmHWM) at the end of the flood
    rss_samples_mb: list[float] = field(default_factory=list)
    sent: int = 0                  # publications the flooders made
    flood_s: float = 0.0
    launcher_rc: int | None = None


def run_with_flood(scenario: Path, run_dir: Path, *, size: int, flood_s: float, flooders: int = 1,
                   node: str = "a", speed: float = 1.0, timeout: float = 180.0) -> FloodRun:
    """``dfusion run SCENARIO`` as a process; once the run has started, ``flooders`` processes publish
    ``size``-byte payloads at its monitor for ``flood_s`` seconds; returns the run's JSON metrics and
    the launcher's memory. The scenario must last longer than the flood."""
    from tests.run.test_processes import start_cli_run

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = run_dir.parent / f"{run_dir.name}.json"
    launcher = start_cli_run(scenario, run_dir, timeout, ("--json", str(out), "--speed", repr(speed)))
    procs: list[subprocess.Popen] = []
    try:
        info = json.loads((run_dir / "run.json").read_text())
        key = f"dfusion/{info['network']}/monitor/{node}"
        before = rss_mb(launcher.pid)[0]
        procs = [subprocess.Popen([sys.executable, "-c", FLOODER, info["monitor_endpoint"], key, str(size),
                                   repr(flood_s)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
                 for _ in range(flooders)]
        samples = []
        while any(p.poll() is None for p in procs):
            samples.append(rss_mb(launcher.pid)[0])
            time.sleep(0.1)
        peak = rss_mb(launcher.pid)[1]
        sent = 0
        for p in procs:
            text, err = p.communicate()
            assert p.returncode == 0, err
            sent += int(text.split()[0])
        rc = launcher.wait(timeout=timeout)
        err = launcher.stderr.read()
        assert rc == 0, err[-3000:]
        return FloodRun(json.loads(out.read_text()), before, peak, samples, sent, flood_s, rc)
    finally:
        for p in [*procs, launcher]:
            if p.poll() is None:
                p.kill()
                p.wait()
