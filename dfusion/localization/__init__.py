"""Localizers and trackers, each an :class:`~dfusion.estimation.Estimator`: MCL, ICP, odometry EKF, landmark EKF, environmental camera, WSN tracker; radio maps and their calibration; scan similarity."""
from dfusion.localization.env_camera import EnvironmentCameraLocalizer
from dfusion.localization.icp import ICPResult, ScanMatcher, icp, scan_to_points, estimate_normals
from dfusion.localization.landmark_ekf import LandmarkEKF
from dfusion.localization.mcl import MonteCarloLocalization, kld_sample_size
from dfusion.localization.odometry_ekf import OdometryEKF
from dfusion.localization.radio_calibration import (
    PathLossCalibration,
    calibrate_path_loss,
    calibrate_radio_map,
    held_out_residuals,
    held_out_score,
    select_radio_map_settings,
    MAP_SETTINGS_GRID,
    NOISE_MODELS,
    weighted_centroid,
    run_tracker,
)
from dfusion.localization.radio_map import (
    RadioMap,
    fit_radio_map,
    fit_radio_maps,
    kernel_residual_map,
    binned_residual_stats,
    split_normal_logpdf,
    fit_split_normal,
    path_loss_design,
    fit_directional_path_loss,
)
from dfusion.localization.similarity import (
    SimilarityResult,
    SimilarityRate,
    correntropy_similarity,
    trimmed_overlap_ratio,
    similarity_rate,
    overlap_ratio,
)
from dfusion.localization.wsn_tracker import WSNTracker, MOTIONS

__all__ = [
    "EnvironmentCameraLocalizer",
    "ICPResult",
    "ScanMatcher",
    "icp",
    "scan_to_points",
    "estimate_normals",
    "LandmarkEKF",
    "MonteCarloLocalization",
    "kld_sample_size",
    "OdometryEKF",
    "PathLossCalibration",
    "calibrate_path_loss",
    "calibrate_radio_map",
    "held_out_residuals",
    "held_out_score",
    "select_radio_map_settings",
    "MAP_SETTINGS_GRID",
    "NOISE_MODELS",
    "weighted_centroid",
    "run_tracker",
    "RadioMap",
    "fit_radio_map",
    "fit_radio_maps",
    "kernel_residual_map",
    "binned_residual_stats",
    "split_normal_logpdf",
    "fit_split_normal",
    "path_loss_design",
    "fit_directional_path_loss",
    "SimilarityResult",
    "SimilarityRate",
    "correntropy_similarity",
    "trimmed_overlap_ratio",
    "similarity_rate",
    "overlap_ratio",
    "WSNTracker",
    "MOTIONS",
]
