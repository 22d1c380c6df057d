"""Reading ROS 1 / ROS 2 bags into rclpy messages and writing them, with rosbags (pure Python, no ROS install).

Reading (``read_bag``): ROS 1 ``.bag`` files and ROS 2 bag folders (sqlite3 or mcap) through ``AnyReader``; each raw
message becomes an rclpy message through CDR (``rclpy.serialization.deserialize_message``); ROS 1 payloads are first
converted byte-wise with the Jazzy type store's ``ros1_to_cdr`` (drops ``Header.seq``; TUM's legacy ``tf/tfMessage``
reads as ``tf2_msgs/TFMessage``, the same wire format). Messages come in bag time order as
``BagMessage(topic, stamp_ns, msg)``.

``tf2_msgs`` is not on PyPI: without it, TF messages are ``TFMessageStandIn`` (a ``transforms`` list of rclpy
``geometry_msgs/TransformStamped``), which the writers also accept. Topics of other types with no importable rclpy
class are skipped with one warning (or are an error when asked for by name).

Corrupt or truncated bags: rosbags needs a bag's index (ROS 1 index records, the mcap summary, an intact sqlite3
database) and cannot recover a partial file, so ``read_bag`` raises ``BagError`` naming the bag and the cause, whether
the damage is found on opening or while iterating. It never yields a silent partial read. (Re-index a truncated
ROS 1 bag with ``rosbag reindex`` or ``ros2 bag reindex`` for ROS 2 first.)

Writing: ``write_bag`` writes a ROS 2 bag (sqlite3 by default, or mcap; metadata version 8, readable by Jazzy);
``write_ros1_bag`` writes a ROS 1 bag (ROS 1 definitions from rosbags' Noetic store), e.g. with ``TUM_TOPICS``.
Stamps are integer nanoseconds (``msg_adapters.stamps.seconds_to_ns``).
"""
from __future__ import annotations

import importlib
import sqlite3
import struct
import warnings
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from geometry_msgs.msg import TransformStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

TF_TYPE = "tf2_msgs/msg/TFMessage"
LEGACY_TF_TYPE = "tf/msg/tfMessage"  # ROS 1 tf (TUM RGB-D bags), same wire format as tf2_msgs/TFMessage
TUM_TOPICS = {"rgb": "/camera/rgb/image_color", "depth": "/camera/depth/image",
              "camera_info": "/camera/rgb/camera_info", "tf": "/tf"}
ROS2_STORAGE = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
_ROS2_BAG_VERSION = 8
_TRANSFORM_TYPE = "geometry_msgs/msg/TransformStamped"
_READ_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, sqlite3.DatabaseError, struct.error)

_ROS2_STORE = get_typestore(Stores.ROS2_JAZZY)
_ROS1_STORE = get_typestore(Stores.ROS1_NOETIC)
_ROS1_STORE.register({**get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_TYPE),
                      **get_types_from_msg("geometry_msgs/TransformStamped[] transforms", LEGACY_TF_TYPE)})


class BagError(ValueError):
    """A bag that cannot be read or written as asked."""


class BagMessage(NamedTuple):
    topic: str
    stamp_ns: int
    msg: object


@dataclass
class TFMessageStandIn:
    """``tf2_msgs/TFMessage`` when the tf2_msgs package is not importable."""

    transforms: list[TransformStamped] = field(default_factory=list)


def _tf_message_class():
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return TFMessageStandIn
    return TFMessage


def _message_class(typename: str):
    """rclpy class for ``pkg/msg/Name`` or None when not importable."""
    if typename == TF_TYPE:
        return _tf_message_class()
    package, _, name = typename.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def _typename(msg) -> str:
    if isinstance(msg, TFMessageStandIn):
        return TF_TYPE
    cls = type(msg)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def _to_cdr(msg) -> bytes:
    if not isinstance(msg, TFMessageStandIn):
        return serialize_message(msg)
    transforms = [_ROS2_STORE.deserialize_cdr(serialize_message(t), _TRANSFORM_TYPE) for t in msg.transforms]
    tf_type = _ROS2_STORE.types[TF_TYPE]
    return bytes(_ROS2_STORE.serialize_cdr(tf_type(transforms=transforms), TF_TYPE))


def _from_cdr(raw: bytes, cls):
    if cls is not TFMessageStandIn:
        return deserialize_message(raw, cls)
    tf = _ROS2_STORE.deserialize_cdr(raw, TF_TYPE)
    return TFMessageStandIn([deserialize_message(bytes(_ROS2_STORE.serialize_cdr(t, _TRANSFORM_TYPE)),
                                                 TransformStamped) for t in tf.transforms])


