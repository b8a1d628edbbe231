"""Front ends: one base class and one module per sensor kind (camera, WSN, MCL, ICP, environmental camera)."""
from dfusion.frontends.base import (
    EIFFrontEnd,
    FrontEnd,
    FrontEndStats,
    embed_source,
    fit_difference_information,
    position_information,
)
from dfusion.frontends.camera import CameraFrontEnd, CameraStats, gate_threshold
from dfusion.frontends.env_camera import EnvCameraFrontEnd
from dfusion.frontends.icp import ICPFrontEnd
from dfusion.frontends.mcl import MCLFrontEnd
from dfusion.frontends.wsn import WSNFrontEnd, WSNStats

__all__ = [
    "FrontEnd",
    "FrontEndStats",
    "EIFFrontEnd",
    "position_information",
    "fit_difference_information",
    "embed_source",
    "CameraFrontEnd",
    "CameraStats",
    "gate_threshold",
    "EnvCameraFrontEnd",
    "ICPFrontEnd",
    "MCLFrontEnd",
    "WSNFrontEnd",
    "WSNStats",
]
