r"""Reader for the position-annotated BLE RSSI dataset (Daniş, Naskali, Cemgil & Ersoy).

Source: GitHub ``philotuxo/Position-Annotated-BLE-RSSI-Dataset`` (CC0 1.0).
Cite F. S. Daniş, A. T. Naskali, A. T. Cemgil and C. Ersoy, "An Indoor
Localization Dataset and Data Collection Framework with High Precision Position
Annotation", *Pervasive and Mobile Computing* 81, 2022; or F. S. Daniş,
A. T. Cemgil and C. Ersoy, "Adaptive sequential Monte Carlo filter for indoor
positioning and tracking with Bluetooth Low Energy beacons", *IEEE Access* 9,
37022-37038, 2021.

Layout of a dataset directory ``DIR``::

    DIR/cnf/tetam.dev      receivers ("Dongles:" + JSON) and the beacon ("Beacons:" + JSON)
    DIR/cnf/tetam.par      JSON; "limits" = [x_min, y_min, x_max, y_max] (m)
    DIR/occ/tetam_<c>.occ  occupancy grids (see NodeLattice.from_occ_file)
    DIR/trk/*.mbd          tracks: CSV, one row per received packet

Pitfalls handled here (documented in the dataset's README):

* track rows with a non-negative RSSI are not physical (``straight_05`` has two,
  +42 and +29 dBm) and are dropped (counted in ``Track.n_dropped``);
* timestamps are not strictly increasing (sub-millisecond steps back): rows
  are stably sorted by time;
* fields 8-16 (the orientation matrix) are often not a rotation and are ignored;
* in the ``.occ`` files 1 marks obstacles, although the source README says the
  opposite (see :meth:`NodeLattice.from_occ_file`);
* ground truth may lie slightly outside the area limits (``straight_03``
  reaches y = -0.14 m) and, on 2 % of rows, on an occupied node.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array
from dfusion.maps.lattice import NodeLattice

__all__ = [
    "BLERSSIDataset",
    "Receiver",
    "Track",
    "read_devices",
    "read_track",
    "find_dataset_root",
]

#: Name of the site in the configuration and occupancy file names.
SITE = "tetam"


@dataclass(frozen=True)
class Receiver:
    """A fixed BLE receiver: MAC address (12 lowercase hex digits), alias and position (m)."""

    mac: str
    alias: str
    position: Array


@dataclass
class Track:
    """One track: packets in time order, one row per packet received by one receiver.

    Attributes
    ----------
    name : str
        File name without ``_all_sensors.mbd``.
    t : (K,) float
        Receive time (Unix seconds).
    receiver : (K,) int
        Index of the receiving receiver in the dataset's receiver list.
    rssi : (K,) float
        RSSI (dBm).
    truth : (K, 3) float
        Ground-truth beacon position at that time (m).
    n_dropped : int
        Rows dropped as invalid (non-negative RSSI).
    """

    name: str
    t: Array
    receiver: np.ndarray
    rssi: Array
    truth: Array
    n_dropped: int = 0
    path: Path | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def duration(self) -> float:
        """Time between the first and the last packet (s)."""
        return float(self.t[-1] - self.t[0]) if len(self) else 0.0


def read_devices(path: str | Path) -> tuple[list[Receiver], dict[str, str]]:
    """Parse ``tetam.dev``: returns the receivers (file order) and ``{beacon MAC: alias}``.

    Each line is ``Dongles:`` or ``Beacons:`` followed by JSON
    ``{mac: [[x, y, z], colour, alias]}`` (split at the first ``:``).
    """
    path = Path(path)
    receivers: list[Receiver] = []
    beacons: dict[str, str] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        key, _, rest = line.partition(":")
        try:
            obj = json.loads(rest)
        except json.JSONDecodeError as exc:
            raise ValidationError(f"{path}: bad JSON after {key!r}: {exc}") from None
        if key.strip() == "Dongles":
            for mac, (pos, _colour, alias) in obj.items():
                p = np.array(pos, dtype=float)
                if p.shape != (3,):
                    raise ValidationError(f"{path}: receiver {mac} needs an [x, y, z] position, got {pos!r}")
                receivers.append(Receiver(mac.lower(), str(alias), p))
        elif key.strip() == "Beacons":
            beacons.update({mac.lower(): str(v[2]) for mac, v in obj.items()})
    if not receivers:
        raise ValidationError(f"{path}: no 'Dongles:' line")
    return receivers, beacons


def read_track(path: str | Path, receiver_macs: list[str], beacon: str | None = None) -> Track:
    """Read one ``*.mbd`` track file; receiver MACs are mapped to indices in ``receiver_macs``.

    Drops rows with RSSI >= 0 dBm, sorts stably by time, ignores the orientation
    fields. With ``beacon`` given, rows of other beacons are dropped too (counted).
    Raises :class:`ValidationError` on a malformed row or an unknown receiver.
    """
    path = Path(path)
    index = {m: i for i, m in enumerate(receiver_macs)}
    t, rec, rssi, truth = [], [], [], []
    dropped = 0
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        f = line.split(",")
        if len(f) < 7:
            raise ValidationError(f"{path}:{lineno}: expected at least 7 fields, got {len(f)}")
        mac = f[1].strip().lower()
        if mac not in index:
            raise ValidationError(f"{path}:{lineno}: unknown receiver {mac!r}")
        try:
            ti, ri = float(f[0]), float(f[3])
            xyz = (float(f[4]), float(f[5]), float(f[6]))
        except ValueError:
            raise ValidationError(f"{path}:{lineno}: non-numeric field") from None
        if ri >= 0 or (beacon is not None and f[2].strip().lower() != beacon):
            dropped += 1
            continue
        t.append(ti)
        rec.append(index[mac])
        rssi.append(ri)
        truth.append(xyz)
    if not t:
        raise ValidationError(f"{path}: no valid rows")
    t_a = np.array(t)
    order = np.argsort(t_a, kind="stable")
    name = path.name.removesuffix(".mbd").removesuffix("_all_sensors")
    return Track(name, t_a[order], np.array(rec, dtype=np.int64)[order], np.array(rssi)[order],
                 np.array(truth)[order], dropped, path)


def find_dataset_root(track_path: str | Path) -> Path | None:
    """The dataset directory holding a track file (``DIR`` for ``DIR/trk/x.mbd``), if it looks like one."""
    p = Path(track_path).resolve().parent
    for cand in (p.parent, p):
        if (cand / "cnf" / f"{SITE}.dev").is_file():
            return cand
    return None


class BLERSSIDataset:
    """A dataset directory (full dataset or a slice with the same layout).

    Parameters
    ----------
    root : path
        Directory containing ``cnf/``, ``occ/`` and ``trk/``.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        dev = self.root / "cnf" / f"{SITE}.dev"
        if not dev.is_file():
            raise ValidationError(f"{self.root} is not a BLE RSSI dataset directory (no cnf/{SITE}.dev)")
        self.receivers, self.beacons = read_devices(dev)
        par = self.root / "cnf" / f"{SITE}.par"
        self.limits = np.array(json.loads(par.read_text())["limits"], dtype=float) if par.is_file() else None

    def __repr__(self) -> str:
        return f"BLERSSIDataset({str(self.root)!r}, receivers={len(self.receivers)}, tracks={self.track_names()})"

    @property
    def receiver_macs(self) -> list[str]:
        return [r.mac for r in self.receivers]

    @property
    def receiver_positions(self) -> Array:
        """``(m, 3)`` receiver positions (m)."""
        return np.array([r.position for r in self.receivers])

    def track_paths(self) -> list[Path]:
        """Track files in ``trk/``, sorted by name."""
        return sorted((self.root / "trk").glob("*_all_sensors.mbd"))

    def track_names(self) -> list[str]:
        return [p.name.removesuffix(".mbd").removesuffix("_all_sensors") for p in self.track_paths()]

    def load_track(self, name_or_path: str | Path) -> Track:
        """Load a track by name (``straight_03``), file name, or path."""
        p = Path(name_or_path)
        if not p.is_file():
            p = self.root / "trk" / f"{name_or_path}_all_sensors.mbd"
        if not p.is_file():
            raise ValidationError(f"no track {name_or_path!r} in {self.root / 'trk'}")
        beacon = next(iter(self.beacons)) if len(self.beacons) == 1 else None
        return read_track(p, self.receiver_macs, beacon)

    def grid_cells(self) -> list[float]:
        """Cell sizes of the occupancy grids present."""
        out = []
        for p in (self.root / "occ").glob(f"{SITE}_*.occ"):
            try:
                out.append(float(p.stem.split("_", 1)[1]))
            except ValueError:
                pass
        return sorted(out)

    def load_grid(self, cell: float = 0.2) -> NodeLattice:
        """Occupancy grid with the given cell size (1 = occupied; see the module docstring)."""
        p = self.root / "occ" / f"{SITE}_{cell:g}.occ"
        if not p.is_file():
            p = self.root / "occ" / f"{SITE}_{cell:.1f}.occ"
        if not p.is_file():
            raise ValidationError(f"no occupancy grid with cell {cell} m in {self.root / 'occ'} "
                                  f"(present: {self.grid_cells()})")
        return NodeLattice.from_occ_file(p)
