"""The segmentation node: ``rgb/image`` -> ``semantic/labels`` (class ids, mono16 by default, same header) and
``semantic/color`` (rgb8, the class table's colours).

It needs a segmenter that works on the image alone: ``semantics.segmenter: ade20k`` (the shared pretrained model,
NYU40 classes: ``-p classes:=nyu40``) or ``dinov2`` (with ``semantics.dinov2_weights`` and
``semantics.head_weights``). With ``semantics.segmenter: labels`` the class ids come with the data -- the player
publishes ``semantic/labels`` from a labelled dataset, or another robot stack does -- so this node is not run (it
refuses to start and says so). Frames are segmented newest first; superseded or undecodable images are dropped and
counted on gausem/diagnostics (bad_encoding, bad_image; processing_error when segmenting raises).
"""
from __future__ import annotations

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image

import msg_adapters as ma
from gausem_core.config import SlamConfig
from gausem_core.data.classes import NYU40_CLASSES
from gausem_core.runtime import resolve_device
from gausem_core.semantics import Segmenter, segmenter_from_config

from ..qos import IMAGE_QOS, INPUT_QOS_HINT, input_qos, subscribe_camera
from .common import (DropReport, NewestFrameQueue, class_table, declare_parameters, declare_slam_config, run_node,
                     survives_errors)

NYU40_HINT = "; this segmenter predicts the NYU40 classes: set -p classes:=nyu40 (on tracking_mapping too)"
NODE_DEFAULTS = {"classes": "synthetic", "input_qos": "reliable", "label_encoding": "mono16"}


def build_segmenter(cfg: SlamConfig) -> Segmenter:
    kind = cfg.semantics.segmenter
    if kind == "labels":
        raise ValueError("segmentation node: semantics.segmenter is 'labels', which passes through class ids that "
                         "come with the data and cannot segment an image by itself; do not run this node -- the "
                         "player (or your robot stack) publishes semantic/labels -- or set semantics.segmenter: ade20k "
                         "(or dinov2)")
    return segmenter_from_config(cfg.semantics, resolve_device(cfg.device))


class SegmentationNode(Node):
    """``segmenter``: an already built segmenter (tests, embedding); by default built from the parameters."""

    def __init__(self, segmenter: Segmenter | None = None, **kwargs):
        super().__init__("segmentation", **kwargs)
        cfg = declare_slam_config(self)
        self.params = p = declare_parameters(self, NODE_DEFAULTS)
        self.table = class_table(p.classes)
        self.segmenter = segmenter if segmenter is not None else build_segmenter(cfg)
        if self.segmenter.num_classes != len(self.table):
            raise ValueError(f"segmentation node: the segmenter predicts {self.segmenter.num_classes} classes, the "
                             f"class table {p.classes!r} has {len(self.table)}" + NYU40_HINT * (
                                 self.segmenter.class_names == NYU40_CLASSES.names))
        ma.labels_to_image(self.table.ids[None], ma.make_header(0.0, ""), p.label_encoding)  # checks the encoding early
        self.drops = DropReport(self)
        self.frames_segmented = 0
        self._labels_pub = self.create_publisher(Image, "semantic/labels", IMAGE_QOS)
        self._color_pub = self.create_publisher(Image, "semantic/color", IMAGE_QOS)
        self._queue = NewestFrameQueue(self, self._segment, lambda _: self.drops.drop(
            "superseded", "a newer image arrived before this one was segmented"))
        subscribe_camera(self, Image, "rgb/image", self._queue.put, input_qos(p.input_qos),
                         MutuallyExclusiveCallbackGroup(), INPUT_QOS_HINT)  # images arrive while segmenting

    @survives_errors
    def _segment(self, msg: Image, arrived: float, skipped: int) -> None:
        del arrived, skipped  # superseded images are counted as drops by the queue's callback
        try:
            rgb = ma.image_to_rgb(msg)
        except ma.ImageEncodingError as err:
            self.drops.drop("bad_encoding", str(err))
            return
        except ValueError as err:  # data length / step inconsistent with the declared size
            self.drops.drop("bad_image", str(err))
            return
        labels = self.segmenter.segment(rgb.copy())
        self._labels_pub.publish(ma.labels_to_image(labels, msg.header, self.params.label_encoding))
        self._color_pub.publish(ma.rgb_to_image(self.table.colorize(labels), msg.header))
        self.frames_segmented += 1


def main(args=None) -> int:
    return run_node(SegmentationNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
