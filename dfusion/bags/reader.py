r"""Read ROS bags (ROS 1 ``.bag``, ROS 2 sqlite3 and MCAP) into time-ordered messages.

Reading is done by `rosbags <https://gitlab.com/ternaris/rosbags>`_ (pure Python; its
``AnyReader`` opens all three formats and takes each message type's definition from
the bag itself, so custom message types need no installed ROS). This module only
decides **which time a message has** and **in what order messages come**:

* A message's time is its ``header.stamp`` (the time the sensor took it), not the time
  the recorder wrote it (``record time``, the bag's log time). A message without a
  header (``geometry_msgs/Twist``, ...) has its record time, and
  :attr:`BagMessage.stamped` is false.
* :func:`read_bag` returns the messages sorted by header stamp; ties keep the bag's
  record order. So the order in which messages were recorded does not matter: a bag
  recorded with the same stamps in another order gives the same sequence (as long as
  no topic holds two messages with one stamp, which is what a sensor driver writes).
* Each message keeps its record time too: a replay that wants to see the data as the
  robot received it (a message recorded after newer ones is a *late measurement*)
  uses :attr:`BagMessage.record_ns` as its arrival (``dfusion.sim.replay``).

Times are integer nanoseconds; :meth:`Bag.seconds` turns one into seconds relative to
an origin (by default the earliest stamp in the bag), so that epoch stamps (1.7e9 s)
do not lose their nanoseconds in a float.

**Only the topics asked for are deserialized**, so a message type that cannot be
decoded on another topic does not stop a reader. **Message definitions.** MCAP bags,
ROS 1 bags and sqlite3 bags from Iron on store them. A sqlite3 bag from Humble does not:
its standard types are taken from rosbags' Humble type store, and a custom type's
definition is given with ``msgdefs`` (``{type: definition text or .msg file}``, or
:func:`msgdefs_from_files` for ``.../<pkg>/msg/<Type>.msg`` files; ``--msg FILE.msg`` on
the command line), registered with rosbags' ``get_types_from_msg``; ``vision_msgs`` (the
detection arrays) needs none: dfusion ships its definitions (:mod:`dfusion.bags.msgdefs`). A
needed type without a definition is refused in one line that says how to give it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

from dfusion.bags.msgdefs import BUNDLED_MSGDEFS
from dfusion.errors import ValidationError

log = logging.getLogger(__name__)

__all__ = ["BagMessage", "Bag", "read_bag", "stamp_ns", "msgdefs_from_files"]


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag.

    Attributes
    ----------
    topic, msgtype : str
        The topic and the message type (``"sensor_msgs/msg/LaserScan"``; ROS 1 names are
        given the same ``pkg/msg/Type`` form by rosbags).
    stamp_ns : int
        ``header.stamp`` in nanoseconds (the record time when the message has no header).
    record_ns : int
        The time the recorder wrote the message (the bag's log time), nanoseconds.
    index : int
        Position of the message in the bag's record order.
    stamped : bool
        Whether ``stamp_ns`` comes from a header.
    msg : object
        The deserialized message (rosbags' dataclass; arrays are numpy arrays).
    """

    topic: str
    msgtype: str
    stamp_ns: int
    record_ns: int
    index: int
    stamped: bool
    msg: Any = field(compare=False, repr=False)


def stamp_ns(msg: Any) -> int | None:
    """``msg.header.stamp`` in nanoseconds, or ``None`` when the message has no header.

    ROS 2 ``builtin_interfaces/Time`` has ``sec`` and ``nanosec``; rosbags gives ROS 1
    ``time`` the same fields.
    """
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class Bag:
    """The messages of a bag, sorted by header stamp (ties in record order).

    Attributes
    ----------
    path : Path
    messages : list of BagMessage
    topics : dict
        Topic -> message type, of every topic in the bag (read or not).
    origin_ns : int
        The earliest stamp among the messages read: time 0 of :meth:`seconds`.
    """

    path: Path
    messages: list[BagMessage]
    topics: dict[str, str]
    origin_ns: int = 0

    def on(self, topic: str) -> list[BagMessage]:
        """The messages of one topic, in stamp order."""
        if topic not in self.topics:
            raise ValidationError(f"{self.path}: no topic {topic!r} (topics: {sorted(self.topics)})")
        return [m for m in self.messages if m.topic == topic]

    def seconds(self, ns: int, origin_ns: int | None = None) -> float:
        """``ns`` in seconds after ``origin_ns`` (default :attr:`origin_ns`), exact to 1 ns
        before the conversion to float."""
        return (int(ns) - (self.origin_ns if origin_ns is None else int(origin_ns))) * 1e-9


