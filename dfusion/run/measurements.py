"""A node's own measurements: from the simulated world, from a recording, and its state log.

Recording formats (one node's measurements, or several nodes' with a ``node`` field):

* **JSON lines** (``.jsonl`` or ``.json``): one object per line,
  ``{"t": 1.2, "z": [0.3, -1.1], "arrival": 1.25, "node": "a"}``; ``arrival``
  defaults to ``t``, ``node`` to the node reading the file. Blank lines and
  lines starting with ``#`` are skipped.
* **NumPy** (``.npz``): arrays ``t`` (m,), ``z`` (m, dim_z), optional
  ``arrival`` (m,) and ``node`` (m,) of strings.

``python -m dfusion.run.node_process --scenario F --node a --record OUT.jsonl``
writes node ``a``'s measurements of scenario ``F`` in the first format.

The **state log** (:class:`MeasurementLog`) is an append-only JSON-lines file
``<state-dir>/<node>.measurements.jsonl``: a header line naming the run, then
one line per measurement the node fused, written and flushed *before* the
measurement is fused. A restarted node replays it (see ``docs/processes.md``).
A log whose header names another run is started afresh; a torn last line (the
process died while writing it) is ignored.

The **incarnation epoch** of a node (:func:`claim_epoch`) is recorded next to it, in
``<state-dir>/<node>.epoch``, so that a restarted node's epoch is strictly newer than
every earlier one even if the wall clock went backwards meanwhile.
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.scenario.spec import Scenario

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OwnMeasurement:
    """A measurement taken at ``t`` that reaches its node at ``arrival``."""

    t: float
    z: Array
    arrival: float

    @property
    def key(self) -> int:
        """Identity of the measurement within one node (its time in nanoseconds)."""
        return int(round(self.t * 1e9))

    def to_json(self) -> dict:
        return {"t": self.t, "z": [float(v) for v in np.atleast_1d(self.z)], "arrival": self.arrival}


def _ordered(meas: Iterable[OwnMeasurement]) -> list[OwnMeasurement]:
    # the order dfusion.sim.runner fuses them in: by arrival, then time
    return sorted(meas, key=lambda m: (m.arrival, m.t))


def world_measurements(sc: Scenario, node: str, world=None) -> list[OwnMeasurement]:
    """``node``'s measurements in scenario ``sc`` (the world of ``sc.seed``), in fusing order."""
    if node not in sc.nodes:
        raise ValidationError(f"{node!r} is not a node of {sc.path}")
    return nodes_measurements(sc, world, [node])[node]


def nodes_measurements(sc: Scenario, world=None, nodes: Iterable[str] | None = None) -> dict[str, list[OwnMeasurement]]:
    """Every node's measurements (or those of ``nodes``) in the world of ``sc.seed``, in fusing order."""
    if world is None:
        from dfusion.sim.world import simulate_world   # a node given a recording never simulates the world

        world = simulate_world(sc)
    out: dict[str, list[OwnMeasurement]] = {n: [] for n in (sorted(sc.nodes) if nodes is None else nodes)}
    for m in world.measurements:
        mine = out.get(m.node)
        if mine is not None:
            mine.append(OwnMeasurement(m.t, np.asarray(m.z, float), m.arrival))
    return {n: _ordered(meas) for n, meas in out.items()}


