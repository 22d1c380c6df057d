"""TF broadcasting that works with and without tf2.

``make_transform_broadcaster(node)`` returns, in order of preference:
1. ``tf2_ros.TransformBroadcaster`` / ``StaticTransformBroadcaster`` (a real ROS install);
2. a small publisher of ``tf2_msgs/TFMessage`` on ``/tf`` (keep last 100) or ``/tf_static`` (transient local),
   the QoS tf2_ros uses, when only ``tf2_msgs`` is importable (the pip set-up builds it: tools/build_tf2_msgs.sh,
   docs/DESIGN.md §5);
3. a broadcaster that drops transforms and logs once that TF is unavailable (neither package: the PyPI wheels ship
   none, and the set-up could not build tf2_msgs without cmake and a compiler);
   nodes keep publishing odometry and path, which carry the same poses.
All three have ``sendTransform(transform_or_list)`` like tf2_ros.
"""
from __future__ import annotations

import threading

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile

_TF_QOS = QoSProfile(depth=100)
_TF_STATIC_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _as_list(transforms) -> list:
    return list(transforms) if isinstance(transforms, (list, tuple)) else [transforms]


class TFMessagePublisher:
    """tf2_ros-compatible broadcaster built on a plain ``tf2_msgs/TFMessage`` publisher."""

    def __init__(self, node, tf_message_type, static: bool = False):
        self._type = tf_message_type
        topic, qos = ("/tf_static", _TF_STATIC_QOS) if static else ("/tf", _TF_QOS)
        self._pub = node.create_publisher(tf_message_type, topic, qos)
        self._static = static
        self._latched: dict[str, object] = {}

    def sendTransform(self, transforms) -> None:  # noqa: N802 (tf2_ros' name)
        transforms = _as_list(transforms)
        if self._static:  # like tf2_ros: the latched message holds every static transform sent so far
            self._latched.update({t.child_frame_id: t for t in transforms})
            transforms = list(self._latched.values())
        self._pub.publish(self._type(transforms=transforms))


class UnavailableTransformBroadcaster:
    """Drops transforms; warns once through the node's logger."""

    def __init__(self, node):
        self._logger = node.get_logger()
        self._warned = False

    def sendTransform(self, transforms) -> None:  # noqa: N802 (tf2_ros' name)
        del transforms
        if not self._warned:
            self._logger.warning("TF is unavailable (neither tf2_ros nor tf2_msgs is importable): "
                                 "transforms are not broadcast; use the odometry and path topics, or build "
                                 "tf2_msgs with tools/build_tf2_msgs.sh VENV (needs cmake and g++)")
            self._warned = True


class SerialisedBroadcaster:
    """A broadcaster whose sends never overlap: a static one keeps every transform sent so far, and parts of a node
    send through it from several callback groups (tracking_mapping's camera and grid frames)."""

    def __init__(self, broadcaster):
        self._broadcaster = broadcaster
        self._lock = threading.Lock()

    def sendTransform(self, transforms) -> None:  # noqa: N802 (tf2_ros' name)
        with self._lock:
            self._broadcaster.sendTransform(transforms)


def make_transform_broadcaster(node, static: bool = False):
    """The best broadcaster available (see the module docstring); a static one is serialised."""
    broadcaster = _best_broadcaster(node, static)
    return SerialisedBroadcaster(broadcaster) if static else broadcaster


def _best_broadcaster(node, static: bool):
    try:
        from tf2_ros import StaticTransformBroadcaster, TransformBroadcaster
    except ImportError:
        pass
    else:
        return StaticTransformBroadcaster(node) if static else TransformBroadcaster(node)
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return UnavailableTransformBroadcaster(node)
    return TFMessagePublisher(node, TFMessage, static)
