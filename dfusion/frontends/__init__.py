"""Front ends: one base class and one module per sensor kind (camera, WSN, MCL, ICP, environmental camera, target tracking)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.frontends.indoor import FingerprintFrontEnd, MagneticFrontEnd, MagneticStats
    from dfusion.frontends.base import embed_position_information
    from dfusion.frontends.base import EIFFrontEnd, FrontEnd, FrontEndStats, embed_source, fit_difference_information, position_information
    from dfusion.frontends.camera import CameraFrame, CameraFrontEnd, CameraStats, gate_threshold
    from dfusion.frontends.env_camera import EnvCameraFrontEnd
    from dfusion.frontends.icp import ICPFrontEnd
    from dfusion.frontends.mcl import MCLFrontEnd
    from dfusion.frontends.target import TargetTrackingFrontEnd, network_support
    from dfusion.frontends.team import TeamSightingsFrontEnd, TeamStats
    from dfusion.frontends.wsn import WSNFrontEnd, WSNStats

__all__ = [
    "FingerprintFrontEnd",
    "MagneticFrontEnd",
    "MagneticStats",
    "embed_position_information",
    "FrontEnd",
    "FrontEndStats",
    "EIFFrontEnd",
    "position_information",
    "fit_difference_information",
    "embed_source",
    "CameraFrontEnd",
    "CameraStats",
    "CameraFrame",
    "gate_threshold",
    "EnvCameraFrontEnd",
    "ICPFrontEnd",
    "MCLFrontEnd",
    "TargetTrackingFrontEnd",
    "network_support",
    "TeamSightingsFrontEnd",
    "TeamStats",
    "WSNFrontEnd",
    "WSNStats",
]

_WHERE = {
    "FingerprintFrontEnd": ("dfusion.frontends.indoor", "FingerprintFrontEnd"),
    "MagneticFrontEnd": ("dfusion.frontends.indoor", "MagneticFrontEnd"),
    "MagneticStats": ("dfusion.frontends.indoor", "MagneticStats"),
    "embed_position_information": ("dfusion.frontends.base", "embed_position_information"),
    "EIFFrontEnd": ("dfusion.frontends.base", 'EIFFrontEnd'),
    "FrontEnd": ("dfusion.frontends.base", 'FrontEnd'),
    "FrontEndStats": ("dfusion.frontends.base", 'FrontEndStats'),
    "embed_source": ("dfusion.frontends.base", 'embed_source'),
    "fit_difference_information": ("dfusion.frontends.base", 'fit_difference_information'),
    "position_information": ("dfusion.frontends.base", 'position_information'),
    "CameraFrontEnd": ("dfusion.frontends.camera", 'CameraFrontEnd'),
    "CameraStats": ("dfusion.frontends.camera", 'CameraStats'),
    "CameraFrame": ("dfusion.frontends.camera", 'CameraFrame'),
    "gate_threshold": ("dfusion.frontends.camera", 'gate_threshold'),
    "EnvCameraFrontEnd": ("dfusion.frontends.env_camera", 'EnvCameraFrontEnd'),
    "ICPFrontEnd": ("dfusion.frontends.icp", 'ICPFrontEnd'),
    "MCLFrontEnd": ("dfusion.frontends.mcl", 'MCLFrontEnd'),
    "TargetTrackingFrontEnd": ("dfusion.frontends.target", 'TargetTrackingFrontEnd'),
    "network_support": ("dfusion.frontends.target", 'network_support'),
    "TeamSightingsFrontEnd": ("dfusion.frontends.team", 'TeamSightingsFrontEnd'),
    "TeamStats": ("dfusion.frontends.team", 'TeamStats'),
    "WSNFrontEnd": ("dfusion.frontends.wsn", 'WSNFrontEnd'),
    "WSNStats": ("dfusion.frontends.wsn", 'WSNStats'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
