r"""Reader for the Indoor Location Competition 2.0 smartphone traces (magnetic, inertial, WiFi, iBeacon).

Source: GitHub ``location-competition/indoor-location-competition-20`` (MIT licence,
"Copyright (c) 2017-2020 XYZ10, Inc."). Cite: Indoor Location Competition 2.0 dataset,
Microsoft Research Asia and XYZ10 (https://github.com/location-competition/indoor-location-competition-20).

One trace is one walk with an Android phone: tab-separated lines ``time_ms TYPE values...``
(Unix time in ms); ``#`` lines are the header. Types read here:

========================  =============================================================
``TYPE_ACCELEROMETER``    x, y, z [m/s^2] in the phone's frame, accuracy
``TYPE_GYROSCOPE``        x, y, z [rad/s], accuracy
``TYPE_MAGNETIC_FIELD``   x, y, z [uT] in the phone's frame, accuracy
``TYPE_ROTATION_VECTOR``  x, y, z: vector part of the unit quaternion device -> world
                          (East, North, Up), ``w = sqrt(1 - x^2 - y^2 - z^2)``
``TYPE_WAYPOINT``         x, y [m]: ground truth in the floor's frame
``TYPE_WIFI``             ssid, bssid, RSSI [dBm], frequency [MHz], last-seen time [ms]
``TYPE_BEACON``           UUID, major, minor, tx power, RSSI [dBm], distance, MAC, time
========================  =============================================================

Lines of other types are skipped (counted in :attr:`IndoorTrace.n_skipped`); a line with the
wrong number of fields raises :class:`~dfusion.errors.ValidationError` naming the file and line.
Times are converted to seconds since the trace's first reading of any type.

A *WiFi scan* is the group of ``TYPE_WIFI`` lines with one time stamp; an entry whose last-seen
time is older than the scan by more than ``max_wifi_age`` seconds is a cached result of an earlier
scan and is dropped (counted in :attr:`IndoorTrace.n_stale_wifi`).

**Floor outline.** The floor's ``geojson_map.json`` is in longitude/latitude degrees (its
coordinates are near 120.07 E, 30.29 N), not in the waypoints' metres; :func:`read_floor_outline`
maps the floor polygon's bounding box linearly onto ``[0, width] x [0, height]`` of
``floor_info.json`` (the floor image's frame, which is the waypoints' frame).
"""
from __future__ import annotations

import gzip
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array

__all__ = [
    "IndoorTrace",
    "RadioScan",
    "read_trace",
    "read_floor",
    "read_floor_outline",
    "Floor",
]

_SENSORS = {
    "TYPE_ACCELEROMETER": "acc",
    "TYPE_GYROSCOPE": "gyro",
    "TYPE_MAGNETIC_FIELD": "mag",
    "TYPE_ROTATION_VECTOR": "rotvec",
}


@dataclass
class RadioScan:
    """One radio scan: its time [s] and the RSSI [dBm] of each transmitter heard (by id)."""

    t: float
    rssi: dict[str, float]


@dataclass
class IndoorTrace:
    """One walk. Sensor arrays are ``(n, 4)``: time [s] then x, y, z (accuracy dropped).

    ``waypoints`` is ``(m, 3)``: time [s], x [m], y [m]. ``t0_ms`` is the Unix time [ms] of
    time zero. ``wifi`` and ``beacons`` are lists of :class:`RadioScan` in time order
    (a beacon "scan" is one reading; its key is ``uuid:major:minor:mac``).
    """

    name: str
    t0_ms: int
    acc: Array
    gyro: Array
    mag: Array
    rotvec: Array
    waypoints: Array
    wifi: list[RadioScan]
    beacons: list[RadioScan]
    header: dict[str, str] = field(default_factory=dict)
    n_skipped: int = 0
    n_stale_wifi: int = 0

    @property
    def duration(self) -> float:
        """Time from the first to the last reading of any type [s]."""
        ends = [a[-1, 0] for a in (self.acc, self.gyro, self.mag, self.rotvec, self.waypoints) if len(a)]
        return float(max(ends)) if ends else 0.0


def _open(path: Path):
    return gzip.open(path, "rt", encoding="utf-8") if path.suffix == ".gz" else open(path, encoding="utf-8")


