"""Estimators: the estimate type, information-form Gaussians, EIF, delayed-state EIF, centralized EKF, the particle-filter engine, probabilistic data association, innovation monitoring (robust weights, lock-out detection)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.estimation.centralized import CentralizedEKF, History
    from dfusion.estimation.delayed_state import measurement_information, DelayedStateEIF
    from dfusion.estimation.eif import ExtendedInformationFilter
    from dfusion.estimation.estimate import Estimate, Estimator
    from dfusion.estimation.gaussian import InformationGaussian, project_psd_information
    from dfusion.estimation.pda import ClutterModel, FrameInnovations, PDAInformation, PDAResult, frame_innovations, gate_threshold, pda_information, pda_moments, pda_update, pda_weights
    from dfusion.estimation.particle_filter import ParticleFilter, ParticleDepletionError, effective_sample_size, normalize_log_weights, systematic_counts, systematic_resample, stratified_resample, multinomial_resample, roughening_std, weighted_mean_cov, RESAMPLERS, gaussian_summary
    from dfusion.estimation.trajectory import MotionFactor, TrajectoryInformation
    from dfusion.estimation.innovation import (Assessment, DivergenceAlarm, InnovationMonitor, JumpEstimate, LockoutDetector,
                                               MonitorSettings, MonitorStats, estimate_jump, monitored_update)

__all__ = [
    "DivergenceAlarm",
    "LockoutDetector",
    "monitored_update",
    "estimate_jump",
    "InnovationMonitor",
    "JumpEstimate",
    "Assessment",
    "MonitorStats",
    "MonitorSettings",
    "CentralizedEKF",
    "History",
    "measurement_information",
    "DelayedStateEIF",
    "ExtendedInformationFilter",
    "Estimate",
    "Estimator",
    "InformationGaussian",
    "project_psd_information",
    "ParticleFilter",
    "ParticleDepletionError",
    "effective_sample_size",
    "normalize_log_weights",
    "systematic_counts",
    "systematic_resample",
    "stratified_resample",
    "multinomial_resample",
    "roughening_std",
    "weighted_mean_cov",
    "RESAMPLERS",
    "gaussian_summary",
    "MotionFactor",
    "TrajectoryInformation",
    "ClutterModel",
    "PDAResult",
    "PDAInformation",
    "FrameInnovations",
    "frame_innovations",
    "pda_weights",
    "pda_update",
    "pda_moments",
    "pda_information",
    "gate_threshold",
    "DivergenceAlarm",
    "LockoutDetector",
    "monitored_update",
    "estimate_jump",
    "InnovationMonitor",
    "JumpEstimate",
    "Assessment",
    "MonitorStats",
    "MonitorSettings",
]

_WHERE = {
    "CentralizedEKF": ("dfusion.estimation.centralized", 'CentralizedEKF'),
    "History": ("dfusion.estimation.centralized", 'History'),
    "measurement_information": ("dfusion.estimation.delayed_state", 'measurement_information'),
    "DelayedStateEIF": ("dfusion.estimation.delayed_state", 'DelayedStateEIF'),
    "ExtendedInformationFilter": ("dfusion.estimation.eif", 'ExtendedInformationFilter'),
    "Estimate": ("dfusion.estimation.estimate", 'Estimate'),
    "Estimator": ("dfusion.estimation.estimate", 'Estimator'),
    "InformationGaussian": ("dfusion.estimation.gaussian", 'InformationGaussian'),
    "project_psd_information": ("dfusion.estimation.gaussian", 'project_psd_information'),
    "ParticleFilter": ("dfusion.estimation.particle_filter", 'ParticleFilter'),
    "ParticleDepletionError": ("dfusion.estimation.particle_filter", 'ParticleDepletionError'),
    "effective_sample_size": ("dfusion.estimation.particle_filter", 'effective_sample_size'),
    "normalize_log_weights": ("dfusion.estimation.particle_filter", 'normalize_log_weights'),
    "systematic_counts": ("dfusion.estimation.particle_filter", 'systematic_counts'),
    "systematic_resample": ("dfusion.estimation.particle_filter", 'systematic_resample'),
    "stratified_resample": ("dfusion.estimation.particle_filter", 'stratified_resample'),
    "multinomial_resample": ("dfusion.estimation.particle_filter", 'multinomial_resample'),
    "roughening_std": ("dfusion.estimation.particle_filter", 'roughening_std'),
    "weighted_mean_cov": ("dfusion.estimation.particle_filter", 'weighted_mean_cov'),
    "RESAMPLERS": ("dfusion.estimation.particle_filter", 'RESAMPLERS'),
    "gaussian_summary": ("dfusion.estimation.particle_filter", 'gaussian_summary'),
    "MotionFactor": ("dfusion.estimation.trajectory", 'MotionFactor'),
    "TrajectoryInformation": ("dfusion.estimation.trajectory", 'TrajectoryInformation'),
    "ClutterModel": ("dfusion.estimation.pda", 'ClutterModel'),
    "PDAResult": ("dfusion.estimation.pda", 'PDAResult'),
    "PDAInformation": ("dfusion.estimation.pda", 'PDAInformation'),
    "FrameInnovations": ("dfusion.estimation.pda", 'FrameInnovations'),
    "frame_innovations": ("dfusion.estimation.pda", 'frame_innovations'),
    "pda_weights": ("dfusion.estimation.pda", 'pda_weights'),
    "pda_update": ("dfusion.estimation.pda", 'pda_update'),
    "pda_moments": ("dfusion.estimation.pda", 'pda_moments'),
    "pda_information": ("dfusion.estimation.pda", 'pda_information'),
    "gate_threshold": ("dfusion.estimation.pda", 'gate_threshold'),
    "DivergenceAlarm": ("dfusion.estimation.innovation", 'DivergenceAlarm'),
    "LockoutDetector": ("dfusion.estimation.innovation", 'LockoutDetector'),
    "monitored_update": ("dfusion.estimation.innovation", 'monitored_update'),
    "estimate_jump": ("dfusion.estimation.innovation", 'estimate_jump'),
    "InnovationMonitor": ("dfusion.estimation.innovation", 'InnovationMonitor'),
    "JumpEstimate": ("dfusion.estimation.innovation", 'JumpEstimate'),
    "Assessment": ("dfusion.estimation.innovation", 'Assessment'),
    "MonitorStats": ("dfusion.estimation.innovation", 'MonitorStats'),
    "MonitorSettings": ("dfusion.estimation.innovation", 'MonitorSettings'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
