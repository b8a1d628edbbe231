r"""Zenoh key expressions of ROS 2 topics and entities, in the two conventions ROS 2 speaks over Zenoh.

``rmw_zenoh`` (ROS 2's Zenoh middleware, ``rmw_zenoh_cpp``, Jazzy and later; the design document in its repository)
    data key ``<domain_id>/<fully qualified topic name without its leading />/<DDS type name>/<type hash>``,
    e.g. ``0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``; the DDS type name of
    ``pkg/msg/Type`` is ``pkg::msg::dds_::Type_``; the type hash is the RIHS01 hash of REP-2016
    (:func:`dfusion.ros2.codec.type_hash`). Every entity announces itself with a liveliness token
    ``@ros2_lv/<domain_id>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>``
    followed, for a publisher (``MP``) or a subscription (``MS``), by
    ``/<mangled topic>/<DDS type name>/<type hash>/<qos>``; a node's own token (``NN``) has its node id as
    entity id. Mangled names have every ``/`` replaced by ``%``; an empty enclave or namespace is ``%``.
    The QoS chunk is rmw_zenoh's compact form; :data:`RMW_DEFAULT_QOS` is reliable, volatile,
    keep-last 10 (``::,10:,:,:,,``, the form of the design document's examples).
``ros2dds`` (``zenoh-bridge-ros2dds`` / ``zenoh-plugin-ros2dds``, for DDS-based ROS 2)
    data key: the topic name without its leading ``/``, after the bridge's namespace when it has one
    (``robot1/chatter``); no domain, type or hash in the key. Liveliness tokens
    ``@/<zenoh id>/@ros2_lv/MP/<key>/<type>/<qos>`` (``MS`` for a subscription) with every ``/`` of the key
    and of the ROS type name (``std_msgs/msg/String``) replaced by ``§``; :data:`BRIDGE_DEFAULT_QOS`
    leaves every field of the bridge's ``keyless:reliability:durability:history_kind,depth`` form empty
    (the DDS defaults).

The payload is CDR in both (little-endian, with its 4-byte encapsulation header). rmw_zenoh also
attaches to every sample a sequence number, a source time and the publisher's 16-byte GID
(:func:`rmw_attachment`). The two conventions do not interoperate (a ROS 2 system uses one):
the node file chooses (``docs/ros.md``, "Live use").
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from dfusion.errors import ValidationError

__all__ = ["CONVENTIONS", "RMW_ZENOH", "ROS2DDS", "Convention", "dds_type_name", "mangle", "rmw_attachment",
           "RMW_DEFAULT_QOS", "BRIDGE_DEFAULT_QOS"]

RMW_ZENOH = "rmw_zenoh"
ROS2DDS = "ros2dds"
#: The conventions a node file may choose.
CONVENTIONS = (RMW_ZENOH, ROS2DDS)
RMW_DEFAULT_QOS = "::,10:,:,:,,"
BRIDGE_DEFAULT_QOS = ":::,"
_BRIDGE_SLASH = "\u00a7"


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_`` (the name DDS and rmw_zenoh give a ROS 2 type)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValidationError(f"a ROS 2 message type is pkg/msg/Type, got {msgtype!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A ROS name in a liveliness token: every ``/`` replaced by ``%`` (``%`` alone when empty)."""
    return name.replace("/", "%") if name else "%"


def check_topic(topic: str) -> str:
    """A fully qualified topic name (``/a/b``): starts with ``/``, no empty, ``*`` or ``$`` chunk."""
    if not isinstance(topic, str) or not topic.startswith("/") or topic == "/" or topic.endswith("/"):
        raise ValidationError(f"a ROS 2 topic is a fully qualified name like /robot1/odom, got {topic!r}")
    chunks = topic[1:].split("/")
    bad = [c for c in chunks if not c or any(ch in c for ch in "*$?#%~ ")]
    if bad:
        raise ValidationError(f"topic {topic!r}: chunk {bad[0]!r} is not a ROS 2 name")
    return topic


def rmw_attachment(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's sample attachment: sequence number and source time (int64, little-endian),
    then the GID's length (one byte, 16) and the 16-byte GID."""
    if len(gid) != 16:
        raise ValidationError(f"a publisher GID has 16 bytes, got {len(gid)}")
    return struct.pack("<qqB", int(sequence), int(source_ns), 16) + bytes(gid)


@dataclass(frozen=True)
class Convention:
    """How ROS 2 topics map to Zenoh keys (see the module docstring).

    Attributes
    ----------
    kind : ``"rmw_zenoh"`` or ``"ros2dds"``
    domain_id : int
        ``ROS_DOMAIN_ID`` (rmw_zenoh; 0-232).
    namespace : str
        The bridge's namespace (ros2dds: ``ros2dds.namespace`` of its configuration; ``""``: none).
    """

    kind: str = RMW_ZENOH
    domain_id: int = 0
    namespace: str = ""

    def __post_init__(self) -> None:
        if self.kind not in CONVENTIONS:
            raise ValidationError(f"convention must be one of {CONVENTIONS}, got {self.kind!r}")
        if isinstance(self.domain_id, bool) or not isinstance(self.domain_id, int) or not 0 <= self.domain_id <= 232:
            raise ValidationError(f"domain_id must be an integer in [0, 232], got {self.domain_id!r}")
        if self.namespace not in ("", "/"):
            check_topic(self.namespace)

    def data_key(self, topic: str, msgtype: str) -> str:
        """The key a topic's messages travel on."""
        from dfusion.ros2.codec import type_hash   # noqa: PLC0415  (rosbags' type store on first use)

        name = check_topic(topic)[1:]
        if self.kind == RMW_ZENOH:
            return f"{self.domain_id}/{name}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"
        ns = self.namespace.strip("/")
        return f"{ns}/{name}" if ns else name

    def node_token(self, session_id: str, node: str, *, node_id: int = 0, namespace: str = "") -> str | None:
        """The liveliness token of a ROS 2 node (rmw_zenoh; the bridge announces no nodes: ``None``)."""
        if self.kind != RMW_ZENOH:
            return None
        return f"@ros2_lv/{self.domain_id}/{session_id}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{node}"

    def entity_token(self, kind: str, session_id: str, node: str, topic: str, msgtype: str, *,
                     node_id: int = 0, entity_id: int = 1, namespace: str = "") -> str:
        """The liveliness token of a publisher (``kind="MP"``) or subscription (``"MS"``) of ``topic``."""
        if kind not in ("MP", "MS"):
            raise ValidationError(f"entity kind must be MP or MS, got {kind!r}")
        if self.kind == RMW_ZENOH:
            from dfusion.ros2.codec import type_hash   # noqa: PLC0415

            return (f"@ros2_lv/{self.domain_id}/{session_id}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/"
                    f"{node}/{mangle(check_topic(topic))}/{dds_type_name(msgtype)}/{type_hash(msgtype)}/"
                    f"{RMW_DEFAULT_QOS}")
        key = self.data_key(topic, msgtype).replace("/", _BRIDGE_SLASH)
        return f"@/{session_id}/@ros2_lv/{kind}/{key}/{msgtype.replace('/', _BRIDGE_SLASH)}/{BRIDGE_DEFAULT_QOS}"
