r"""Message definitions dfusion ships for types that are not in rosbags' type stores.

``vision_msgs`` (ROS 2 Humble and later, package version 4.x: ``ros-perception/vision_msgs``,
Apache-2.0) is the standard home of a detector's output but is not in rosbags' ROS 2 type
stores. An MCAP bag, a ROS 1 bag or a sqlite3 bag from Iron on stores the definitions itself
(and the bag's own win); a Humble sqlite3 bag does not, so :func:`dfusion.bags.read_bag`
registers these when a topic it reads has one of their types and the bag gives no definition.
Each text lists the fields of the package's ``.msg`` file (comments left out), in the
``.msg`` syntax rosbags' ``get_types_from_msg`` reads.

Dependencies (``std_msgs/Header``, ``geometry_msgs/Pose``, ``PoseWithCovariance``,
``Vector3``) are standard types of the reader's type store.
"""
from __future__ import annotations

__all__ = ["VISION_MSGS", "BUNDLED_MSGDEFS"]

#: ``vision_msgs`` 4.x: the detection arrays and the types they hold.
VISION_MSGS: dict[str, str] = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": ("vision_msgs/ObjectHypothesis hypothesis\n"
                                                 "geometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/Detection2D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                    "vision_msgs/BoundingBox2D bbox\nstring id\n"),
    "vision_msgs/msg/Detection3D": ("std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                    "vision_msgs/BoundingBox3D bbox\nstring id\n"),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

#: Every definition :func:`dfusion.bags.read_bag` falls back on (a user's ``msgdefs`` win).
BUNDLED_MSGDEFS: dict[str, str] = dict(VISION_MSGS)
