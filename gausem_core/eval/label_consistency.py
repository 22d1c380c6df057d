"""Cross-view label consistency: where no semantic ground truth exists, how often two views of the same surface point
give it the same class.

Frame A's pixels with a measured depth are lifted to 3D with A's pose, carried into frame B with B's pose and
compared with B's class id at the pixel they land on, where that pixel sees the same surface (B's measured depth
agrees within ``tolerance`` of the carried point's depth, relative). Labels that flicker from view to view score low;
labels fused in a map score high when the map's classes are stable and the poses right.
"""
from __future__ import annotations

import torch

from gausem_core.geometry import PinholeCamera, invert_pose


def carried_labels(labels: torch.Tensor, depth: torch.Tensor, cam_to_world: torch.Tensor,
                   target_cam_to_world: torch.Tensor, target_depth: torch.Tensor, camera: PinholeCamera,
                   tolerance: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame A's class ids (``labels``, ``depth``, ``cam_to_world``) carried into frame B (``target_*``, same camera):
    the flat pixel indices of B that they land on, and the ids they carry there (one per carried A pixel)."""
    a_to_b = invert_pose(target_cam_to_world.double()) @ cam_to_world.double()
    valid = depth > 0
    points = camera.backproject(depth.double())[valid]
    points = points @ a_to_b[:3, :3].T + a_to_b[:3, 3]
    in_front = points[:, 2] > 1e-6
    points, carried = points[in_front], labels[valid][in_front]
    uv = torch.floor(camera.project(points)).long()
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    uv, points, carried = uv[inside], points[inside], carried[inside]
    index = uv[:, 1] * camera.width + uv[:, 0]
    seen = target_depth.reshape(-1)[index].double()
    same_surface = (seen > 0) & ((seen - points[:, 2]).abs() <= tolerance * points[:, 2])
    return index[same_surface], carried[same_surface]


def label_agreement(labels: torch.Tensor, depth: torch.Tensor, cam_to_world: torch.Tensor,
                    target_labels: torch.Tensor, target_depth: torch.Tensor, target_cam_to_world: torch.Tensor,
                    camera: PinholeCamera, tolerance: float = 0.05) -> tuple[int, int]:
    """(pixels whose carried class equals frame B's, pixels compared) for frame A's labels carried into B."""
    index, carried = carried_labels(labels, depth, cam_to_world, target_cam_to_world, target_depth, camera, tolerance)
    return int((target_labels.reshape(-1)[index] == carried).sum()), int(index.numel())
