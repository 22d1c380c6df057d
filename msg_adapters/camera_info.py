"""sensor_msgs/CameraInfo <-> gausem_core.geometry.PinholeCamera.

Pixel-centre convention: ROS (like OpenCV) puts the centre of pixel j at coordinate j, PinholeCamera at j + 0.5, so
``cx = K[0,2] + 0.5`` and ``cy = K[1,2] + 0.5`` (and back). Only K, width and height are used: distortion, R, P,
binning and ROI are ignored (GauSem expects rectified, unbinned, full-frame images); the built message carries
``distortion_model = "plumb_bob"`` with zero coefficients, R = I and P = [K | 0].
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from gausem_core.geometry import PinholeCamera

_PIXEL_CENTRE = 0.5


def camera_info_to_camera(msg: CameraInfo) -> PinholeCamera:
    k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if not np.isfinite(k).all() or fx <= 0 or fy <= 0:
        raise ValueError(f"CameraInfo (frame {msg.header.frame_id!r}) has an invalid K {k.ravel().tolist()}: "
                         "focal lengths must be finite and positive (an all-zero K means an uncalibrated camera)")
    if msg.width <= 0 or msg.height <= 0:
        raise ValueError(f"CameraInfo (frame {msg.header.frame_id!r}) has image size {msg.width}x{msg.height}")
    return PinholeCamera(float(fx), float(fy), float(cx) + _PIXEL_CENTRE, float(cy) + _PIXEL_CENTRE,
                         int(msg.width), int(msg.height))


def camera_to_camera_info(camera: PinholeCamera, header: Header) -> CameraInfo:
    cx, cy = camera.cx - _PIXEL_CENTRE, camera.cy - _PIXEL_CENTRE
    k = np.array([[camera.fx, 0, cx], [0, camera.fy, cy], [0, 0, 1]], dtype=np.float64)
    return CameraInfo(header=header, width=camera.width, height=camera.height, distortion_model="plumb_bob",
                      d=[0.0] * 5, k=k.ravel(), r=np.eye(3).ravel(), p=np.hstack([k, np.zeros((3, 1))]).ravel())
