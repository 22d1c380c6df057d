"""Semantic landmark scores (paper §III-C, Eq. 7): Gaussian-IDF per submap and per-frame landmark score vectors.

All functions take per-Gaussian class ids (N,) (``GaussianCloud.class_ids(palette)``) and the number of classes C.
"""
from __future__ import annotations

import torch

from gausem_core.geometry import PinholeCamera, invert_pose, transform_points


def _class_counts(class_ids: torch.Tensor, num_classes: int, where: str) -> torch.Tensor:
    if num_classes <= 0:
        raise ValueError(f"{where}: num_classes must be positive, got {num_classes}")
    if class_ids.dim() != 1 or class_ids.dtype.is_floating_point or class_ids.dtype == torch.bool:
        raise ValueError(f"{where}: class_ids must be a 1-D integer tensor, "
                         f"got {class_ids.dtype} {tuple(class_ids.shape)}")
    if class_ids.numel() and (int(class_ids.min()) < 0 or int(class_ids.max()) >= num_classes):
        raise ValueError(f"{where}: class ids must lie in [0, {num_classes}), got [{int(class_ids.min())}, "
                         f"{int(class_ids.max())}]")
    return torch.bincount(class_ids, minlength=num_classes).to(torch.float64)


def gaussian_idf(class_ids: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Gaussian-IDF of a submap, f(c) = log(N / (1 + N_c)), (C,) float64.

    N is the number of Gaussians of the submap and N_c those of class c. A class absent from the submap (N_c = 0)
    gets the largest value, log N; it never matters for a frame of that submap, whose landmark score for an absent
    class is 0. A class holding (almost) all Gaussians gets f(c) <= 0 (log(N / (N + 1)) at N_c = N).
    """
    counts = _class_counts(class_ids, num_classes, "gaussian_idf")
    if class_ids.numel() == 0:
        raise ValueError("gaussian_idf: the submap has no Gaussians")
    return torch.log(class_ids.numel() / (1 + counts))


def landmark_scores(class_ids: torch.Tensor, observed: torch.Tensor, idf: torch.Tensor) -> torch.Tensor:
    """Landmark score vector of a frame, w(c) = (M / M_c) f(c) (Eq. 7), (C,) float64.

    ``class_ids`` (N,) and ``observed`` (N,) bool describe the Gaussians of the frame's submap and which of them the
    frame observes (e.g. visible in its render); ``idf`` (C,) is that submap's :func:`gaussian_idf`. M is the number
    of observed Gaussians and M_c those of class c. Classes not observed (M_c = 0) score 0, so a frame that observes
    nothing has the zero vector.
    """
    if observed.dtype != torch.bool or observed.shape != class_ids.shape:
        raise ValueError(f"landmark_scores: observed must be a bool mask of shape {tuple(class_ids.shape)}, "
                         f"got {observed.dtype} {tuple(observed.shape)}")
    if idf.dim() != 1:
        raise ValueError(f"landmark_scores: idf must be a (C,) vector, got shape {tuple(idf.shape)}")
    counts = _class_counts(class_ids[observed], idf.shape[0], "landmark_scores")
    seen = counts > 0
    ratio = torch.where(seen, counts.sum() / counts.clamp_min(1), torch.zeros_like(counts))
    return ratio * idf.to(torch.float64)


def landmark_distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """L2 distance between two landmark score vectors (C,)."""
    if a.dim() != 1 or a.shape != b.shape:
        raise ValueError(f"landmark_distance: need two vectors of equal length, "
                         f"got {tuple(a.shape)} and {tuple(b.shape)}")
    return float(torch.linalg.vector_norm(a.to(torch.float64) - b.to(torch.float64)))


def observed_gaussians(means: torch.Tensor, cam_to_world: torch.Tensor, camera: PinholeCamera, depth: torch.Tensor,
                       margin: float = 0.1) -> torch.Tensor:
    """Which Gaussians (centres (N, 3)) a frame observes, (N,) bool: the centre projects into the image, in front
    of the camera, onto a valid depth reading (H, W) that it is not more than ``margin`` metres behind (unoccluded)."""
    points = transform_points(invert_pose(cam_to_world.to(means.dtype)), means)
    z = points[:, 2]
    uv = camera.project(points)
    u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (z > 1e-3) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    measured = torch.zeros_like(z)
    measured[inside] = depth.to(z.dtype)[v[inside], u[inside]]
    return inside & (measured > 0) & (z <= measured + margin)
