"""The loop-detection node (paper Algorithm 1): ``gausem/keyframes`` + ``semantic/labels`` ->
``gausem/loop_candidates``.

Each keyframe record is paired with the label image of its stamp (within ``stamp_tolerance`` s; whichever arrives
first waits, at most ``cache_size`` of each). The keyframe's global descriptor is computed here from its semantic
colour image (the class table's colours of the labels) with ``semantics.descriptor`` (DINOv2 CLS with
``semantics.dinov2_weights``, else the colour-layout fallback), so labels are needed. Every keyframe the tracker
publishes is a loop keyframe (the tracker already keeps one every ``mapping.every`` frames; a keyframe id seen before
is a re-publication, whose corrected pose is kept, and otherwise ignored; a new id below the newest one is dropped as
``keyframe_out_of_order``); ``loop.check_every``,
``loop.max_descriptor_distance`` (DINOv2) or ``loop.max_fallback_descriptor_distance`` (the fallback descriptor),
``loop.exclude_recent`` and ``loop.proximity_radius`` (keyframes near in the latest published poses are candidates
too) configure the detector.

A keyframe id seen before with another stamp means the tracker started a new map (it was restarted or reset): the
node then forgets every keyframe and starts over, logging it.

Landmark scores (Eq. 7) need the class of every Gaussian of a submap and which ones a frame observes; this node does
not hold the map, so the keyframes' label pixels (every ``label_stride``-th row and column) stand in for the Gaussians:
a submap's Gaussian-IDF is computed over the pixels of its keyframes so far and a keyframe observes its own pixels.
"""
from __future__ import annotations

from collections import OrderedDict, defaultdict

import torch
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2

import msg_adapters as ma
from gausem_core.pipeline import resolve_device
from gausem_core.semantics import make_descriptor
from gausem_core.slam.loop import LoopDetector, gaussian_idf, landmark_scores, nearby_keyframes

from ..qos import EVENT_QOS, input_qos
from .common import DropReport, class_table, declare_parameters, declare_slam_config, run_node, survives_errors

NODE_DEFAULTS = {"classes": "synthetic", "input_qos": "reliable", "stamp_tolerance": 0.02, "cache_size": 60,
                 "label_stride": 4}


