"""Object fragmentation across submaps (paper §III-A, Fig. 6): how much of each object lies in ONE submap.

Objects are instances found without an instance annotation: points of one class whose voxels (``voxel`` metres) touch,
26-connected. Each point carries the submap of the keyframe that observed it; an object's cohesion is the fraction of
its points in its majority submap (1 = never split). Structural classes (floor, wall, ...) span the scene and are
excluded by the caller.

An object the camera comes back to after a while (a loop) necessarily lands in a later submap too: that split is
loop closure's business, not allocation's. ``revisit_gap`` makes each visit its own object: an object's points seen
again after more than ``revisit_gap`` keyframes without any of them start a new visit.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.geometry import PinholeCamera, transform_points

_NEIGHBOURS = torch.tensor([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                            if (dx, dy, dz) > (0, 0, 0)])  # 13 offsets: each neighbour pair once


def keyframe_points(depth: torch.Tensor, labels: torch.Tensor, camera: PinholeCamera, cam_to_world: torch.Tensor,
                    stride: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (N, 3) and class ids (N,) of every ``stride``-th pixel (both axes) with valid depth."""
    if depth.shape != labels.shape or depth.shape != (camera.height, camera.width):
        raise ValueError(f"keyframe_points: depth {tuple(depth.shape)} and labels {tuple(labels.shape)} must both be "
                         f"{camera.height}x{camera.width}")
    points = camera.backproject(depth.double())[::stride, ::stride].reshape(-1, 3)
    keep = (depth[::stride, ::stride] > 0).reshape(-1)
    return transform_points(cam_to_world.to(points), points[keep]), labels[::stride, ::stride].reshape(-1)[keep]


def object_instances(points: torch.Tensor, labels: torch.Tensor, voxel: float = 0.1,
                     ignore_classes: tuple[int, ...] = ()) -> torch.Tensor:
    """(N,) instance id per point (-1 for ignored classes): connected components of same-class occupied voxels."""
    if points.shape[0] != labels.shape[0] or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"object_instances: points {tuple(points.shape)} must be (N, 3) "
                         f"for labels {tuple(labels.shape)}")
    if voxel <= 0:
        raise ValueError(f"object_instances: voxel must be positive, got {voxel}")
    device = labels.device
    instance = torch.full((points.shape[0],), -1, dtype=torch.long, device=device)
    kept = ~torch.isin(labels, torch.tensor(ignore_classes, dtype=labels.dtype, device=device))
    if not bool(kept.any()):
        return instance
    cells = torch.floor(points[kept] / voxel).long()
    cells = cells - cells.min(0).values + 1  # >= 1, so every neighbour offset stays >= 0
    extent = cells.max(0).values + 2
    classes = labels[kept].long()

    def encode(c, xyz):
        return ((c * extent[0] + xyz[..., 0]) * extent[1] + xyz[..., 1]) * extent[2] + xyz[..., 2]

    voxels, point_voxel = torch.unique(encode(classes, cells), return_inverse=True)
    voxel_class = torch.zeros(len(voxels), dtype=torch.long, device=device).scatter_(0, point_voxel, classes)
    voxel_cell = torch.zeros(len(voxels), 3, dtype=torch.long, device=device).index_copy_(0, point_voxel, cells)
    # edges between occupied same-class voxels that touch
    src, dst = [], []
    for offset in _NEIGHBOURS.to(device):
        keys = encode(voxel_class, voxel_cell + offset)
        at = torch.searchsorted(voxels, keys).clamp_max(len(voxels) - 1)
        hit = voxels[at] == keys
        src.append(torch.nonzero(hit).squeeze(1))
        dst.append(at[hit])
    src, dst = torch.cat(src), torch.cat(dst)
    component = torch.arange(len(voxels), device=device)
    while True:  # min-label propagation with pointer jumping
        updated = component.clone()
        updated.scatter_reduce_(0, src, component[dst], "amin")
        updated.scatter_reduce_(0, dst, component[src], "amin")
        updated = updated[updated]
        if torch.equal(updated, component):
            break
        component = updated
    instance[kept] = torch.unique(component, return_inverse=True)[1][point_voxel]
    return instance


