"""Trajectories and TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` lines, cam_to_world (world-from-camera)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gausem_core.data.tum import read_timestamped, tum_pose
from gausem_core.geometry import matrix_to_quaternion


@dataclass(frozen=True)
class Trajectory:
    """Timestamps (N,) in seconds and cam_to_world poses (N, 4, 4), float64."""

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self):
        stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if poses.shape[0] != stamps.shape[0]:
            raise ValueError(f"Trajectory: {stamps.shape[0]} stamps but {poses.shape[0]} poses")
        if not (np.isfinite(stamps).all() and np.isfinite(poses).all()):
            raise ValueError("Trajectory: stamps and poses must be finite")
        object.__setattr__(self, "stamps", stamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def subset(self, indices) -> "Trajectory":
        indices = np.asarray(indices, dtype=np.int64)
        return Trajectory(self.stamps[indices], self.poses[indices])

    def transformed(self, transform: np.ndarray, scale: float = 1.0) -> "Trajectory":
        """Apply ``x -> scale * R x + t`` (``transform`` = [R t; 0 1]) to the world frame of every pose."""
        poses = self.poses.copy()
        poses[:, :3, :3] = transform[:3, :3] @ self.poses[:, :3, :3]
        poses[:, :3, 3] = scale * self.positions @ transform[:3, :3].T + transform[:3, 3]
        return Trajectory(self.stamps, poses)


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """Read ``timestamp tx ty tz qx qy qz qw`` lines (``#`` comments, commas as separators accepted)."""
    rows = read_timestamped(Path(path), 7)
    for stamp, values in rows:
        if np.linalg.norm(np.asarray(values[3:], dtype=np.float64)) < 1e-9:
            raise ValueError(f"{path}: zero quaternion at timestamp {stamp}")
    poses = [tum_pose(values) for _, values in rows]
    return Trajectory([stamp for stamp, _ in rows], np.array(poses).reshape(-1, 4, 4))


def write_tum_trajectory(path: str | Path, trajectory: Trajectory) -> None:
    """Write a TUM trajectory file (evo-readable); quaternions in x y z w order with w >= 0."""
    quats = matrix_to_quaternion(torch.from_numpy(trajectory.poses[:, :3, :3])).numpy()
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, t, q in zip(trajectory.stamps, trajectory.positions, quats):
        lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    Path(path).write_text("\n".join(lines) + "\n")
