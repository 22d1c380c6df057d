"""REP-105 frames of the tracked camera: ``map -> odom -> camera``, or with a base frame ``map -> odom -> base_link``
and the camera on a static ``base_link -> camera`` (its extrinsic, ``/tf_static``).

``map`` is GauSem's world frame, the first frame's camera pose (as on gausem/odometry, gausem/path and gausem/map; not
gravity-aligned). ``odom`` coincides with it until the first correction. ``odom -> camera`` is the motion as tracked
and never jumps: each frame's odom pose is the last published frame's, moved by the motion between the two frames'
map poses read after the same corrections (so a correction in between is no motion); a frame that was not tracked
from that one (relocalised after tracking was lost, the first of a reset or loaded map) keeps the last odom pose.
``map -> odom`` (the map pose times the inverse odom pose) takes the rest: it jumps when the map is corrected (loop
closures, pose-graph updates, the global refinement) and at relocalisations.

With a base frame, ``odom -> base_link`` is the odom pose times the inverse extrinsic and ``base_link -> camera`` the
extrinsic, the tree REP-105 and a URDF's robot_state_publisher give (set the same extrinsic as the URDF's; the static
transform then repeats it). ``map`` and ``odom`` stay at the first camera pose either way, so TF, odometry, path and
map cloud share one map frame. GauSem is then the robot's odometry source: a robot whose own odometry publishes
``odom -> base_link`` would need GauSem to read TF (no tf2_ros on the pip path) and is not served.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

import msg_adapters as ma
from gausem_core.geometry import invert_pose, quaternion_to_matrix


def inverse(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (the core's :func:`~gausem_core.geometry.invert_pose` on an array)."""
    return invert_pose(torch.from_numpy(np.asarray(pose, dtype=np.float64))).numpy()


def extrinsic_matrix(values: Sequence[float]) -> np.ndarray:
    """``x y z qx qy qz qw`` (the camera in the base frame) as base-from-camera; ValueError naming the parameter."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (7,) or not np.isfinite(values).all() or np.linalg.norm(values[3:]) < 1e-9:
        raise ValueError("camera_extrinsic must be 7 finite numbers x y z qx qy qz qw (a non-zero quaternion), got "
                         f"{values.tolist()}")
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(torch.from_numpy(values[3:])).numpy()
    pose[:3, 3] = values[:3]
    return pose


class OdomFrame:
    """The odom pose (odom-from-camera) of the last published frame."""

    def __init__(self):
        self.pose: np.ndarray | None = None

    def advance(self, map_pose: np.ndarray, motion: np.ndarray | None) -> np.ndarray:
        """The odom pose of the next published frame: the last one moved by ``motion`` (last-frame-from-this-frame,
        from their map poses after the same corrections); None: not tracked from the last frame, the pose stays. The
        first frame's odom pose is its ``map_pose``."""
        if self.pose is None:
            self.pose = map_pose
        elif motion is not None:
            self.pose = self.pose @ motion
        return self.pose


class Rep105Frames:
    """The transforms of each published frame. ``base_frame`` "" (none): ``odom -> camera``; else ``odom ->
    base_frame`` and the static ``base_frame -> camera`` from ``camera_extrinsic`` (x y z qx qy qz qw)."""

    def __init__(self, map_frame: str, odom_frame: str, base_frame: str = "",
                 camera_extrinsic: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)):
        names = [map_frame, odom_frame] + ([base_frame] if base_frame else [])
        if not all(names) or len(set(names)) < len(names):
            raise ValueError(f"map_frame, odom_frame and base_frame must be distinct and the first two non-empty, got "
                             f"{map_frame!r}, {odom_frame!r}, {base_frame!r}")
        self.map_frame, self.odom_frame, self.base_frame = map_frame, odom_frame, base_frame
        self.base_from_camera = extrinsic_matrix(camera_extrinsic) if base_frame else None
        self.odom = OdomFrame()

    def transforms(self, stamp: float, camera_frame: str, map_pose: np.ndarray, motion: np.ndarray | None) -> list:
        """``map -> odom`` and ``odom -> camera`` (or ``odom -> base_frame``) of a frame with map pose ``map_pose``
        (map-from-camera) and ``motion`` (see :meth:`OdomFrame.advance`); they compose to ``map_pose``."""
        odom_pose = self.odom.advance(map_pose, motion)
        child, child_pose = camera_frame, odom_pose
        if self.base_from_camera is not None:
            child, child_pose = self.base_frame, odom_pose @ inverse(self.base_from_camera)
        return [ma.matrix_to_transform(map_pose @ inverse(odom_pose), ma.make_header(stamp, self.map_frame),
                                       self.odom_frame),
                ma.matrix_to_transform(child_pose, ma.make_header(stamp, self.odom_frame), child)]

    def static_transforms(self, stamp: float, camera_frame: str) -> list:
        """``base_frame -> camera`` (none without a base frame)."""
        if self.base_from_camera is None:
            return []
        return [ma.matrix_to_transform(self.base_from_camera, ma.make_header(stamp, self.base_frame), camera_frame)]
