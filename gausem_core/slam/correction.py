"""Rigid correction of a submap after pose-graph optimisation moved its anchor (paper §III-C).

Our keyframe poses are cam_to_world (world-from-camera) and Gaussian centres are world points. The submap moves
rigidly with its anchor: every keyframe keeps its pose relative to the anchor, T_a^-1 T_k = T_a'^-1 T_k', so
    T_k' = C T_k,   x' = C x,   with the world-frame correction C = T_a' T_a^-1.
The paper writes T_k <- (T_a')^-1 T_a T_k, i.e. the same C with the anchor poses taken as world-to-camera
(P_a = T_a^-1 gives P_a'^-1 P_a = T_a' T_a^-1). Points seen from a keyframe keep their camera coordinates:
T_k'^-1 x' = T_k^-1 C^-1 C x = T_k^-1 x.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose


def anchor_correction(old_anchor: torch.Tensor, new_anchor: torch.Tensor) -> torch.Tensor:
    """World-frame correction C = T_a' T_a^-1 (4, 4) for cam_to_world anchor poses before and after."""
    old, new = _pose_stack(old_anchor, "old_anchor"), _pose_stack(new_anchor, "new_anchor")
    if old.shape[0] != 1 or new.shape[0] != 1:
        raise ValueError("anchor_correction: the anchors must be single 4x4 poses")
    return (new @ invert_pose(old))[0]


def correct_poses(poses: torch.Tensor | np.ndarray | Sequence, correction: torch.Tensor) -> torch.Tensor:
    """cam_to_world poses (N, 4, 4) (tensor, array or list of 4x4) -> C @ poses, as a tensor (N, 4, 4) on C's
    device."""
    stack = _pose_stack(poses, "poses")
    return correction.to(stack.dtype) @ stack.to(correction.device)


def correct_submap(cloud: GaussianCloud, keyframe_poses, old_anchor: torch.Tensor,
                   new_anchor: torch.Tensor) -> tuple[GaussianCloud, torch.Tensor]:
    """Move a submap's Gaussians and cam_to_world keyframe poses with its anchor: (moved cloud, poses (N, 4, 4))."""
    correction = anchor_correction(old_anchor, new_anchor)
    return cloud.transformed(correction), correct_poses(keyframe_poses, correction)


def _pose_stack(poses, what: str) -> torch.Tensor:
    if isinstance(poses, (list, tuple)):
        if not poses:
            raise ValueError(f"{what}: empty list of poses")
        poses = torch.stack([torch.as_tensor(p) for p in poses])
    stack = torch.as_tensor(poses)
    if stack.shape == (4, 4):
        stack = stack[None]
    if stack.dim() != 3 or stack.shape[1:] != (4, 4):
        raise ValueError(f"{what}: expected 4x4 poses, got shape {tuple(stack.shape)}")
    if not stack.is_floating_point() or not torch.isfinite(stack).all():
        raise ValueError(f"{what}: poses must be finite floating-point values")
    return stack
