"""Write any dataset as a TUM RGB-D folder that :class:`~gausem_core.data.tum.TumDataset` reads back.

Besides the TUM files (``rgb/``, ``depth/`` 16-bit x5000, ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``,
``calib.txt``), labelled datasets get ``labels/`` (16-bit class ids) and ``classes.txt``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gausem_core.data.images import write_rgb, write_uint16
from gausem_core.data.tum import TUM_DEPTH_SCALE
from gausem_core.geometry import matrix_to_quaternion


def tum_pose_line(timestamp: float, pose: np.ndarray) -> str:
    """``timestamp tx ty tz qx qy qz qw`` of a 4x4 cam_to_world."""
    q = matrix_to_quaternion(torch.from_numpy(np.asarray(pose[:3, :3], np.float64))).numpy()
    return f"{timestamp:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))


def write_tum_folder(dataset, path: str | Path) -> Path:
    """Write every frame of ``dataset`` (one camera for all frames) under ``path``; returns the folder."""
    root = Path(path)
    labelled = dataset.class_table is not None
    for sub in ("rgb", "depth", "labels") if labelled else ("rgb", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines = ["# timestamp filename"], ["# timestamp filename"]
    gt_lines = ["# timestamp tx ty tz qx qy qz qw"]
    camera = None
    for frame in dataset:
        camera = camera or frame.camera
        if frame.camera != camera:
            raise ValueError(f"frame {frame.index} has camera {frame.camera}, the folder has one camera: {camera}")
        name = f"{frame.index:06d}.png"
        write_rgb(root / "rgb" / name, frame.rgb)
        write_uint16(root / "depth" / name, np.round(np.minimum(frame.depth * TUM_DEPTH_SCALE, 65535)))
        if labelled:
            if frame.labels is None:
                raise ValueError(f"frame {frame.index} has no labels although the dataset has a class table")
            write_uint16(root / "labels" / name, frame.labels)
        rgb_lines.append(f"{frame.timestamp:.6f} rgb/{name}")
        depth_lines.append(f"{frame.timestamp:.6f} depth/{name}")
        if frame.gt_pose is not None:
            gt_lines.append(tum_pose_line(frame.timestamp, frame.gt_pose))
    if camera is None:
        raise ValueError(f"{dataset}: no frames to write")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("groundtruth.txt", gt_lines)):
        (root / name).write_text("\n".join(lines) + "\n")
    # files state intrinsics with pixel centres at integers (see gausem_core.data.tum)
    (root / "calib.txt").write_text("# fx fy cx cy depth_scale width height\n"
                                    f"{camera.fx!r} {camera.fy!r} {camera.cx - 0.5!r} {camera.cy - 0.5!r} "
                                    f"{TUM_DEPTH_SCALE} {camera.width} {camera.height}\n")
    if labelled:
        dataset.class_table.save(root / "classes.txt")
    return root