def read_bag(path: str | Path, topics: Collection[str] | None = None) -> Iterator[BagMessage]:
    """Messages of a ROS 1 ``.bag`` file or a ROS 2 bag folder, in time order; all topics with an rclpy type, or
    exactly ``topics``."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        with AnyReader([path]) as reader:
            connections = _select(path, reader, topics)
            classes = {c.msgtype: _message_class(_ros2_typename(c.msgtype)) for c in connections}
            for conn, stamp, raw in reader.messages(connections=connections):
                typename = _ros2_typename(conn.msgtype)
                cdr = bytes(raw) if reader.is2 else bytes(_ROS2_STORE.ros1_to_cdr(raw, typename))
                yield BagMessage(conn.topic, stamp, _from_cdr(cdr, classes[conn.msgtype]))
    except _READ_ERRORS as err:
        raise BagError(f"bag {path} is corrupt or truncated ({type(err).__name__}: {err})") from err


def bag_topics(path: str | Path) -> dict[str, str]:
    """A bag's topics and their message types, read from its index (no message is read)."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        with AnyReader([path]) as reader:
            return {c.topic: _ros2_typename(c.msgtype) for c in reader.connections}
    except _READ_ERRORS as err:
        raise BagError(f"bag {path} is corrupt or truncated ({type(err).__name__}: {err})") from err


def _ros2_typename(msgtype: str) -> str:
    return TF_TYPE if msgtype == LEGACY_TF_TYPE else msgtype


def _select(path: Path, reader: AnyReader, topics: Collection[str] | None) -> list:
    available = {c.topic for c in reader.connections}
    if topics is not None:
        unknown = sorted(set(topics) - available)
        if unknown:
            raise BagError(f"bag {path} has no topics {unknown}; it has {sorted(available)}")
    chosen = [c for c in reader.connections if topics is None or c.topic in topics]
    unreadable = {(c.topic, c.msgtype) for c in chosen if _message_class(_ros2_typename(c.msgtype)) is None}
    if unreadable and topics is not None:
        raise BagError(f"bag {path}: no rclpy message class for {sorted(unreadable)}")
    if unreadable:
        warnings.warn(f"bag {path}: skipping topics without an rclpy message class: {sorted(unreadable)}",
                      stacklevel=3)
    return [c for c in chosen if (c.topic, c.msgtype) not in unreadable]


def _check_stamp(stamp_ns) -> int:
    if not isinstance(stamp_ns, int) or stamp_ns < 0:
        raise BagError(f"bag stamps are non-negative integer nanoseconds, got {stamp_ns!r}")
    return stamp_ns


class _Connections:
    """Topic -> (type name, connection) of a bag being written; one type per topic."""

    def __init__(self, add):
        self._add, self._by_topic = add, {}

    def get(self, topic: str, typename: str):
        if topic not in self._by_topic:
            self._by_topic[topic] = (typename, self._add(topic, typename))
        known, connection = self._by_topic[topic]
        if known != typename:
            raise BagError(f"topic {topic} carries {known}, cannot also write {typename}")
        return connection


def write_bag(path: str | Path, messages: Iterable[tuple[str, int, object]], storage: str = "sqlite3") -> None:
    """Write (topic, stamp_ns, rclpy msg) tuples to a new ROS 2 bag folder ``path`` (sqlite3 or mcap)."""
    if storage not in ROS2_STORAGE:
        raise BagError(f"unknown ROS 2 bag storage {storage!r}; choose one of {', '.join(ROS2_STORAGE)}")
    with Ros2Writer(Path(path), version=_ROS2_BAG_VERSION, storage_plugin=ROS2_STORAGE[storage]) as writer:
        connections = _Connections(lambda topic, typename: writer.add_connection(topic, typename,
                                                                                typestore=_ROS2_STORE))
        for topic, stamp_ns, msg in messages:
            writer.write(connections.get(topic, _typename(msg)), _check_stamp(stamp_ns), _to_cdr(msg))


def write_ros1_bag(path: str | Path, messages: Iterable[tuple[str, int, object]], legacy_tf: bool = True) -> None:
    """Write (topic, stamp_ns, rclpy msg) tuples to a new ROS 1 bag file; TF as ``tf/tfMessage`` (like the TUM
    RGB-D bags) when ``legacy_tf``, else as ``tf2_msgs/TFMessage``."""
    with Ros1Writer(Path(path)) as writer:
        def add(topic, typename):
            ros1_type = LEGACY_TF_TYPE if legacy_tf and typename == TF_TYPE else typename
            return writer.add_connection(topic, ros1_type, typestore=_ROS1_STORE)

        connections = _Connections(add)
        for topic, stamp_ns, msg in messages:
            typename = _typename(msg)
            ros1_data = _ROS2_STORE.cdr_to_ros1(_to_cdr(msg), typename)
            writer.write(connections.get(topic, typename), _check_stamp(stamp_ns), bytes(ros1_data))
