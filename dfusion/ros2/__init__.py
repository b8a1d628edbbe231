"""ROS 2 in and out over Zenoh, without a ROS installation (``docs/ros.md``, "Live use").

* :mod:`dfusion.ros2.keys` -- the Zenoh keys and liveliness tokens of ROS 2 topics in the two
  conventions: ``rmw_zenoh`` (ROS 2's Zenoh middleware) and ``ros2dds`` (``zenoh-bridge-ros2dds``);
* :mod:`dfusion.ros2.codec` -- CDR (de)serialization and RIHS01 type hashes with rosbags, and the
  messages a live node publishes (``Odometry``, ``PoseWithCovarianceStamped``, ``DiagnosticArray``);
* static transforms (``/tf_static``) come from :mod:`dfusion.bags.tf`, shared with bags;
* :mod:`dfusion.ros2.inputs` -- input messages to measurements with their own covariances;
* :mod:`dfusion.ros2.link` -- :class:`Ros2Link`: subscriptions, publishers and tokens on a session.
"""
from dfusion.lazy import lazy_exports

_WHERE = {
    "Convention": ("dfusion.ros2.keys", "Convention"),
    "CONVENTIONS": ("dfusion.ros2.keys", "CONVENTIONS"),
    "dds_type_name": ("dfusion.ros2.keys", "dds_type_name"),
    "type_hash": ("dfusion.ros2.codec", "type_hash"),
    "encode": ("dfusion.ros2.codec", "encode"),
    "decode": ("dfusion.ros2.codec", "decode"),
    "estimate_messages": ("dfusion.ros2.codec", "estimate_messages"),
    "diagnostics": ("dfusion.ros2.codec", "diagnostics"),
    "StaticTransforms": ("dfusion.bags.tf", "StaticTransforms"),
    "Reading": ("dfusion.ros2.inputs", "Reading"),
    "reading_of": ("dfusion.ros2.inputs", "reading_of"),
    "SUPPORTED_INPUTS": ("dfusion.ros2.inputs", "SUPPORTED_INPUTS"),
    "Ros2Link": ("dfusion.ros2.link", "Ros2Link"),
}
__all__ = sorted(_WHERE)
__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
