"""ROS bags in: ROS 1 and ROS 2 (sqlite3, MCAP) recordings as dfusion measurements.

:func:`read_bag` reads a bag into messages ordered by header stamp
(:mod:`dfusion.bags.reader`); :mod:`dfusion.bags.convert` turns the standard message
types into plain measurements (user functions map any other type), detection arrays
(``PoseArray``, ``vision_msgs`` ``Detection2DArray`` / ``Detection3DArray``) included;
:mod:`dfusion.bags.detections` takes a detection array into the fixed frame (homography for
pixels, ``/tf_static``, covariances); :mod:`dfusion.bags.msgdefs` holds the ``vision_msgs``
definitions a bag may not carry;
:mod:`dfusion.bags.datasets` gives a bag the shape of a dataset reader's result, so the
MRCLAM and CARMEN pipelines run on recordings. Scenario nodes are fed from a bag by
:func:`dfusion.sim.replay.replay_scenario` (``dfusion replay``). See ``docs/ros.md``.
"""
from dfusion.bags.convert import (
    CONVERTERS,
    DETECTION_TYPES,
    Converter,
    Detections,
    PoseReading,
    PositionFix,
    RangeReading,
    ScanReading,
    Velocity,
    POSE_TYPES,
    POSITION_READINGS,
    convert,
    known_covariance,
    quaternion_of_yaw,
    read_pose,
    standard_z,
    yaw_of,
)
from dfusion.bags.datasets import (
    MRCLAM_TOPICS,
    POSE_TOLERANCE,
    SIGHTINGS_MSGDEF,
    SIGHTINGS_TYPE,
    carmen_from_bag,
    mrclam_from_bag,
    sightings,
)
from dfusion.bags.detections import DetectionTopic, WorldDetections, read_homography, world_detections
from dfusion.bags.msgdefs import BUNDLED_MSGDEFS, VISION_MSGS
from dfusion.bags.reader import Bag, BagMessage, msgdefs_from_files, read_bag, stamp_ns
from dfusion.bags.tf import TF_STATIC, StaticTransforms, rotate_covariance

__all__ = [
    "Bag", "BagMessage", "read_bag", "stamp_ns", "msgdefs_from_files", "TF_STATIC", "StaticTransforms", "rotate_covariance",
    "CONVERTERS", "Converter", "PoseReading", "PositionFix", "RangeReading", "ScanReading", "Velocity",
    "convert", "standard_z", "POSITION_READINGS", "quaternion_of_yaw", "yaw_of", "read_pose", "POSE_TYPES",
    "DETECTION_TYPES", "Detections", "known_covariance", "DetectionTopic", "WorldDetections", "read_homography",
    "world_detections", "BUNDLED_MSGDEFS", "VISION_MSGS",
    "MRCLAM_TOPICS", "POSE_TOLERANCE", "SIGHTINGS_MSGDEF", "SIGHTINGS_TYPE", "carmen_from_bag", "mrclam_from_bag", "sightings",
]
