"""The pose-graph node (GTSAM): ``gausem/keyframes``, ``gausem/submaps``, ``gausem/loop_constraints`` ->
``gausem/pose_graph`` (a PoseGraphUpdate: corrected poses, one record per node).

A thin shell over the core's :class:`~gausem_core.slam.loop_graphs.LoopGraphs`, the pose graphs ``gausem run``
corrects loops with: keyframe records give keyframe poses in their submap frame and their submaps' anchors (the latest
record wins: tracking_mapping re-publishes every keyframe with its current pose and anchor before each loop
constraint, so the graphs start from what the core's own would), submap events give the anchors of submaps no
keyframe record named yet, and each loop constraint re-optimises its level; the corrected poses are published
(KEYFRAME or ANCHOR nodes). A keyframe id seen before with another stamp means the
tracker started a new map (restarted or reset): the graphs start over. Constraints naming unknown keyframes or
submaps, or that the graph cannot take, are dropped and counted.
"""
from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_core.slam.loop_graphs import LoopGraphs

from ..qos import EVENT_QOS
from .common import DropReport, declare_parameters, declare_slam_config, run_node, survives_errors

NODE_DEFAULTS = {"map_frame": "map", "max_iterations": 100}


class PoseGraphNode(Node):
    def __init__(self, **kwargs):
        super().__init__("pose_graph", **kwargs)
        self.cfg = declare_slam_config(self)
        self.params = declare_parameters(self, NODE_DEFAULTS)
        LoopGraphs(self.cfg.loop)  # fails now, not at the first loop, on bad odometry sigmas or kernel
        self.drops = DropReport(self)
        self.updates_published = 0
        self._start_map()
        self._pub = self.create_publisher(PointCloud2, "gausem/pose_graph", EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/keyframes", self._on_keyframes, EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/submaps", self._on_submaps, EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/loop_constraints", self._on_loops, EVENT_QOS)

    def _start_map(self) -> None:
        self.graphs = LoopGraphs(self.cfg.loop, self.params.max_iterations)
        self._stamps: dict[int, float] = {}  # keyframe id -> its stamp

    @property
    def keyframes(self) -> dict[int, tuple[int, object]]:
        """Keyframe id -> (submap id, latest pose in the submap frame)."""
        return self.graphs.keyframes

    def _records(self, msg: PointCloud2, record_type):
        try:
            return ma.pointcloud2_to_records(msg, record_type)
        except ValueError as err:
            self.drops.drop(f"bad_{record_type.__name__}", str(err))
            return []

    @survives_errors
    def _on_keyframes(self, msg: PointCloud2) -> None:
        for r in self._records(msg, ma.KeyframeRecord):
            if self._stamps.setdefault(r.keyframe_id, r.stamp) != r.stamp:
                self.get_logger().info(f"keyframe {r.keyframe_id} arrived with a new stamp: the tracker started a new "
                                       "map; the pose graph starts over")
                self._start_map()
                self._stamps[r.keyframe_id] = r.stamp
            self.graphs.set_keyframe(r.keyframe_id, r.submap_id, r.pose)
            self.graphs.set_anchor(r.submap_id, r.anchor_pose)

    @survives_errors
    def _on_submaps(self, msg: PointCloud2) -> None:
        for r in self._records(msg, ma.SubmapEvent):
            if r.submap_id not in self.graphs.anchors:
                self.graphs.set_anchor(r.submap_id, r.anchor_pose)

    @survives_errors
    def _on_loops(self, msg: PointCloud2) -> None:
        for record in self._records(msg, ma.LoopConstraintRecord):
            name = f"loop constraint {record.keyframe_a}-{record.keyframe_b}"
            try:
                loop = ma.record_to_loop_constraint(record)
            except ValueError as err:
                self.drops.drop("bad_constraint", f"{name}: {err}")
                continue
            missing = self.graphs.missing(loop)
            if missing:
                self.drops.drop("unknown_nodes", f"{name}: unknown {', '.join(missing)}")
                continue
            try:
                update = self.graphs.add(loop)
            except ValueError as err:  # e.g. a loop between a node and itself
                self.drops.drop("bad_constraint", f"{name}: {err}")
                continue
            before, after = self.graphs.last_error
            self.get_logger().info(f"pose graph: {name}, {len(update.keyframes) or len(update.anchors)} nodes, "
                                   f"error {before:.4g} -> {after:.4g}")
            header = ma.make_header(max(ma.header_seconds(msg.header), 0.0), self.params.map_frame)
            self._pub.publish(ma.pose_graph_update_to_pointcloud2(ma.pose_graph_update_from_core(update), header))
            self.updates_published += 1


def main(args=None) -> int:
    return run_node(PoseGraphNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
