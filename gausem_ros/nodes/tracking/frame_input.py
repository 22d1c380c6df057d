"""The tracking node's frames: the camera of ``rgb/camera_info`` and the validated observation of one synchronised
rgb / depth (/ labels) frame.

A camera_info stating a lens distortion (non-zero D, OpenCV's plumb_bob or rational_polynomial coefficients) makes
every frame go through its undistortion (``gausem_core.data.undistortion``): the frames are then a pinhole camera's.
A frame is rejected (:class:`~gausem_ros.nodes.common.FrameRejected`, its reason the drop's) for a stamp not after
the last processed frame's, no camera_info yet, a side below ``min_image_size``, wrong encodings, data shorter than
its declared size, sizes that differ, labels outside the class table, too little valid depth (``min_valid_depth``),
or a camera that is neither the map's nor a scaling of it (``camera_changed``: a frame of a scaled camera is resized
to the map's, said once per size). Frames of more than ``max_image_pixels`` pixels are downscaled (aspect kept,
intrinsics scaled).
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch
from sensor_msgs.msg import CameraInfo, Image

import msg_adapters as ma
from gausem_core.data.frame import Frame, resize_frame
from gausem_core.data.undistortion import Undistortion
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.observation import Observation

from ...qos import INPUT_QOS_HINT, subscribe_camera
from ..common import DropReport, FrameRejected, survives_errors

CAMERA_TOLERANCE_PX = 0.5  # intrinsics (scaled to the map's image size) that differ by more are another camera
NO_LABELS_FIX = ("use_labels is true but no semantic/labels arrived: a bag that records labels under another name "
                 "replays them with --topic labels=TOPIC (gausem-player, gausem-ros); for data without labels set "
                 "-p use_labels:=false, or run the segmentation node (-p semantics.segmenter:=ade20k "
                 "-p classes:=nyu40)")


class FrameInput:
    """Subscribes ``rgb/camera_info`` (with ``qos``, in ``callback_group``; a rejected one counts on ``drops``) and
    turns messages into observations for the core; ``params``: the node's (``min_image_size``, ``max_image_pixels``,
    ``min_valid_depth``); ``palette``: the class table's colours."""

    def __init__(self, node, params: SimpleNamespace, palette: torch.Tensor, device: torch.device, drops: DropReport,
                 qos, callback_group):
        self.get_logger, self.drops = node.get_logger, drops  # as survives_errors takes them
        self._params, self._palette, self._device = params, palette, device
        # the latest valid camera_info: (the pinhole camera the frames are given in, the Undistortion that takes
        # them there or None), replaced whole so that a frame never pairs one camera_info's camera with another's
        self._camera: tuple[PinholeCamera, Undistortion | None] | None = None
        self.lens_distortion: tuple[float, ...] = ()  # its D (empty: none stated)
        self._rescaled_sizes: set[tuple[int, int]] = set()  # frame sizes said to be resized to the map's camera
        subscribe_camera(node, CameraInfo, "rgb/camera_info", self.camera_info, qos, callback_group, INPUT_QOS_HINT)

    def reset(self) -> None:
        """A new map: a frame size resized to its camera is said again."""
        self._rescaled_sizes.clear()

    @property
    def camera(self) -> PinholeCamera | None:
        """The pinhole camera the frames are processed in (after any undistortion); None before a camera_info."""
        return None if self._camera is None else (self._camera[1].camera if self._camera[1] else self._camera[0])

    @survives_errors(frame=False)
    def camera_info(self, msg: CameraInfo) -> None:
        """Take a camera_info's camera and undistortion (said once per calibration); one it cannot take is rejected
        (bad_camera_info: the one before stays)."""
        try:
            camera = ma.camera_info_to_camera(msg)
            distortion = tuple(float(d) for d in msg.d) if any(msg.d) else ()
            if distortion and len(distortion) not in (4, 5, 8):
                raise ValueError(f"CameraInfo distortion {msg.distortion_model!r} has {len(distortion)} "
                                 "coefficients; GauSem undoes OpenCV's 4, 5 or 8 (plumb_bob, rational_polynomial)")
        except ValueError as err:
            self.drops.drop("bad_camera_info", str(err), frame=False)
            return
        if self._camera is not None and (self._camera[0], self.lens_distortion) == (camera, distortion):
            return
        undistortion = Undistortion(camera, distortion) if distortion else None
        if undistortion is not None:
            c = undistortion.camera
            self.get_logger().info(f"rgb/camera_info states lens distortion {msg.distortion_model} {list(distortion)}: "
                              f"frames are undistorted into the pinhole fx {c.fx:.1f} fy {c.fy:.1f} "
                              f"cx {c.cx - 0.5:.1f} cy {c.cy - 0.5:.1f}")
        self._camera, self.lens_distortion = (camera, undistortion), distortion

    def observation(self, msgs: tuple[Image, ...], after: float, map_camera: PinholeCamera | None) -> Observation:
        """The validated observation of one synchronised frame (rgb, depth and maybe labels), stamped after
        ``after``, in ``map_camera`` (None: a new map's first frame), or FrameRejected saying why not."""
        rgb_msg, depth_msg, labels_msg = (*msgs, None)[:3]
        stamp = ma.header_seconds(rgb_msg.header)
        if stamp <= after:
            raise FrameRejected("stale_stamp", f"frame stamped {stamp:.6f} s is not after the last processed "
                                               f"frame ({after:.6f} s)")
        if self._camera is None:
            raise FrameRejected("no_camera_info", "no valid rgb/camera_info received yet; waiting for it")
        camera, undistortion = self._camera
        self._check_min_size(rgb_msg, depth_msg, labels_msg)
        rgb, depth, labels = _decode(rgb_msg, depth_msg, labels_msg)
        sizes = {"rgb": rgb.shape[:2], "depth": depth.shape, "labels": labels.shape,
                 "camera_info": (camera.height, camera.width)}
        if len(set(sizes.values())) > 1:
            raise FrameRejected("size_mismatch", "image sizes differ (height, width): "
                                + ", ".join(f"{k} {v}" for k, v in sizes.items()))
        if labels.size and (labels.min() < 0 or labels.max() >= len(self._palette)):
            raise FrameRejected("bad_labels", f"labels span [{labels.min()}, {labels.max()}], outside the class "
                                              f"table's ids 0..{len(self._palette) - 1} (parameter classes)")
        if undistortion is not None:
            rgb, depth, labels, camera = (undistortion.color(rgb), undistortion.nearest(depth),
                                          undistortion.labels(labels), undistortion.camera)
        valid = float((depth > 0).mean()) if depth.size else 0.0
        if valid < self._params.min_valid_depth:
            raise FrameRejected("invalid_depth", f"only {100 * valid:.1f} % of the depth pixels are valid (finite, "
                                                 f"> 0); at least {100 * self._params.min_valid_depth:.1f} % needed")
        frame = self._limit_pixels(Frame(0, stamp, rgb, depth, labels, camera))
        if map_camera is not None:
            frame = self._in_map_camera(frame, map_camera)
        return Observation.from_arrays(frame.rgb, frame.depth, frame.labels, frame.camera, self._palette, stamp,
                                       self._device)

    def _check_min_size(self, *msgs: Image | None) -> None:
        """FrameRejected (bad_size) for an image with a side below ``min_image_size``, before any decoding."""
        least = self._params.min_image_size
        for name, msg in zip(("rgb", "depth", "labels"), msgs):
            if msg is not None and min(msg.width, msg.height) < least:
                raise FrameRejected("bad_size", f"{name} image is {msg.width}x{msg.height}: sides below "
                                                f"{least} pixels are dropped (parameter min_image_size)")

    def _limit_pixels(self, frame: Frame) -> Frame:
        """The frame downscaled, aspect kept, to at most ``max_image_pixels`` pixels (rgb area-averaged, depth and
        labels nearest, intrinsics scaled: ``resize_frame``); FrameRejected (bad_size) if a side would fall below
        ``min_image_size``."""
        w, h = frame.size
        limit = self._params.max_image_pixels
        if w * h <= limit:
            return frame
        scale = math.sqrt(limit / (w * h))
        size = int(w * scale), int(h * scale)
        if min(size) < self._params.min_image_size:
            raise FrameRejected("bad_size", f"a {w}x{h} image downscaled to max_image_pixels = {limit} would be "
                                            f"{size[0]}x{size[1]}, a side below min_image_size; raise "
                                            "max_image_pixels or lower min_image_size")
        return resize_frame(frame, *size)

    def _in_map_camera(self, frame: Frame, ours: PinholeCamera) -> Frame:
        """The frame in the map's camera ``ours``: one whose camera is a scaling of it is resized to it (said once
        per size); another camera is rejected (camera_changed: a map has one camera model)."""
        theirs = frame.camera.scaled(ours.width, ours.height)
        if max(abs(a - b) for a, b in zip((theirs.fx, theirs.fy, theirs.cx, theirs.cy),
                                          (ours.fx, ours.fy, ours.cx, ours.cy))) > CAMERA_TOLERANCE_PX:
            raise FrameRejected("camera_changed", f"the frame's camera {frame.camera} is not the map's {ours} nor a "
                                                  "scaling of it; gausem/reset starts a map in the new camera")
        if frame.size != (ours.width, ours.height) and frame.size not in self._rescaled_sizes:
            self._rescaled_sizes.add(frame.size)
            self.get_logger().info(f"frames of {frame.size[0]}x{frame.size[1]} are resized to the map's "
                              f"{ours.width}x{ours.height} (their camera is a scaling of its camera)")
        return resize_frame(frame, ours.width, ours.height)


def _decode(rgb_msg: Image, depth_msg: Image, labels_msg: Image | None):
    """RGB, depth (metres) and labels (zeros without a labels input) arrays, or FrameRejected (bad_encoding;
    bad_image when the data does not hold the declared size)."""
    try:
        rgb = ma.image_to_rgb(rgb_msg)
        depth = ma.image_to_depth(depth_msg)
        labels = ma.image_to_labels(labels_msg) if labels_msg is not None else np.zeros(depth.shape, np.int64)
    except ma.ImageEncodingError as err:
        raise FrameRejected("bad_encoding", str(err)) from err
    except ValueError as err:  # data length / step inconsistent with the declared size
        raise FrameRejected("bad_image", str(err)) from err
    return rgb, depth, labels
