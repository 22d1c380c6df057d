"""Replica sequences in the NICE-SLAM layout: ``results/frame%06d.jpg``, ``results/depth%06d.png``, ``traj.txt``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gausem_core.data.frame import Dataset, Frame
from gausem_core.data.images import read_depth, read_rgb, require_file
from gausem_core.data.tum import camera_from_opencv
from gausem_core.geometry import PinholeCamera

REPLICA_DEPTH_SCALE = 6553.5
REPLICA_CAMERA = camera_from_opencv(600.0, 600.0, 599.5, 339.5, 1200, 680)


class ReplicaDataset(Dataset):
    """A NICE-SLAM Replica scene folder; ``traj.txt`` holds one row-major 4x4 cam_to_world (16 numbers) per frame.

    camera: the intrinsics (default NICE-SLAM's 600/600/599.5/339.5 at 1200x680); depth_scale: units per metre.
    """

    def __init__(self, path: str | Path, *, camera: PinholeCamera = REPLICA_CAMERA,
                 depth_scale: float = REPLICA_DEPTH_SCALE, fps: float = 30.0, **options):
        super().__init__(**options)
        self.root = Path(path)
        if not self.root.is_dir():
            raise FileNotFoundError(f"Replica folder {self.root} does not exist")
        self.name, self.camera, self.depth_scale, self.fps = self.root.name, camera, float(depth_scale), float(fps)
        self.poses = self._read_trajectory(self.root / "traj.txt")
        for i in range(len(self.poses)):
            require_file(self._rgb_path(i))
            require_file(self._depth_path(i))

    @staticmethod
    def _read_trajectory(path: Path) -> np.ndarray:
        rows = [line.split() for line in require_file(path).read_text().splitlines() if line.strip()]
        for number, row in enumerate(rows, 1):
            if len(row) != 16:
                raise ValueError(f"{path}:{number}: expected 16 numbers (a row-major 4x4 pose), got {len(row)}")
        if not rows:
            raise ValueError(f"{path}: empty trajectory")
        try:
            return np.array(rows, dtype=np.float64).reshape(-1, 4, 4)
        except ValueError as exc:
            raise ValueError(f"{path}: non-numeric entry ({exc})") from None

    def _rgb_path(self, i: int) -> Path:
        return self.root / "results" / f"frame{i:06d}.jpg"

    def _depth_path(self, i: int) -> Path:
        return self.root / "results" / f"depth{i:06d}.png"

    def _source_length(self) -> int:
        return len(self.poses)

    def _load(self, index: int) -> Frame:
        rgb = read_rgb(self._rgb_path(index))
        depth = read_depth(self._depth_path(index), self.depth_scale)
        return Frame(index, index / self.fps, rgb, depth, None, self.camera, self.poses[index])
