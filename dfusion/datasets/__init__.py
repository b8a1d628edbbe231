"""Readers for public datasets used to evaluate dfusion (data not bundled; pass the path)."""
from .ble_rssi import (
    BLERSSIDataset,
    PathLossCalibration,
    Receiver,
    Track,
    calibrate_path_loss,
    calibrate_radio_map,
    held_out_residuals,
    select_radio_map_settings,
    error_stats,
    find_dataset_root,
    read_devices,
    read_track,
    run_tracker,
    weighted_centroid,
)

__all__ = [
    "BLERSSIDataset",
    "Receiver",
    "Track",
    "read_devices",
    "read_track",
    "find_dataset_root",
    "PathLossCalibration",
    "calibrate_path_loss",
    "calibrate_radio_map",
    "held_out_residuals",
    "select_radio_map_settings",
    "weighted_centroid",
    "run_tracker",
    "error_stats",
]