def _bag_paths(path: Path) -> Path:
    """The path rosbags opens: a ROS 1 file, or a ROS 2 directory (also given by one of its
    files, e.g. the ``.mcap`` or ``.db3`` next to ``metadata.yaml``)."""
    if path.is_dir():
        return path
    if not path.exists():
        raise ValidationError(f"{path}: no such bag")
    if path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def msgdefs_from_files(paths: Iterable[str | Path]) -> dict[str, str]:
    """Message definitions from ``.msg`` files: ``.../<pkg>/msg/<Type>.msg`` (the layout of
    a ROS package) is the type ``<pkg>/msg/<Type>``. ``PKG/msg/TYPE=FILE`` names the type
    of a file kept elsewhere."""
    out: dict[str, str] = {}
    for item in paths:
        name, sep, file = str(item).rpartition("=")
        p = Path(file)
        if not p.is_file():
            raise ValidationError(f"message definition {file}: no such file")
        if not sep:
            if p.suffix != ".msg" or p.parent.name != "msg" or not p.parent.parent.name:
                raise ValidationError(f"message definition {file}: the type is read from .../<pkg>/msg/<Type>.msg; "
                                      f"otherwise give it as PKG/msg/TYPE={file}")
            name = f"{p.parent.parent.name}/msg/{p.stem}"
        out[name] = p.read_text()
    return out


def _register(reader: Any, msgdefs: Mapping[str, str | Path]) -> None:
    """Add the user's message definitions to the reader's type store (the bag's own win)."""
    from rosbags.typesys import get_types_from_msg

    have = set(reader.typestore.fielddefs)
    types: dict[str, Any] = {}
    for name, text in msgdefs.items():
        if isinstance(text, Path) or (isinstance(text, str) and text.endswith(".msg") and "\n" not in text):
            text = Path(text).read_text()
        try:
            types.update(get_types_from_msg(str(text), name))
        except Exception as exc:   # rosbags' parser raises its own error types
            raise ValidationError(f"message definition of {name}: {type(exc).__name__}: {exc}") from None
    reader.typestore.register({k: v for k, v in types.items() if k not in have})


def read_bag(path: str | Path, topics: Iterable[str] | None = None, *, optional: Iterable[str] = (),
             msgdefs: Mapping[str, str | Path] | None = None) -> Bag:
    """Read ``topics`` (default: every topic) of a ROS 1 or ROS 2 bag.

    Returns a :class:`Bag` whose messages are sorted by header stamp (see the module
    docstring). Message types are read from the bag's own definitions; for a bag that
    does not carry them (a Humble sqlite3 bag), from the standard ROS 2 Humble types and
    ``msgdefs`` (type -> definition text or ``.msg`` file). Only ``topics`` are
    deserialized, and ``optional`` topics when the bag has them.

    Raises
    ------
    ValidationError
        When the path is not a bag rosbags can open, a requested topic is missing, or a
        requested topic's type has no definition.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    p = _bag_paths(Path(path))
    wanted = None if topics is None else set(topics)
    optional = set(optional)
    out: list[tuple[int, int, BagMessage]] = []
    try:
        with AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            all_topics = {c.topic: c.msgtype for c in reader.connections}
            if wanted is not None:
                missing = sorted(wanted - set(all_topics))
                if missing:
                    raise ValidationError(f"{path}: no topic {missing[0]!r} (topics: {sorted(all_topics)})")
            if msgdefs:
                _register(reader, msgdefs)
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted | optional]
            if any(c.msgtype not in reader.typestore.fielddefs and c.msgtype in BUNDLED_MSGDEFS for c in conns):
                _register(reader, BUNDLED_MSGDEFS)
            for c in conns:
                if c.msgtype not in reader.typestore.fielddefs:
                    raise ValidationError(f"{path}: topic {c.topic}: the bag stores no definition of {c.msgtype}; "
                                          f"give its .msg file (--msg .../{c.msgtype}.msg, or msgdefs=)")
            for i, (conn, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
                msg = reader.deserialize(raw, conn.msgtype)
                st = stamp_ns(msg)
                bm = BagMessage(conn.topic, conn.msgtype, rec_ns if st is None else st, int(rec_ns), i,
                                st is not None, msg)
                out.append((bm.stamp_ns, i, bm))
    except ValidationError:
        raise
    except Exception as exc:   # rosbags raises its own types for unreadable bags
        raise ValidationError(f"{path}: cannot read the bag ({type(exc).__name__}: {exc})") from None
    out.sort(key=lambda e: (e[0], e[1]))
    messages = [e[2] for e in out]
    origin = messages[0].stamp_ns if messages else 0
    log.info("%s: %d messages on %d topics", path, len(messages), len({m.topic for m in messages}))
    return Bag(Path(path), messages, all_topics, origin)