def read_trace(path: str | Path, max_wifi_age: float = 2.0) -> IndoorTrace:
    """Read one trace file (plain or gzipped text); see the module docstring for the format."""
    path = Path(path)
    if not path.is_file():
        raise ValidationError(f"trace file not found: {path}")
    rows: dict[str, list] = {k: [] for k in _SENSORS.values()}
    way: list = []
    wifi: dict[int, dict[str, float]] = {}
    beac: list[tuple[int, str, float]] = []
    header: dict[str, str] = {}
    skipped = stale = 0
    with _open(path) as fh:
        for ln, line in enumerate(fh, 1):
            line = line.rstrip("\n\r")
            if not line:
                continue
            if line.startswith("#"):
                for part in line[1:].split("\t"):
                    if ":" in part:
                        k, v = part.split(":", 1)
                        header.setdefault(k.strip(), v.strip())
                continue
            f = line.split("\t")
            if len(f) < 2:
                raise ValidationError(f"{path.name}:{ln}: expected 'time TYPE values', got {line[:60]!r}")
            kind = f[1]
            try:
                t = int(f[0])
                if kind in _SENSORS:
                    if len(f) < 5:
                        raise ValueError("fewer than 3 values")
                    rows[_SENSORS[kind]].append((t, float(f[2]), float(f[3]), float(f[4])))
                elif kind == "TYPE_WAYPOINT":
                    way.append((t, float(f[2]), float(f[3])))
                elif kind == "TYPE_WIFI":
                    if len(f) < 7:
                        raise ValueError("fewer than 5 values")
                    if t - int(f[6]) > max_wifi_age * 1000.0:
                        stale += 1
                        continue
                    wifi.setdefault(t, {})[f[3]] = float(f[4])
                elif kind == "TYPE_BEACON":
                    if len(f) < 10:
                        raise ValueError("fewer than 8 values")
                    beac.append((t, f"{f[2]}:{f[3]}:{f[4]}:{f[8]}", float(f[6])))
                else:
                    skipped += 1
            except ValueError as e:
                raise ValidationError(f"{path.name}:{ln}: bad {kind} line ({e})") from None
    starts = [r[0][0] for r in rows.values() if r] + [w[0] for w in way] + list(wifi) + [b[0] for b in beac]
    if not starts:
        raise ValidationError(f"{path.name}: no readings")
    t0 = min(starts)

    def arr(r: list, width: int) -> Array:
        a = np.array(r, dtype=float).reshape(-1, width)
        a[:, 0] = (a[:, 0] - t0) / 1000.0
        return a[np.argsort(a[:, 0], kind="stable")]

    return IndoorTrace(
        name=path.name.split(".")[0],
        t0_ms=int(t0),
        acc=arr(rows["acc"], 4), gyro=arr(rows["gyro"], 4), mag=arr(rows["mag"], 4), rotvec=arr(rows["rotvec"], 4),
        waypoints=arr(way, 3),
        wifi=[RadioScan((t - t0) / 1000.0, d) for t, d in sorted(wifi.items())],
        beacons=[RadioScan((t - t0) / 1000.0, {k: r}) for t, k, r in beac],
        header=header, n_skipped=skipped, n_stale_wifi=stale,
    )


@dataclass
class Floor:
    """One floor: its name, size [m] (``width``, ``height`` of ``floor_info.json``), traces, outline."""

    name: str
    width: float
    height: float
    traces: list[IndoorTrace]
    outline: list[Array]


def read_floor_outline(floor_dir: str | Path) -> list[Array]:
    """The floor polygon(s) of ``geojson_map.json`` as ``(k, 2)`` arrays in metres (see the module docstring).

    The feature whose ``properties.type`` is ``"floor"`` (else the first) gives the outline and the
    bounding box; returns the exterior ring of each of its polygons. Empty if there is no GeoJSON file.
    """
    d = Path(floor_dir)
    gj, info = d / "geojson_map.json", d / "floor_info.json"
    if not gj.is_file():
        return []
    mi = json.loads(info.read_text())["map_info"]
    feats = json.loads(gj.read_text()).get("features", [])
    if not feats:
        return []
    floor = next((f for f in feats if (f.get("properties") or {}).get("type") == "floor"), feats[0])
    geom = floor["geometry"]
    polys = geom["coordinates"] if geom["type"] == "MultiPolygon" else [geom["coordinates"]]
    rings = [np.asarray(p[0], dtype=float) for p in polys]
    allp = np.vstack(rings)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    scale = np.array([float(mi["width"]), float(mi["height"])]) / np.where(hi > lo, hi - lo, 1.0)
    return [(r - lo) * scale for r in rings]


def read_floor(floor_dir: str | Path, max_wifi_age: float = 2.0, limit: int | None = None) -> Floor:
    """Every trace of a floor directory (``path_data_files/*.txt[.gz]``, sorted by name), its size and outline."""
    d = Path(floor_dir)
    info = d / "floor_info.json"
    if not info.is_file():
        raise ValidationError(f"{d}: no floor_info.json (not a floor directory)")
    mi = json.loads(info.read_text())["map_info"]
    files = sorted(p for p in (d / "path_data_files").glob("*.txt*") if p.suffix in (".txt", ".gz"))
    if not files:
        raise ValidationError(f"{d}: no traces in path_data_files/")
    files = files[:limit] if limit else files
    return Floor(d.name, float(mi["width"]), float(mi["height"]),
                 [read_trace(p, max_wifi_age) for p in files], read_floor_outline(d))
