"""QoS profiles used across GauSem's topics (docs/DESIGN.md §3; measurements in its §4).

- ``IMAGE_QOS``: reliable, keep last 10 -- images between GauSem processes (best effort drops 20-60 % of VGA
  frames across processes with Fast DDS).
- ``SENSOR_QOS``: ``qos_profile_sensor_data`` (best effort, depth 5) -- accepted for live camera drivers.
- ``EVENT_QOS``: reliable, keep last 100 -- internal records (keyframes, submaps, loops, pose-graph updates) that
  must not be lost.
- ``LATCHED_QOS``: reliable, transient local, keep last 1 -- path and map: late subscribers get the latest.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

IMAGE_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
SENSOR_QOS = qos_profile_sensor_data
EVENT_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

_INPUT_PROFILES = {"reliable": IMAGE_QOS, "sensor_data": SENSOR_QOS}


def input_qos(name: str) -> QoSProfile:
    """The camera-input profile named by a node parameter: ``reliable`` (default) or ``sensor_data`` (live camera)."""
    try:
        return _INPUT_PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown input QoS {name!r}; choose one of {', '.join(_INPUT_PROFILES)}") from None
