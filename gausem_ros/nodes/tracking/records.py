"""The map's records for the loop nodes and observers (``msg_adapters.records``, one PointCloud2 table a message):
``gausem/keyframes`` (KeyframeRecord, pose in its submap frame), ``gausem/submaps`` (SubmapEvent: created / closed,
anchor) and ``gausem/loop_constraints`` (LoopConstraintRecord, every accepted loop: the core's with ``loop_closure:
core``, for observers; the one registered here with ``nodes``, for pose_graph)."""
from __future__ import annotations

from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_core.slam.events import FrameEvents, KeyframeState, SubmapChange
from gausem_core.slam.loop_closure import LoopOutcome

from ...qos import EVENT_QOS


class RecordPublisher:
    """Publishes a frame's events and the keyframes and submaps as they are now."""

    def __init__(self, node):
        self._keyframe_pub = node.create_publisher(PointCloud2, "gausem/keyframes", EVENT_QOS)
        self._submap_pub = node.create_publisher(PointCloud2, "gausem/submaps", EVENT_QOS)
        self._constraint_pub = node.create_publisher(PointCloud2, "gausem/loop_constraints", EVENT_QOS)

    def constraint_listened(self) -> bool:
        """Whether anyone (pose_graph) subscribes to the loop constraints."""
        return self._constraint_pub.get_subscription_count() > 0

    def publish_events(self, events: FrameEvents, header) -> None:
        """A frame's submaps closed and opened, its keyframe and the loop the core closed, if accepted."""
        self.publish_submaps(events.submaps, header)
        if events.keyframe is not None:
            self.publish_keyframes([events.keyframe], header)
        self.publish_loop(events.loop, header)

    def publish_submaps(self, changes: list[SubmapChange] | tuple[SubmapChange, ...], header) -> None:
        events = [ma.SubmapEvent(c.submap_id, c.first_keyframe, c.anchor.numpy(),
                                 ma.SubmapEventKind.CREATED if c.opened else ma.SubmapEventKind.CLOSED)
                  for c in changes]
        if events:
            self._submap_pub.publish(ma.records_to_pointcloud2(events, header))

    def publish_keyframes(self, keyframes: list[KeyframeState], header) -> None:
        """KeyframeRecords with the keyframes' current poses."""
        records = [ma.KeyframeRecord(k.frame_id, k.timestamp, k.submap_id, k.pose.numpy(), k.anchor.numpy())
                   for k in keyframes]
        if records:
            self._keyframe_pub.publish(ma.records_to_pointcloud2(records, header))

    def publish_loop(self, loop: LoopOutcome | None, header) -> None:
        """A loop closure's constraint, when it was accepted."""
        if loop is not None and loop.constraint is not None:
            self._constraint_pub.publish(ma.records_to_pointcloud2([ma.loop_constraint_to_record(loop.constraint)],
                                                                   header))
