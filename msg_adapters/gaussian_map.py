"""GaussianCloud <-> sensor_msgs/PointCloud2 (the ``gausem/map`` topic).

Fields: x y z (FLOAT32), rgb (FLOAT32 holding 0x00RRGGBB like PCL, so RViz colours points with its RGB8 transformer),
label (INT32 class id, so the 28-byte points stay 4-byte aligned), opacity and radius (FLOAT32, activated values).
Colours are quantised to 8 bits. The reverse rebuilds semantic colours from a palette when one is given, otherwise
they are zero (unknown); the labels are returned either way.
"""
from __future__ import annotations

import numpy as np
import torch
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from gausem_core.gaussians import GaussianCloud

from .pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2

MAP_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4"), ("label", "<i4"),
                      ("opacity", "<f4"), ("radius", "<f4")])


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] (N, 3) -> PCL packed float32 (N,)."""
    c = np.rint(np.clip(colors, 0.0, 1.0) * 255).astype(np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """PCL packed float32 (N,) -> RGB in [0, 1] (N, 3) float32."""
    u = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], -1).astype(np.float32) / 255.0


def cloud_to_pointcloud2(cloud: GaussianCloud, header: Header, palette: torch.Tensor) -> PointCloud2:
    """The map as PointCloud2; ``palette`` (C, 3) gives each Gaussian's class id (nearest palette colour)."""
    return structured_to_pointcloud2(cloud_to_points(cloud, palette), header)


def cloud_to_points(cloud: GaussianCloud, palette: torch.Tensor, voxel_size: float = 0.0) -> np.ndarray:
    """The Gaussians as points of :data:`MAP_DTYPE`; with ``voxel_size`` > 0 (metres), one per voxel of that side
    that holds any: the most opaque (in the order of ``cloud``)."""
    c = cloud.detach().to(device="cpu", dtype=torch.float32)
    means, opacity = c.means.numpy(), c.opacities.numpy()
    keep = slice(None) if voxel_size <= 0 or not len(c) else _voxel_representatives(means, opacity, voxel_size)
    points = np.empty(len(means[keep]), MAP_DTYPE)
    points["x"], points["y"], points["z"] = means[keep, 0], means[keep, 1], means[keep, 2]
    points["rgb"] = pack_rgb(c.colors.numpy()[keep])
    points["label"] = c.class_ids(palette).numpy()[keep]
    points["opacity"] = opacity[keep]
    points["radius"] = c.radii.numpy()[keep]
    return points


def _voxel_representatives(means: np.ndarray, weights: np.ndarray, size: float) -> np.ndarray:
    """Indices (ascending) of the largest-``weights`` point in each voxel of side ``size`` that holds points."""
    keys = np.floor(means / size).astype(np.int64)
    order = np.lexsort((-weights, keys[:, 2], keys[:, 1], keys[:, 0]))
    keys = keys[order]
    first = np.ones(len(keys), bool)
    first[1:] = (keys[1:] != keys[:-1]).any(1)
    return np.sort(order[first])


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points of :data:`MAP_DTYPE` moved by the rigid 4x4 ``pose`` (a copy)."""
    out = points.copy()
    xyz = np.stack([points["x"], points["y"], points["z"]], -1).astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return out


def pointcloud2_to_cloud(msg: PointCloud2, palette: torch.Tensor | None = None) -> tuple[GaussianCloud, np.ndarray]:
    """PointCloud2 with the map fields -> (GaussianCloud, class ids (N,) int64)."""
    points = pointcloud2_to_structured(msg)
    missing = set(MAP_DTYPE.names) - set(points.dtype.names)
    if missing:
        raise ValueError(f"PointCloud2 is not a GauSem map: missing fields {sorted(missing)}")
    labels = points["label"].astype(np.int64)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    if palette is None:
        semantics = torch.zeros(len(points), 3)
    else:
        if labels.size and (labels.min() < 0 or labels.max() >= len(palette)):
            raise ValueError(f"map labels span [{labels.min()}, {labels.max()}], palette has {len(palette)} classes")
        semantics = palette.to(torch.float32)[torch.from_numpy(labels)]
    cloud = GaussianCloud.from_points(t(np.stack([points["x"], points["y"], points["z"]], -1)),
                                      t(unpack_rgb(points["rgb"])), semantics, t(points["radius"]),
                                      t(points["opacity"]))
    return cloud, labels
