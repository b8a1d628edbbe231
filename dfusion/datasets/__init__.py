"""Readers of public datasets used to evaluate dfusion (data not bundled; pass the path)."""
from dfusion.datasets.ble_rssi import (
    BLERSSIDataset,
    Receiver,
    Track,
    find_dataset_root,
    read_devices,
    read_track,
)
from dfusion.datasets.carmen import CarmenLog, LaserScan, beam_angles, read_carmen
from dfusion.datasets.mrclam import (
    ROBOTS,
    MRCLAMDataset,
    RobotLog,
    integrate_odometry,
    interpolate_poses,
    mean_velocities,
    read_landmarks,
    read_mrclam,
)

__all__ = [
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
    "read_landmarks",
    "integrate_odometry",
    "interpolate_poses",
    "mean_velocities",
    "ROBOTS",
]
