"""Localizers and trackers, each an :class:`~dfusion.estimation.Estimator`: MCL, ICP, correlative scan matching, odometry EKF, landmark EKF, environmental camera, WSN tracker; radio maps and their calibration; scan similarity."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.localization.magnetic_pf import MagneticLocalizer, MagneticPFSettings, build_bias_free_map
    from dfusion.localization.fingerprint import FingerprintLocalizer, FingerprintFix
    from dfusion.localization.correlative import CorrelativeResult, CorrelativeScanMatcher, enclosing_covariance
    from dfusion.localization.env_camera import EnvironmentCameraLocalizer
    from dfusion.localization.scan_matching import (
        ICPResult,
        ScanMatcher,
        estimate_normals,
        icp,
        scan_to_points,
    )
    from dfusion.localization.landmark_ekf import LandmarkEKF
    from dfusion.localization.mcl import MonteCarloLocalization, kld_sample_size
    from dfusion.localization.odometry_ekf import OdometryEKF, ScanMatchingEKF, ScanMatchOutcome
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
    "MagneticLocalizer",
    "MagneticPFSettings",
    "build_bias_free_map",
    "FingerprintLocalizer",
    "FingerprintFix",
    "CorrelativeResult",
    "CorrelativeScanMatcher",
    "enclosing_covariance",
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
    "ScanMatchingEKF",
    "ScanMatchOutcome",
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

_WHERE = {
    "MagneticLocalizer": ("dfusion.localization.magnetic_pf", "MagneticLocalizer"),
    "MagneticPFSettings": ("dfusion.localization.magnetic_pf", "MagneticPFSettings"),
    "build_bias_free_map": ("dfusion.localization.magnetic_pf", "build_bias_free_map"),
    "FingerprintLocalizer": ("dfusion.localization.fingerprint", "FingerprintLocalizer"),
    "FingerprintFix": ("dfusion.localization.fingerprint", "FingerprintFix"),
    "CorrelativeResult": ("dfusion.localization.correlative", 'CorrelativeResult'),
    "CorrelativeScanMatcher": ("dfusion.localization.correlative", 'CorrelativeScanMatcher'),
    "enclosing_covariance": ("dfusion.localization.correlative", 'enclosing_covariance'),
    "EnvironmentCameraLocalizer": ("dfusion.localization.env_camera", 'EnvironmentCameraLocalizer'),
    "ICPResult": ("dfusion.localization.scan_matching", 'ICPResult'),
    "ScanMatcher": ("dfusion.localization.scan_matching", 'ScanMatcher'),
    "estimate_normals": ("dfusion.localization.scan_matching", 'estimate_normals'),
    "icp": ("dfusion.localization.scan_matching", 'icp'),
    "scan_to_points": ("dfusion.localization.scan_matching", 'scan_to_points'),
    "LandmarkEKF": ("dfusion.localization.landmark_ekf", 'LandmarkEKF'),
    "MonteCarloLocalization": ("dfusion.localization.mcl", 'MonteCarloLocalization'),
    "kld_sample_size": ("dfusion.localization.mcl", 'kld_sample_size'),
    "OdometryEKF": ("dfusion.localization.odometry_ekf", 'OdometryEKF'),
    "ScanMatchingEKF": ("dfusion.localization.odometry_ekf", 'ScanMatchingEKF'),
    "ScanMatchOutcome": ("dfusion.localization.odometry_ekf", 'ScanMatchOutcome'),
    "MAP_SETTINGS_GRID": ("dfusion.localization.radio_calibration", 'MAP_SETTINGS_GRID'),
    "NOISE_MODELS": ("dfusion.localization.radio_calibration", 'NOISE_MODELS'),
    "PathLossCalibration": ("dfusion.localization.radio_calibration", 'PathLossCalibration'),
    "calibrate_path_loss": ("dfusion.localization.radio_calibration", 'calibrate_path_loss'),
    "calibrate_radio_map": ("dfusion.localization.radio_calibration", 'calibrate_radio_map'),
    "held_out_residuals": ("dfusion.localization.radio_calibration", 'held_out_residuals'),
    "held_out_score": ("dfusion.localization.radio_calibration", 'held_out_score'),
    "run_tracker": ("dfusion.localization.radio_calibration", 'run_tracker'),
    "select_radio_map_settings": ("dfusion.localization.radio_calibration", 'select_radio_map_settings'),
    "weighted_centroid": ("dfusion.localization.radio_calibration", 'weighted_centroid'),
    "RadioMap": ("dfusion.localization.radio_map", 'RadioMap'),
    "binned_residual_stats": ("dfusion.localization.radio_map", 'binned_residual_stats'),
    "fit_directional_path_loss": ("dfusion.localization.radio_map", 'fit_directional_path_loss'),
    "fit_radio_map": ("dfusion.localization.radio_map", 'fit_radio_map'),
    "fit_radio_maps": ("dfusion.localization.radio_map", 'fit_radio_maps'),
    "fit_split_normal": ("dfusion.localization.radio_map", 'fit_split_normal'),
    "kernel_residual_map": ("dfusion.localization.radio_map", 'kernel_residual_map'),
    "path_loss_design": ("dfusion.localization.radio_map", 'path_loss_design'),
    "split_normal_logpdf": ("dfusion.localization.radio_map", 'split_normal_logpdf'),
    "SimilarityRate": ("dfusion.localization.similarity", 'SimilarityRate'),
    "SimilarityResult": ("dfusion.localization.similarity", 'SimilarityResult'),
    "correntropy_similarity": ("dfusion.localization.similarity", 'correntropy_similarity'),
    "overlap_ratio": ("dfusion.localization.similarity", 'overlap_ratio'),
    "similarity_rate": ("dfusion.localization.similarity", 'similarity_rate'),
    "trimmed_overlap_ratio": ("dfusion.localization.similarity", 'trimmed_overlap_ratio'),
    "MOTIONS": ("dfusion.localization.wsn_tracker", 'MOTIONS'),
    "WSNTracker": ("dfusion.localization.wsn_tracker", 'WSNTracker'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
