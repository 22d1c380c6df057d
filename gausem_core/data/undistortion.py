"""Lens distortion undone: images of a camera with OpenCV's radial-tangential distortion remapped into a pinhole
camera (the TUM reader's frames, and a ROS camera whose camera_info states a distortion)."""
from __future__ import annotations

import cv2
import numpy as np

from gausem_core.geometry import PinholeCamera


class Undistortion:
    """Remaps images of a camera with lens distortion (OpenCV's k1 k2 p1 p2 [k3 [k4 k5 k6]]) into a pinhole
    :attr:`camera`: the largest one whose every pixel the distorted image covers (OpenCV's optimal new camera matrix,
    alpha 0; TUM fr1: focal length 5.7 % longer), so no border without depth or colour is left."""

    def __init__(self, camera: PinholeCamera, distortion: tuple[float, ...]):
        matrix = np.array([[camera.fx, 0, camera.cx - 0.5], [0, camera.fy, camera.cy - 0.5], [0, 0, 1]])
        coefficients, self.size = np.asarray(distortion, np.float64), (camera.width, camera.height)
        pinhole, _ = cv2.getOptimalNewCameraMatrix(matrix, coefficients, self.size, 0.0)
        fx, fy, cx, cy = (float(v) for v in (pinhole[0, 0], pinhole[1, 1], pinhole[0, 2], pinhole[1, 2]))
        self.camera = PinholeCamera(fx, fy, cx + 0.5, cy + 0.5, *self.size)  # pixel centres at integer + 0.5
        self._maps = cv2.initUndistortRectifyMap(matrix, coefficients, None, pinhole, self.size, cv2.CV_32FC1)

    def color(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def nearest(self, image: np.ndarray) -> np.ndarray:
        """Depth (or uint8/uint16 labels) by nearest pixel: no blend across a depth edge; 0 where no source."""
        return cv2.remap(image, *self._maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def labels(self, labels: np.ndarray) -> np.ndarray:
        """Class ids of any integer type by nearest pixel (0 where no source)."""
        return self.nearest(labels.astype(np.float32)).astype(labels.dtype)
