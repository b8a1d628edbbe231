"""Readers of public datasets used to evaluate dfusion (data not bundled; pass the path)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.datasets.indoor import IndoorTrace, RadioScan, Floor, read_trace, read_floor, read_floor_outline
    from dfusion.datasets.ble_rssi import BLERSSIDataset, Receiver, Track, find_dataset_root, read_devices, read_track
    from dfusion.datasets.carmen import CarmenLog, LaserScan, beam_angles, read_carmen
    from dfusion.datasets.mrclam import ROBOTS, MRCLAMDataset, RobotLog, integrate_odometry, interpolate_poses, mean_velocities, perturb_mrclam, PERTURBATIONS, read_landmarks, read_mrclam

__all__ = [
    "IndoorTrace",
    "RadioScan",
    "Floor",
    "read_trace",
    "read_floor",
    "read_floor_outline",
    "BLERSSIDataset",
    "Receiver",
    "Track",
    "read_devices",
    "read_track",
    "find_dataset_root",
    "LaserScan",
    "CarmenLog",
    "read_carmen",
    "beam_angles",
    "RobotLog",
    "MRCLAMDataset",
    "read_mrclam",
    "perturb_mrclam",
    "PERTURBATIONS",
    "read_landmarks",
    "integrate_odometry",
    "interpolate_poses",
    "mean_velocities",
    "ROBOTS",
]

_WHERE = {
    "IndoorTrace": ("dfusion.datasets.indoor", "IndoorTrace"),
    "RadioScan": ("dfusion.datasets.indoor", "RadioScan"),
    "Floor": ("dfusion.datasets.indoor", "Floor"),
    "read_trace": ("dfusion.datasets.indoor", "read_trace"),
    "read_floor": ("dfusion.datasets.indoor", "read_floor"),
    "read_floor_outline": ("dfusion.datasets.indoor", "read_floor_outline"),
    "read_landmarks": ("dfusion.datasets.mrclam", "read_landmarks"),
    "BLERSSIDataset": ("dfusion.datasets.ble_rssi", 'BLERSSIDataset'),
    "Receiver": ("dfusion.datasets.ble_rssi", 'Receiver'),
    "Track": ("dfusion.datasets.ble_rssi", 'Track'),
    "find_dataset_root": ("dfusion.datasets.ble_rssi", 'find_dataset_root'),
    "read_devices": ("dfusion.datasets.ble_rssi", 'read_devices'),
    "read_track": ("dfusion.datasets.ble_rssi", 'read_track'),
    "CarmenLog": ("dfusion.datasets.carmen", 'CarmenLog'),
    "LaserScan": ("dfusion.datasets.carmen", 'LaserScan'),
    "beam_angles": ("dfusion.datasets.carmen", 'beam_angles'),
    "read_carmen": ("dfusion.datasets.carmen", 'read_carmen'),
    "ROBOTS": ("dfusion.datasets.mrclam", 'ROBOTS'),
    "MRCLAMDataset": ("dfusion.datasets.mrclam", 'MRCLAMDataset'),
    "RobotLog": ("dfusion.datasets.mrclam", 'RobotLog'),
    "integrate_odometry": ("dfusion.datasets.mrclam", 'integrate_odometry'),
    "interpolate_poses": ("dfusion.datasets.mrclam", 'interpolate_poses'),
    "mean_velocities": ("dfusion.datasets.mrclam", 'mean_velocities'),
    "read_mrclam": ("dfusion.datasets.mrclam", 'read_mrclam'),
    "perturb_mrclam": ("dfusion.datasets.mrclam", 'perturb_mrclam'),
    "PERTURBATIONS": ("dfusion.datasets.mrclam", 'PERTURBATIONS'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
