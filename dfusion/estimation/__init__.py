"""Estimators: the estimate type, information-form Gaussians, EIF, delayed-state EIF, centralized EKF, the particle-filter engine."""
from dfusion.estimation.centralized import CentralizedEKF, History
from dfusion.estimation.delayed_state import measurement_information, DelayedStateEIF
from dfusion.estimation.eif import ExtendedInformationFilter
from dfusion.estimation.estimate import Estimate, Estimator
from dfusion.estimation.gaussian import InformationGaussian, project_psd_information
from dfusion.estimation.particle_filter import (
    ParticleFilter,
    ParticleDepletionError,
    effective_sample_size,
    normalize_log_weights,
    systematic_counts,
    systematic_resample,
    stratified_resample,
    multinomial_resample,
    roughening_std,
    weighted_mean_cov,
    RESAMPLERS,
    gaussian_summary,
)
from dfusion.estimation.trajectory import MotionFactor, TrajectoryInformation

__all__ = [
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
]
