"""Localizers and trackers, each an :class:`~dfusion.estimation.Estimator`: MCL, ICP, odometry EKF, landmark EKF, environmental camera, WSN tracker; radio maps and their calibration; scan similarity."""
from dfusion.localization.env_camera import EnvironmentCameraLocalizer
from dfusion.localization.icp import (
    ICPResult,
    ScanMatcher,
    estimate_normals,
    icp,
    scan_to_points,
)
from dfusion.localization.landmark_ekf import LandmarkEKF
from dfusion.localization.mcl import MonteCarloLocalization, kld_sample_size
from dfusion.localization.odometry_ekf import OdometryEKF
from dfusion.localization.radio_calibration import (
    MAP_SETTINGS_GRID,
    NOISE_MODELS,
    PathLossCalibration,
    calibrate_path_loss,
    calibrate_radio_map,
    held_out_residuals,
    held_out_score,
    run_tracker,
    select_radio_map_settings,
    weighted_centroid,
)
from dfusion.localization.radio_map import (
    RadioMap,
    binned_residual_stats,
    fit_directional_path_loss,
    fit_radio_map,
    fit_radio_maps,
    fit_split_normal,
    kernel_residual_map,
    path_loss_design,
    split_normal_logpdf,
)
from dfusion.localization.similarity import (
    SimilarityRate,
    SimilarityResult,
    correntropy_similarity,
    overlap_ratio,
    similarity_rate,
    trimmed_overlap_ratio,
)
from dfusion.localization.wsn_tracker import MOTIONS, WSNTracker

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
