"""Colour resampled into the depth camera, for RGB-D data whose depth is not registered to colour (7-Scenes).

The depth camera stays the reference (the frame's camera, and the camera whose poses 7-Scenes' KinectFusion ground
truth gives): every depth pixel takes the colour where its 3-D point projects into the colour camera. Pixels
without a depth reading use the frame's median depth (the two cameras are a few centimetres apart, so the parallax
error there is small). The calibration (colour intrinsics, depth-to-colour transform) comes from the suite file.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from gausem_core.data.frame import Frame
from gausem_core.data.tum import camera_from_opencv


@dataclass(frozen=True)
class ColorCalibration:
    """Colour camera ``intrinsics`` (fx fy cx cy, OpenCV convention) at ``size`` (width, height), and the rigid
    ``depth_to_color`` transform (4x4, depth-camera to colour-camera coordinates, metres)."""

    intrinsics: tuple[float, float, float, float]
    size: tuple[int, int]
    depth_to_color: tuple[float, ...] = tuple(np.eye(4).ravel().tolist())  # 16 numbers, row-major

    @classmethod
    def from_dict(cls, values: dict) -> "ColorCalibration":
        """From a suite entry: ``intrinsics`` (4 numbers), ``size`` ([w, h]), optional ``depth_to_color`` (12/16)."""
        intrinsics = tuple(float(v) for v in values["intrinsics"])
        size = tuple(int(v) for v in values["size"])
        if len(intrinsics) != 4 or len(size) != 2:
            raise ValueError("color_calibration needs intrinsics [fx, fy, cx, cy] and size [width, height]")
        matrix = np.eye(4)
        if "depth_to_color" in values:
            numbers = np.asarray(values["depth_to_color"], np.float64).ravel()
            if numbers.size not in (12, 16):
                raise ValueError("color_calibration.depth_to_color needs 12 or 16 numbers (a 3x4 or 4x4 matrix)")
            matrix[:3] = numbers[:12].reshape(3, 4)
        return cls(intrinsics, size, tuple(matrix.ravel().tolist()))

    def color_in_depth_camera(self, frame: Frame) -> Frame:
        """``frame`` with its RGB resampled into its (depth) camera."""
        depth_camera = frame.camera
        color_camera = camera_from_opencv(*self.intrinsics, *self.size).scaled(depth_camera.width, depth_camera.height)
        valid = frame.depth > 0
        fill = float(np.median(frame.depth[valid])) if valid.any() else 1.0
        depth = torch.from_numpy(np.where(valid, frame.depth, fill).astype(np.float64))
        points = depth_camera.backproject(depth).numpy()
        transform = np.asarray(self.depth_to_color).reshape(4, 4)
        points = points @ transform[:3, :3].T + transform[:3, 3]
        z = np.maximum(points[..., 2], 1e-6)
        # cv2.remap samples at integer pixel centres; GauSem's cameras put them at integer + 0.5
        map_x = (color_camera.fx * points[..., 0] / z + color_camera.cx - 0.5).astype(np.float32)
        map_y = (color_camera.fy * points[..., 1] / z + color_camera.cy - 0.5).astype(np.float32)
        rgb = cv2.remap(frame.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return dataclasses.replace(frame, rgb=rgb)


class ColorRegistered:
    """A dataset view whose frames have their colour resampled into the depth camera (same length, names, ids;
    ``depth_registered`` stays the source's)."""

    def __init__(self, dataset, calibration: ColorCalibration):
        self.dataset, self.calibration = dataset, calibration
        self.name = dataset.name
        self.class_table = getattr(dataset, "class_table", None)
        self.depth_registered = getattr(dataset, "depth_registered", True)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> Frame:
        return self.calibration.color_in_depth_camera(self.dataset[i])
