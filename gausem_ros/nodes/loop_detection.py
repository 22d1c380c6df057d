"""The loop-detection node (paper Algorithm 1): ``gausem/place_signatures`` -> ``gausem/loop_candidates``.

A thin shell over the core's :class:`~gausem_core.slam.loop.LoopDetector`, built as the tracker's loop closure builds
it (``LoopDetector.from_config``: ``loop.place_recognition``, the descriptor kind ``semantics.descriptor`` and
``semantics.dinov2_weights`` name, ``loop.check_every``, the distance thresholds, ``loop.exclude_recent``,
``loop.bow``). tracking_mapping describes each loop keyframe (``LoopClosure.describe``: the global descriptor or the
bag of words' ORB features, the landmark scores over its submap's Gaussians, the keyframes near it in its current
pose estimates) and publishes that place signature, one per message; this node gives it to the detector and
answers every message with one ``gausem/loop_candidates`` message with its header (the keyframe's stamp): the ranked
candidates (at most ``loop.bow.candidates`` with the bag of words, which tracking_mapping verifies in order; at most
one otherwise), none when there are none or the signature was dropped (the tracker waits for this answer).

The first signature of a new map (the tracker started, was reset or loaded a map) is flagged ``new_map``: the node
forgets every keyframe first. After a load, the tracker sends the loaded map's stored signatures flagged ``loaded``,
one per message and each answered (with none) before the next, as it does for new keyframes: they are stored
without a loop check, so the database holds what the loaded core's does.

Signatures of ids seen before with the same stamp are re-publications and ignored; a new id below the newest one is
dropped as ``keyframe_out_of_order`` (the database needs increasing ids); a signature the detector refuses (another
place recognition, descriptor length or bad values) is dropped as ``bad_signature``. A keyframe id seen before with
another stamp also means the tracker started a new map (e.g. its ``new_map`` signature was lost): the node then
forgets every keyframe and starts over, logging it.
"""
from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from gausem_core.semantics.descriptors import DESCRIPTOR_DIM, descriptor_kind
from gausem_core.slam.loop import LoopDetector

from ..qos import EVENT_QOS
from .common import DropReport, declare_slam_config, run_node, survives_errors


class LoopDetectionNode(Node):
    def __init__(self, **kwargs):
        super().__init__("loop_detection", **kwargs)
        self.cfg = cfg = declare_slam_config(self)
        self.place_recognition = cfg.loop.place_recognition_for(descriptor_kind(cfg.semantics.descriptor,
                                                                                cfg.semantics.dinov2_weights))
        self.drops = DropReport(self)
        self.candidates: list[ma.LoopCandidateRecord] = []
        self._start_map()
        self._pub = self.create_publisher(PointCloud2, "gausem/loop_candidates", EVENT_QOS)
        self.create_subscription(PointCloud2, "gausem/place_signatures", self._on_signatures, EVENT_QOS)
        if not cfg.loop.enabled:
            self.get_logger().info("loop.enabled is false: place signatures are ignored")

    def _start_map(self) -> None:
        """Forget every keyframe (a new map)."""
        self.detector = LoopDetector.from_config(self.cfg.loop, self.place_recognition, descriptor_dim=DESCRIPTOR_DIM)
        self.keyframes_checked = 0
        self._stamps: dict[int, float] = {}  # keyframe id -> its stamp

    @survives_errors
    def _on_signatures(self, msg: PointCloud2) -> None:
        """Detect loops for the signatures of a message and answer it, whatever becomes of them."""
        if not self.cfg.loop.enabled:
            return
        candidates: list[ma.LoopCandidateRecord] = []
        try:
            for record in self._records(msg):
                candidates += self._detect(record)
        finally:
            self._pub.publish(ma.records_to_pointcloud2(candidates, msg.header, ma.LoopCandidateRecord))

    def _records(self, msg: PointCloud2) -> list[ma.PlaceSignatureRecord]:
        try:
            return ma.pointcloud2_to_records(msg, ma.PlaceSignatureRecord)
        except ValueError as err:
            self.drops.drop("bad_signature", str(err))
            return []

    def _detect(self, record: ma.PlaceSignatureRecord) -> list[ma.LoopCandidateRecord]:
        """The detector's ranked candidates for a new keyframe's signature (none for a loaded one, one seen before or
        one dropped)."""
        if record.new_map and self._stamps:
            self.get_logger().info(f"keyframe {record.keyframe_id} starts a new map; starting over")
            self._start_map()
        known = self._stamps.get(record.keyframe_id)
        if known == record.stamp:
            return []
        if known is not None:
            self.get_logger().info(f"keyframe {record.keyframe_id} arrived with a new stamp ({record.stamp:.6f} s, "
                                   f"was {known:.6f} s): the tracker started a new map; starting over")
            self._start_map()
        newest = max(self._stamps, default=-1)
        if record.keyframe_id < newest:
            self.drops.drop("keyframe_out_of_order", f"new keyframe {record.keyframe_id} arrived after keyframe "
                                                     f"{newest}; the detector needs increasing ids")
            return []
        try:
            ranked = self.detector.add_keyframe(ma.record_to_place_signature(record), check=not record.loaded)
        except ValueError as err:
            self.drops.drop("bad_signature", f"keyframe {record.keyframe_id} ({self.place_recognition} place "
                                             f"recognition here): {err}")
            return []
        self._stamps[record.keyframe_id] = record.stamp
        self.keyframes_checked += 1
        for c in ranked:
            self.get_logger().info(f"loop candidate: keyframe {c.query_keyframe} -> {c.match_keyframe} "
                                   f"(descriptor distance {c.descriptor_distance:.3f})")
        candidates = [ma.loop_candidate_to_record(c) for c in ranked]
        self.candidates += candidates
        return candidates


def main(args=None) -> int:
    return run_node(LoopDetectionNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
