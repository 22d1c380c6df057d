"""QoS profiles used across GauSem's topics (docs/DESIGN.md §4; measurements in its §5).

- ``IMAGE_QOS``: reliable, keep last 10 -- images between GauSem processes (best effort drops 20-60 % of VGA
  frames across processes with Fast DDS).
- ``SENSOR_QOS``: ``qos_profile_sensor_data`` (best effort, depth 5) -- accepted for live camera drivers.
- ``EVENT_QOS``: reliable, keep last 100 -- internal records (keyframes, submaps, loops, pose-graph updates) that
  must not be lost.
- ``LATCHED_QOS``: reliable, transient local, keep last 1 -- path and map: late subscribers get the latest.

Camera-rate inputs are subscribed with :func:`subscribe_camera`: without rclpy's default QoS-event handlers (see
there), with :class:`IncompatiblePublishers` saying instead what those handlers would have said.
"""
from __future__ import annotations

from collections.abc import Callable

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

IMAGE_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
SENSOR_QOS = qos_profile_sensor_data
EVENT_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

_INPUT_PROFILES = {"reliable": IMAGE_QOS, "sensor_data": SENSOR_QOS}
INPUT_QOS_HINT = "; a best-effort camera driver needs input_qos:=sensor_data"  # ends an incompatible-input warning


def input_qos(name: str) -> QoSProfile:
    """The camera-input profile named by a node parameter: ``reliable`` (default) or ``sensor_data`` (live camera)."""
    try:
        return _INPUT_PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown input QoS {name!r}; choose one of {', '.join(_INPUT_PROFILES)}") from None


def incompatibility(offered: QoSProfile, requested: QoSProfile) -> str | None:
    """Why a publisher offering ``offered`` delivers nothing to a subscription requesting ``requested`` (the DDS
    request-offered rules for reliability and durability), or None when it can."""
    if requested.reliability == ReliabilityPolicy.RELIABLE and offered.reliability == ReliabilityPolicy.BEST_EFFORT:
        return "it publishes best effort and this subscription is reliable"
    if (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and offered.durability == DurabilityPolicy.VOLATILE):
        return "it publishes volatile and this subscription is transient local"
    return None


class IncompatiblePublishers:
    """Looks up a subscription's publishers every ``period`` s and logs a warning once for each one whose QoS it
    cannot receive (what rclpy's default incompatible-QoS event handler says, for subscriptions made without it)."""

    def __init__(self, node, subscription, qos: QoSProfile, hint: str = "", period: float = 2.0):
        self._node, self._subscription, self._qos, self._hint = node, subscription, qos, hint
        self.reported: dict[bytes, str] = {}  # publisher gid -> the warning logged for it
        self._timer = node.create_timer(period, self.check)

    def check(self) -> None:
        topic = self._subscription.topic_name
        for info in self._node.get_publishers_info_by_topic(topic):
            why = incompatibility(info.qos_profile, self._qos)
            gid = bytes(info.endpoint_gid)
            if why and gid not in self.reported:
                publisher = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                self.reported[gid] = (f"{topic}: publisher {publisher} offers an incompatible QoS ({why}); no "
                                      f"messages will arrive from it{self._hint}")
                self._node.get_logger().warning(self.reported[gid])


def subscribe_camera(node, msg_type, topic: str, callback: Callable, qos: QoSProfile, callback_group=None,
                     hint: str = ""):
    """A subscription for camera-rate input, made without rclpy's default QoS-event handlers. Measured with
    Fast DDS (rmw_fastrtps_cpp, rclpy 7 / Jazzy): while a subscription holds messages not yet taken (its callback
    group busy with the one before), those handlers' wait conditions stay ready, though no event is there to
    take, so rclpy's executor rebuilds its wait set in a loop: 250-1,000 wait sets a second at a 30 Hz camera, its
    thread busy in Python for 60 % of the time, and each of those wake-ups takes the interpreter lock from the SLAM
    thread (whose torch calls release it). On a GPU, where a frame is thousands of short calls, the first frame of
    the tracking node then took over 40 s instead of 3. :class:`IncompatiblePublishers` says what the default
    handlers would have said (``hint`` is appended to its warning); the subscription keeps it as
    ``incompatible_publishers``."""
    subscription = node.create_subscription(
        msg_type, topic, callback, qos, callback_group=callback_group,
        event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
    subscription.incompatible_publishers = IncompatiblePublishers(node, subscription, qos, hint)
    return subscription
