"""Hand-made submaps for the loop-closure tests: Gaussians back-projected from frames of the synthetic loop sequence
at their ground-truth poses, so every pose inside a submap is exact and only anchors (or injected drift) are wrong."""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from gausem_core.data.classes import SYNTHETIC_CLASSES
from gausem_core.data.synthetic import SyntheticDataset
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_exp, se3_log
from gausem_core.slam.densification import gaussians_from_pixels
from gausem_core.slam.mapper import Keyframe
from gausem_core.slam.observation import Observation
from gausem_core.slam.submap import Submap

PALETTE = SYNTHETIC_CLASSES.palette.float()


@lru_cache(maxsize=4)
def dataset(width: int = 160, height: int = 120) -> SyntheticDataset:
    return SyntheticDataset("loop", resolution=(width, height))


@lru_cache(maxsize=512)
def frame(index: int, width: int = 160, height: int = 120) -> tuple[Observation, torch.Tensor]:
    """Observation and ground-truth cam_to_world (float32) of a frame of the loop sequence."""
    f = dataset(width, height)[index % 360]
    return (Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, PALETTE, f.timestamp),
            torch.tensor(f.gt_pose, dtype=torch.float32))


def pixel_cloud(obs: Observation, cam_to_world: torch.Tensor, step: int = 4) -> GaussianCloud:
    """Every ``step``-th valid pixel as an opaque Gaussian 1.5 pixels wide (a stand-in for a mapped submap)."""
    pixels = torch.nonzero(obs.valid_depth.reshape(-1)).squeeze(1)[::step]
    cloud = gaussians_from_pixels(obs, cam_to_world, pixels, 0.9)
    cloud.log_radii = cloud.log_radii + math.log(1.5)
    return cloud


def make_submap(submap_id: int, frames: list[int], anchor: torch.Tensor | None = None, *, size=(160, 120),
                step: int = 4, ids: list[int] | None = None) -> Submap:
    """A submap over ``frames`` (its first frame is the anchor keyframe), keyframe ids ``ids`` (default: the frame
    indices). ``anchor``: the world-from-submap pose to store (default: the true one)."""
    true_anchor = frame(frames[0], *size)[1]
    keyframes, clouds = [], []
    for n, (index, kf_id) in enumerate(zip(frames, ids or frames)):
        obs, pose = frame(index, *size)
        local = invert_pose(true_anchor) @ pose
        keyframes.append(Keyframe(kf_id, obs, local, fixed=n == 0))
        clouds.append(pixel_cloud(obs, local, step))
    return Submap(submap_id, true_anchor.clone() if anchor is None else anchor, GaussianCloud.cat(clouds), keyframes)


def perturbation(translation: float, rotation_deg: float, seed: int = 0) -> torch.Tensor:
    """A rigid transform (float64) of exactly this translation (m) and rotation angle, random directions."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(6, generator=g, dtype=torch.float64)
    xi[:3] *= translation / xi[:3].norm()
    xi[3:] *= math.radians(rotation_deg) / xi[3:].norm()
    pose = se3_exp(xi)
    pose[:3, 3] = xi[:3]  # exactly ``translation`` metres
    return pose


def pose_error(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """(translation m, rotation deg) of a^-1 b."""
    rel = invert_pose(a.double()) @ b.double()
    return float(rel[:3, 3].norm()), math.degrees(float(se3_log(rel)[3:].norm()))