class LoopDetectionNode(Node):
    def __init__(self, **kwargs):
        super().__init__("loop_detection", **kwargs)
        self.cfg = cfg = declare_slam_config(self)
        self.params = p = declare_parameters(self, NODE_DEFAULTS)
        if p.label_stride < 1 or p.cache_size < 1 or p.stamp_tolerance < 0:
            raise ValueError(f"loop_detection: label_stride and cache_size must be >= 1 and stamp_tolerance >= 0, "
                             f"got {p.label_stride}, {p.cache_size}, {p.stamp_tolerance}")
        self.table = class_table(p.classes)
        self.extractor = make_descriptor(cfg.semantics.descriptor, cfg.semantics.dinov2_weights or None,
                                         device=resolve_device(cfg.device))
        self.drops = DropReport(self)
        self.candidates: list[ma.LoopCandidateRecord] = []
        self._labels: OrderedDict[float, object] = OrderedDict()  # stamp -> label image message
        self._start_map()
        self._pub = self.create_publisher(PointCloud2, "gausem/loop_candidates", EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/keyframes", self._on_keyframes, EVENT_QOS)
        self.create_subscription(Image, "semantic/labels", self._on_labels, input_qos(p.input_qos))
        if not cfg.loop.enabled:
            self.get_logger().info("loop.enabled is false: keyframes are ignored")

    def _start_map(self) -> None:
        """Forget every keyframe (a new map)."""
        self.detector = LoopDetector.from_config(self.cfg.loop, self.extractor.kind,
                                                 descriptor_dim=self.extractor.dim)
        self.keyframes_checked = 0
        self._keyframes: OrderedDict[float, ma.KeyframeRecord] = OrderedDict()  # waiting for their labels
        self._stamps: dict[int, float] = {}  # keyframe id -> its stamp
        self._world_poses: dict[int, torch.Tensor] = {}  # keyframe id -> latest map-from-camera (for proximity)
        self._submap_pixels: dict[int, list[torch.Tensor]] = defaultdict(list)

    @survives_errors
    def _on_labels(self, msg: Image) -> None:
        self._remember(self._labels, ma.header_seconds(msg.header), msg, "labels")
        self._pair()

    @survives_errors
    def _on_keyframes(self, msg: PointCloud2) -> None:
        if not self.cfg.loop.enabled:
            return
        try:
            records = ma.pointcloud2_to_records(msg, ma.KeyframeRecord)
        except ValueError as err:
            self.drops.drop("bad_keyframes", str(err))
            return
        for record in records:
            known = self._stamps.get(record.keyframe_id)
            if known is not None and known != record.stamp:
                self.get_logger().info(f"keyframe {record.keyframe_id} arrived with a new stamp ({record.stamp:.6f} s, "
                                       f"was {known:.6f} s): the tracker started a new map; starting over")
                self._start_map()
            newest = max(self._stamps, default=-1)
            if record.keyframe_id < newest and record.keyframe_id not in self._stamps:
                self.drops.drop("keyframe_out_of_order", f"new keyframe {record.keyframe_id} arrived after keyframe "
                                                         f"{newest}; the detector needs increasing ids")
                continue
            self._world_poses[record.keyframe_id] = torch.from_numpy(record.anchor_pose @ record.pose)
            if record.keyframe_id not in self._stamps:  # re-published keyframes (corrected poses) are not new
                self._stamps[record.keyframe_id] = record.stamp
                self._remember(self._keyframes, record.stamp, record, "keyframe")
        self._pair()

    def _remember(self, cache: OrderedDict, stamp: float, item, what: str) -> None:
        cache[stamp] = item
        if len(cache) > self.params.cache_size:
            oldest, _ = cache.popitem(last=False)
            if what == "keyframe":
                self.drops.drop("no_labels", f"keyframe stamped {oldest:.6f} s: no semantic/labels within "
                                             f"{self.params.stamp_tolerance} s arrived")

    def _pair(self) -> None:
        for stamp in list(self._keyframes):
            match = min(self._labels, key=lambda s: abs(s - stamp), default=None)
            if match is not None and abs(match - stamp) <= self.params.stamp_tolerance:
                self._check(self._keyframes.pop(stamp), self._labels[match])

    def _check(self, record: ma.KeyframeRecord, labels_msg: Image) -> None:
        try:
            labels = ma.image_to_labels(labels_msg)
            if not labels.size:
                raise ValueError(f"the label image is empty ({labels_msg.width}x{labels_msg.height})")
            semantic = self.table.colorize(labels)
        except ValueError as err:
            self.drops.drop("bad_labels", f"keyframe {record.keyframe_id}: {err}")
            return
        descriptor = torch.from_numpy(self.extractor.describe(semantic))
        step = self.params.label_stride
        pixels = torch.from_numpy(labels[::step, ::step].reshape(-1))
        submap = self._submap_pixels[record.submap_id]
        submap.append(pixels)
        class_ids = torch.cat(submap)
        observed = torch.zeros(len(class_ids), dtype=torch.bool)
        observed[-len(pixels):] = True
        scores = landmark_scores(class_ids, observed, gaussian_idf(class_ids, len(self.table)))
        loop = self.detector.add_keyframe(record.keyframe_id, record.submap_id, descriptor, scores,
                                          self._nearby(record.keyframe_id))
        self.keyframes_checked += 1
        if loop is None:
            return
        candidate = ma.loop_candidate_to_record(loop)
        self.candidates.append(candidate)
        self.get_logger().info(f"loop candidate: keyframe {loop.query_keyframe} -> {loop.match_keyframe} "
                               f"(descriptor distance {loop.descriptor_distance:.3f})")
        self._pub.publish(ma.records_to_pointcloud2([candidate], ma.make_header(record.stamp, "map")))


    def _nearby(self, keyframe_id: int) -> list[int]:
        """Keyframes near this one in the latest published poses (``loop.proximity_radius``; none when 0)."""
        others = {k: pose for k, pose in self._world_poses.items() if k != keyframe_id}
        loop = self.cfg.loop
        return nearby_keyframes(self._world_poses[keyframe_id], others, loop.proximity_radius,
                                loop.proximity_max_angle_deg)


def main(args=None) -> int:
    return run_node(LoopDetectionNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