def load_recording(path: str | Path, node: str) -> list[OwnMeasurement]:
    """Read ``node``'s measurements from a JSON-lines or ``.npz`` recording (see the module docstring)."""
    path = Path(path)
    out: list[OwnMeasurement] = []
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as d:
            t = np.asarray(d["t"], float)
            z = np.asarray(d["z"], float).reshape(len(t), -1)
            arrival = np.asarray(d["arrival"], float) if "arrival" in d else t
            names = [str(s) for s in d["node"]] if "node" in d else [node] * len(t)
        for i in range(len(t)):
            if names[i] == node:
                out.append(OwnMeasurement(float(t[i]), z[i].copy(), float(arrival[i])))
    else:
        for lineno, line in enumerate(path.read_text().splitlines(), 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                d = json.loads(line)
                if d.get("node", node) != node:
                    continue
                t = float(d["t"])
                out.append(OwnMeasurement(t, np.asarray(d["z"], float).reshape(-1), float(d.get("arrival", t))))
            except (ValueError, KeyError, TypeError) as exc:
                raise ValidationError(f"{path}:{lineno}: not a measurement ({exc})") from None
    for m in out:
        if not (np.isfinite(m.t) and np.isfinite(m.arrival) and np.all(np.isfinite(m.z))) or m.arrival < m.t:
            raise ValidationError(f"{path}: invalid measurement at t={m.t} (non-finite, or arrival before t)")
    return _ordered(out)


def save_recording(path: str | Path, node: str, meas: Iterable[OwnMeasurement]) -> Path:
    """Write ``meas`` as JSON lines (``.jsonl``) or ``.npz``, by the suffix of ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meas = list(meas)
    if path.suffix == ".npz":
        np.savez(path, t=np.array([m.t for m in meas]), z=np.array([np.atleast_1d(m.z) for m in meas]),
                 arrival=np.array([m.arrival for m in meas]), node=np.array([node] * len(meas)))
    else:
        with path.open("w") as f:
            for m in meas:
                f.write(json.dumps({"node": node, **m.to_json()}) + "\n")
    return path


#: The largest incarnation epoch (the wire format's bound, ``docs/wire-format.md``).
MAX_EPOCH = 2**63 - 1


def claim_epoch(state_dir: str | Path, node: str, now_ns: int | None = None, *, fsync: bool = True) -> int:
    """A new incarnation epoch for ``node``: ``max(clock, last + 1)``, recorded before it is used.

    ``clock`` is the wall clock in nanoseconds (``now_ns``, default :func:`time.time_ns`);
    ``last`` is the epoch recorded in ``<state_dir>/<node>.epoch`` by the previous incarnation
    (0 when there is none, or when the file is unreadable). The new epoch is written there
    (a temporary file renamed over the old one, flushed to disk with ``fsync``) before it is
    returned, so the neighbours, which reject messages of an epoch older than the newest they
    have seen (reason ``previous-incarnation``), accept the restarted node even if the clock
    was set back between two incarnations.
    """
    path = Path(state_dir) / f"{node}.epoch"
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        last = int(path.read_text().strip())
    except (OSError, ValueError):
        last = 0
    now = time.time_ns() if now_ns is None else int(now_ns)
    epoch = max(now, last + 1, 1)
    if epoch > MAX_EPOCH:
        raise ValidationError(f"epoch of {node} would exceed 2^63 - 1 (last {last})")
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as f:
        f.write(f"{epoch}\n")
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    tmp.replace(path)
    if now < last + 1:
        log.warning("%s: the clock (%d ns) is behind the previous incarnation's epoch (%d): epoch %d", node, now,
                    last, epoch)
    return epoch


class MeasurementLog:
    """Append-only log of the measurements a node fused, in ``state_dir``.

    Parameters
    ----------
    state_dir : path
        Directory (created if needed).
    node : str
        The node; the file is ``<node>.measurements.jsonl``.
    run_id : str
        Identifies the run; a log of another run is discarded.
    fsync : bool
        ``os.fsync`` after each line (survives a power cut, not just a crash).
    """

    def __init__(self, state_dir: str | Path, node: str, run_id: str, *, fsync: bool = False) -> None:
        self.path = Path(state_dir) / f"{node}.measurements.jsonl"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.node, self.run_id, self.fsync = node, str(run_id), fsync
        self.entries: list[OwnMeasurement] = self._read()
        if self.entries is None:
            self.entries = []
            self._file = self.path.open("w")
            self._write({"run": self.run_id, "node": node, "format": 1})
        else:
            data = self.path.read_bytes()
            if not data.endswith(b"\n"):   # a torn last line: cut it off before appending
                with self.path.open("r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
            self._file = self.path.open("a")

    def _read(self) -> list[OwnMeasurement] | None:
        if not self.path.exists():
            return None
        lines = self.path.read_text().split("\n")
        try:
            head = json.loads(lines[0])
        except (ValueError, IndexError):
            return None
        if head.get("run") != self.run_id or head.get("node") != self.node:
            log.info("%s: state log %s belongs to another run: starting afresh", self.node, self.path)
            return None
        out = []
        for line in lines[1:]:
            if not line.strip():
                continue
            try:
                d = json.loads(line)
                out.append(OwnMeasurement(float(d["t"]), np.asarray(d["z"], float), float(d["arrival"])))
            except (ValueError, KeyError, TypeError):
                log.warning("%s: ignoring a torn line in %s", self.node, self.path)
        return out

    def _write(self, obj: dict) -> None:
        self._file.write(json.dumps(obj) + "\n")
        self._file.flush()
        if self.fsync:
            os.fsync(self._file.fileno())

    def append(self, m: OwnMeasurement) -> None:
        """Record ``m`` (call before fusing it)."""
        self._write(m.to_json())
        self.entries.append(m)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> MeasurementLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
