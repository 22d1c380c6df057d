"""The pose-graph node (GTSAM): ``gausem/keyframes``, ``gausem/submaps``, ``gausem/loop_constraints`` ->
``gausem/pose_graph`` (a PoseGraphUpdate: corrected poses, one record per node).

It keeps every keyframe's pose in its submap frame (the latest record of it wins: tracking_mapping re-publishes a
submap's keyframes before an intra-submap constraint, as bundle adjustment moves them) and every submap's anchor
pose in the map. A keyframe id seen before with another stamp means the tracker started a new map (restarted or
reset): the graph is then emptied. Each loop constraint re-optimises one level (paper §III-C) with the core's graph
(:func:`~gausem_core.slam.pose_graph.optimise_chain`, as ``gausem run`` does): an intra-submap loop the keyframes of
that submap, an inter-submap loop the anchors, each with odometry edges between consecutive nodes (sigmas from
``loop.odometry_sigma_*``, grown with the keyframes in between), the first node fixed, and every loop of that level so
far under ``loop.robust_kernel`` with the sigmas of its information matrix. The optimised poses replace the stored
ones and are published (KEYFRAME or ANCHOR nodes). Constraints naming unknown keyframes or submaps are dropped and
counted.
"""
from __future__ import annotations

from collections import Counter

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_core.slam.loop_closure import LoopConstraint, odometry_sigmas
from gausem_core.slam.pose_graph import PoseGraph, optimise_chain

from ..qos import EVENT_QOS
from .common import DropReport, declare_parameters, declare_slam_config, run_node, survives_errors

NODE_DEFAULTS = {"map_frame": "map", "max_iterations": 100}


class PoseGraphNode(Node):
    def __init__(self, **kwargs):
        super().__init__("pose_graph", **kwargs)
        self.cfg = declare_slam_config(self)
        self.params = declare_parameters(self, NODE_DEFAULTS)
        # fails now, not at the first loop, on bad odometry sigmas or kernel:
        PoseGraph(odometry_sigmas=odometry_sigmas(self.cfg.loop, 1), robust_kernel=self.cfg.loop.robust_kernel)
        self.drops = DropReport(self)
        self.updates_published = 0
        self._start_map()
        self._pub = self.create_publisher(PointCloud2, "gausem/pose_graph", EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/keyframes", self._on_keyframes, EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/submaps", self._on_submaps, EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/loop_constraints", self._on_loops, EVENT_QOS)

    def _start_map(self) -> None:
        self.keyframes: dict[int, tuple[int, object]] = {}  # keyframe id -> (submap id, pose in the submap frame)
        self.anchors: dict[int, object] = {}  # submap id -> anchor pose in the map
        self.loops: list[LoopConstraint] = []
        self._stamps: dict[int, float] = {}  # keyframe id -> its stamp

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
            self.keyframes[r.keyframe_id] = (r.submap_id, r.pose)
            self.anchors.setdefault(r.submap_id, r.anchor_pose)

    @survives_errors
    def _on_submaps(self, msg: PointCloud2) -> None:
        for r in self._records(msg, ma.SubmapEvent):
            self.anchors.setdefault(r.submap_id, r.anchor_pose)

    @survives_errors
    def _on_loops(self, msg: PointCloud2) -> None:
        for record in self._records(msg, ma.LoopConstraintRecord):
            name = f"loop constraint {record.keyframe_a}-{record.keyframe_b}"
            try:
                loop = ma.record_to_loop_constraint(record)
            except ValueError as err:
                self.drops.drop("bad_constraint", f"{name}: {err}")
                continue
            missing = self._missing(loop)
            if missing:
                self.drops.drop("unknown_nodes", f"{name}: unknown {missing}")
                continue
            self.loops.append(loop)
            try:
                nodes = self._optimise_keyframes(loop.submap_a) if loop.intra else self._optimise_anchors()
            except ValueError as err:  # e.g. a loop between a node and itself
                self.loops.pop()
                self.drops.drop("bad_constraint", f"{name}: {err}")
                continue
            header = ma.make_header(max(ma.header_seconds(msg.header), 0.0), self.params.map_frame)
            self._pub.publish(ma.pose_graph_update_to_pointcloud2(ma.PoseGraphUpdate(nodes), header))
            self.updates_published += 1

    def _missing(self, loop: LoopConstraint) -> list[str]:
        if loop.intra:
            return [f"keyframe {k}" for k in (loop.keyframe_a, loop.keyframe_b)
                    if self.keyframes.get(k, (None,))[0] != loop.submap_a]
        return [f"submap {s}" for s in (loop.submap_a, loop.submap_b) if s not in self.anchors]

    def _optimise(self, poses: dict[int, object], intra: bool, sigmas) -> dict[int, object]:
        loops = [c.edge for c in self.loops if c.intra == intra and c.edge[0] in poses]
        result = optimise_chain(poses, loops, sigmas, self.cfg.loop.robust_kernel, self.params.max_iterations)
        self.get_logger().info(f"pose graph: {len(poses)} nodes, {len(loops)} loops, error "
                               f"{result.error_before:.4g} -> {result.error_after:.4g}")
        return result.poses

    def _optimise_keyframes(self, submap_id: int) -> list[ma.PoseGraphNode]:
        poses = {k: pose for k, (s, pose) in self.keyframes.items() if s == submap_id}
        optimised = self._optimise(poses, True, lambda _: odometry_sigmas(self.cfg.loop, 1))
        self.keyframes.update({k: (submap_id, pose) for k, pose in optimised.items()})
        return [ma.PoseGraphNode(ma.PoseGraphNodeKind.KEYFRAME, k, pose) for k, pose in optimised.items()]

    def _optimise_anchors(self) -> list[ma.PoseGraphNode]:
        counts = Counter(s for s, _ in self.keyframes.values())
        optimised = self._optimise(self.anchors, False, lambda s: odometry_sigmas(self.cfg.loop, counts[s]))
        self.anchors.update(optimised)
        return [ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, s, pose) for s, pose in optimised.items()]


def main(args=None) -> int:
    return run_node(PoseGraphNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
