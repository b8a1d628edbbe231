"""Particle filters: a generic vectorized filter, an occupancy grid, and the WSN RSSI tracker."""
from .occupancy import OccupancyGrid
from .particle_filter import (
    ParticleDepletionError,
    ParticleFilter,
    effective_sample_size,
    normalize_log_weights,
    roughening_std,
    stratified_resample,
    systematic_counts,
    systematic_resample,
    weighted_mean_cov,
)
from .radio_map import (
    RadioMap,
    fit_directional_path_loss,
    fit_radio_map,
    fit_radio_maps,
    fit_split_normal,
    kernel_residual_map,
    path_loss_design,
    split_normal_logpdf,
)
from .wsn import WSNTracker, project_psd_information

__all__ = [
    "ParticleFilter",
    "ParticleDepletionError",
    "effective_sample_size",
    "normalize_log_weights",
    "systematic_counts",
    "systematic_resample",
    "stratified_resample",
    "roughening_std",
    "weighted_mean_cov",
    "OccupancyGrid",
    "WSNTracker",
    "RadioMap",
    "fit_radio_map",
    "kernel_residual_map",
    "fit_radio_maps",
    "fit_directional_path_loss",
    "path_loss_design",
    "split_normal_logpdf",
    "fit_split_normal",
    "project_psd_information",
]