def split_visits(instances: torch.Tensor, keyframes: torch.Tensor, revisit_gap: int) -> torch.Tensor:
    """(N,) visit id per point (-1 where ``instances`` is -1): an instance's points split where the keyframe indices
    (N,) that observe it jump by more than ``revisit_gap``."""
    if instances.shape != keyframes.shape:
        raise ValueError(f"split_visits: instances {tuple(instances.shape)} and keyframes {tuple(keyframes.shape)} "
                         f"must have one shape")
    if revisit_gap < 1:
        raise ValueError(f"split_visits: revisit_gap must be >= 1, got {revisit_gap}")
    visits = torch.full_like(instances, -1)
    seen = instances >= 0
    if not bool(seen.any()):
        return visits
    stride = int(keyframes.max()) + 1
    keys = instances[seen] * stride + keyframes[seen]
    pairs = torch.unique(keys)  # sorted: by instance, then keyframe
    starts = torch.ones(len(pairs), dtype=torch.bool, device=pairs.device)
    starts[1:] = (pairs[1:] // stride != pairs[:-1] // stride) | (pairs[1:] - pairs[:-1] > revisit_gap)
    visits[seen] = (starts.cumsum(0) - 1)[torch.searchsorted(pairs, keys)]
    return visits


@dataclass(frozen=True)
class Cohesion:
    """Per object (instance id, class id, points, fraction in its majority submap); ``mean`` over objects, ``worst``."""

    objects: list[tuple[int, int, int, float]]

    @property
    def mean(self) -> float:
        return sum(o[3] for o in self.objects) / len(self.objects)

    @property
    def worst(self) -> float:
        return min(o[3] for o in self.objects)


def submap_cohesion(instances: torch.Tensor, labels: torch.Tensor, submaps: torch.Tensor,
                    min_points: int = 50) -> Cohesion:
    """Fraction of each object's points (instance >= 0, at least ``min_points``) that lie in its majority submap."""
    if not instances.shape == labels.shape == submaps.shape:
        raise ValueError(f"submap_cohesion: instances {tuple(instances.shape)}, labels {tuple(labels.shape)} and "
                         f"submaps {tuple(submaps.shape)} must have one shape")
    objects = []
    for inst in torch.unique(instances[instances >= 0]).tolist():
        mine = instances == inst
        count = int(mine.sum())
        if count >= min_points:
            majority = int(torch.bincount(submaps[mine]).max())
            objects.append((inst, int(labels[mine][0]), count, majority / count))
    if not objects:
        raise ValueError(f"submap_cohesion: no object has {min_points} points or more")
    return Cohesion(objects)


def allocation_cohesion(keyframes: list[tuple[torch.Tensor, torch.Tensor, PinholeCamera, torch.Tensor]],
                        submap_of_keyframe: list[int], ignore_classes: tuple[int, ...], voxel: float = 0.1,
                        stride: int = 2, min_points: int = 50, revisit_gap: int | None = None) -> Cohesion:
    """Cohesion of a keyframe-to-submap assignment. keyframes (in time order): (depth (H, W), labels (H, W), camera,
    cam_to_world) with reference (e.g. ground-truth) poses, so that objects are found in one consistent world frame.
    With ``revisit_gap`` (keyframes), each visit of an object counts as one object (see the module notes)."""
    if len(keyframes) != len(submap_of_keyframe):
        raise ValueError(f"allocation_cohesion: {len(keyframes)} keyframes but {len(submap_of_keyframe)} submap ids")
    points, labels, submaps, observers = [], [], [], []
    for index, ((depth, kf_labels, camera, pose), submap) in enumerate(zip(keyframes, submap_of_keyframe)):
        p, lab = keyframe_points(depth, kf_labels, camera, pose, stride)
        points.append(p)
        labels.append(lab)
        submaps.append(torch.full((len(p),), submap, dtype=torch.long, device=lab.device))
        observers.append(torch.full((len(p),), index, dtype=torch.long, device=lab.device))
    points, labels, submaps = torch.cat(points), torch.cat(labels), torch.cat(submaps)
    instances = object_instances(points, labels, voxel, ignore_classes)
    if revisit_gap is not None:
        instances = split_visits(instances, torch.cat(observers), revisit_gap)
    return submap_cohesion(instances, labels, submaps, min_points)
