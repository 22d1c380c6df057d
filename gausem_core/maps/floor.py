"""The floor plane of a map, and the floor frame the occupancy grid lies in.

GauSem's map frame is its first camera's (optical axes: x right, y down, z forward), so the floor is a plane to find,
not z = 0. The floor class's Gaussians give it when the map has class ids and enough of them are opaque; otherwise
the lowest well-supported level plane (normal within ``max_tilt_deg`` of the keyframes' mean image-up direction,
their -y axis: a hand-held or robot camera is held roughly level) below the cameras. Either way RANSAC on the
Gaussians' centres, refined by least squares on the inliers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

SOURCES = ("class", "plane")  # where a floor came from: the floor class's Gaussians, or the dominant level plane
HYPOTHESES = 512  # RANSAC planes tried
MAX_POINTS = 5000  # Gaussians scored per hypothesis (a random subset of larger maps)
LOWEST_SUPPORT = 0.3  # the floor: a plane below one with this fraction of its points is lower still
MIN_FLOOR_GAUSSIANS = 50  # fewer opaque floor-class Gaussians: the plane fit over all of them instead


@dataclass(frozen=True)
class FloorPlane:
    """A floor in the map frame: the height of a point ``p`` above it is ``normal @ p + offset``.

    ``pose``: map-from-floor (4, 4), the floor frame: z along ``normal`` (up), origin the map origin's foot on the
    floor, x the map's z axis (the first camera's view direction) projected onto the floor. ``source``: one of
    :data:`SOURCES`; ``inliers``: the Gaussians within the fit's threshold of it (of the
    :data:`MAX_POINTS` scored)."""

    normal: np.ndarray
    offset: float
    inliers: int
    source: str

    @property
    def pose(self) -> np.ndarray:
        up = self.normal
        forward = np.array([0.0, 0.0, 1.0]) - up[2] * up
        if np.linalg.norm(forward) < 1e-6:  # the first camera looked straight down: its x axis then
            forward = np.array([1.0, 0.0, 0.0]) - up[0] * up
        forward /= np.linalg.norm(forward)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([forward, np.cross(up, forward), up], 1)
        pose[:3, 3] = -self.offset * up
        return pose

    def heights(self, points: torch.Tensor) -> torch.Tensor:
        """Heights above the floor of map-frame points (..., 3)."""
        return points @ torch.as_tensor(self.normal, dtype=points.dtype, device=points.device) + self.offset


def fit_floor(means: torch.Tensor, floor_mask: torch.Tensor | None, cameras: torch.Tensor, max_tilt_deg: float,
              threshold: float, seed: int = 0) -> FloorPlane:
    """The floor from Gaussian centres ``means`` (N, 3) (opaque ones) and the keyframes' world poses ``cameras``
    (K, 4, 4): from the centres ``floor_mask`` (N,) marks (the floor class) when at least
    :data:`MIN_FLOOR_GAUSSIANS`, else from all. ValueError when no plane below the cameras is level enough."""
    if len(cameras) == 0:
        raise ValueError("the floor needs at least one keyframe (its view sets which way is up)")
    cameras = cameras.to(means)
    up = -cameras[:, :3, 1].mean(0)
    up = up / up.norm()
    centres = cameras[:, :3, 3]
    generator = torch.Generator(device=means.device).manual_seed(seed)
    if floor_mask is not None and int(floor_mask.sum()) >= MIN_FLOOR_GAUSSIANS:
        plane = _ransac(means[floor_mask], up, centres, max_tilt_deg, threshold, generator)
        if plane is not None:
            return FloorPlane(*plane, "class")
    plane = _ransac(means, up, centres, max_tilt_deg, threshold, generator)
    if plane is None:
        raise ValueError(f"no plane within {max_tilt_deg} deg of level lies below the cameras: no floor in the map")
    return FloorPlane(*plane, "plane")


def _ransac(points: torch.Tensor, up: torch.Tensor, centres: torch.Tensor, max_tilt_deg: float, threshold: float,
            generator: torch.Generator) -> tuple[np.ndarray, float, int] | None:
    """(normal, offset, inliers) of the lowest well-supported level plane below the cameras: the plane holding the
    most points, then, while the points below it (and below every plane before it) hold a plane with at least
    :data:`LOWEST_SUPPORT` of its points, that one (a sofa seat or a table top may hold more than the floor in view);
    refined by least squares on its inliers. None when no level plane lies below the cameras."""
    if len(points) > MAX_POINTS:
        points = points[torch.randperm(len(points), generator=generator, device=points.device)[:MAX_POINTS]]
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    plane = _dominant_plane(points, up, centres, cos_tilt, threshold, generator)
    if plane is None:
        return None
    below = points
    while True:  # the points left shrink at every step: it ends
        normal, offset, support = plane
        below = below[below @ normal + offset < -threshold]
        lower = _dominant_plane(below, up, centres, cos_tilt, threshold, generator)
        if lower is None or lower[2] < LOWEST_SUPPORT * support:
            break
        plane = lower
    normal, offset, _ = plane
    inliers = points[(points @ normal + offset).abs() < threshold]
    centre = inliers.mean(0)
    normal = torch.linalg.svd(inliers - centre, full_matrices=False).Vh[-1]
    normal = normal if normal @ up >= 0 else -normal
    return normal.double().cpu().numpy(), float(-(normal @ centre)), len(inliers)


def _dominant_plane(points: torch.Tensor, up: torch.Tensor, centres: torch.Tensor, cos_tilt: float, threshold: float,
                    generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, int] | None:
    """(normal turned up, offset, points within ``threshold``) of the plane through random triples of ``points``
    that holds the most, among those within the tilt of ``up`` and below every camera centre; None if none is."""
    if len(points) < 3:
        return None
    triples = points[torch.randint(len(points), (HYPOTHESES, 3), generator=generator, device=points.device)]
    normals = torch.linalg.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    normals = normals * torch.where(normals @ up < 0, -1.0, 1.0)[:, None]
    offsets = -(normals * triples[:, 0]).sum(-1)
    valid = (normals @ up >= cos_tilt) & ((centres @ normals.T + offsets) > threshold).all(0)
    support = ((points @ normals.T + offsets).abs() < threshold).sum(0) * valid
    best = int(support.argmax())
    return (normals[best], offsets[best], int(support[best])) if support[best] >= 3 else None
