"""4x4 ``cam_to_world`` matrices (numpy) <-> geometry_msgs Pose / PoseStamped / TransformStamped, nav_msgs
Odometry and Path.

A message pose of a child frame in a parent frame (``header.frame_id``, e.g. ``map``) is the matrix that maps child
coordinates to parent coordinates, i.e. ``cam_to_world`` for the camera in the map. Quaternions are (x, y, z, w).
Odometry carries no twist (GauSem estimates poses only) and zero covariances (unknown).
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
from nav_msgs.msg import Odometry, Path
from std_msgs.msg import Header

from gausem_core.geometry import matrix_to_quaternion, quaternion_to_matrix

from .stamps import header_seconds, make_header

_ORTHONORMAL_TOL = 1e-4


def check_pose(matrix: np.ndarray, what: str = "pose") -> np.ndarray:
    """Validate a rigid 4x4 transform and return it as float64."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"{what}: expected a finite 4x4 matrix, got shape {m.shape}")
    rot = m[:3, :3]
    if (not np.allclose(m[3], [0, 0, 0, 1], atol=_ORTHONORMAL_TOL)
            or not np.allclose(rot.T @ rot, np.eye(3), atol=_ORTHONORMAL_TOL) or np.linalg.det(rot) <= 0):
        raise ValueError(f"{what}: not a rigid transform (rotation not orthonormal or bottom row not [0 0 0 1])")
    return m


def _quaternion_of(rot: np.ndarray) -> np.ndarray:
    return matrix_to_quaternion(torch.from_numpy(rot)).numpy()


def _rotation_of(q: Quaternion, what: str) -> np.ndarray:
    xyzw = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    norm = np.linalg.norm(xyzw)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"{what}: quaternion {xyzw.tolist()} cannot be normalised")
    return quaternion_to_matrix(torch.from_numpy(xyzw)).numpy()


def _matrix(translation: np.ndarray, rot: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, translation
    return m


def matrix_to_pose(matrix: np.ndarray) -> Pose:
    m = check_pose(matrix)
    x, y, z, w = _quaternion_of(m[:3, :3]).tolist()
    return Pose(position=Point(x=m[0, 3], y=m[1, 3], z=m[2, 3]), orientation=Quaternion(x=x, y=y, z=z, w=w))


def pose_to_matrix(pose: Pose) -> np.ndarray:
    p = pose.position
    return _matrix(np.array([p.x, p.y, p.z]), _rotation_of(pose.orientation, "Pose"))


def matrix_to_pose_stamped(matrix: np.ndarray, header: Header) -> PoseStamped:
    return PoseStamped(header=header, pose=matrix_to_pose(matrix))


def pose_stamped_to_matrix(msg: PoseStamped) -> np.ndarray:
    return pose_to_matrix(msg.pose)


def matrix_to_transform(matrix: np.ndarray, header: Header, child_frame_id: str) -> TransformStamped:
    """The transform of ``child_frame_id`` in ``header.frame_id`` (TF parent -> child)."""
    pose = matrix_to_pose(matrix)
    p = pose.position
    return TransformStamped(header=header, child_frame_id=child_frame_id,
                            transform=Transform(translation=Vector3(x=p.x, y=p.y, z=p.z), rotation=pose.orientation))


def transform_to_matrix(msg: TransformStamped) -> np.ndarray:
    t = msg.transform.translation
    return _matrix(np.array([t.x, t.y, t.z]), _rotation_of(msg.transform.rotation, "TransformStamped"))


def matrix_to_odometry(matrix: np.ndarray, header: Header, child_frame_id: str) -> Odometry:
    """Odometry of ``child_frame_id`` (the camera frame) in ``header.frame_id`` (``map``)."""
    msg = Odometry(header=header, child_frame_id=child_frame_id)
    msg.pose.pose = matrix_to_pose(matrix)
    return msg


def odometry_to_matrix(msg: Odometry) -> np.ndarray:
    return pose_to_matrix(msg.pose.pose)


def poses_to_path(poses: Iterable[tuple[float, np.ndarray]], frame_id: str, stamp: float | None = None) -> Path:
    """(stamp seconds, cam_to_world) pairs -> Path in ``frame_id``; the path's stamp is ``stamp`` or the last pose's."""
    entries = [matrix_to_pose_stamped(m, make_header(t, frame_id)) for t, m in poses]
    if stamp is None:
        header = entries[-1].header if entries else make_header(0.0, frame_id)
    else:
        header = make_header(stamp, frame_id)
    return Path(header=header, poses=entries)


def path_to_poses(msg: Path) -> list[tuple[float, np.ndarray]]:
    return [(header_seconds(p.header), pose_stamped_to_matrix(p)) for p in msg.poses]
