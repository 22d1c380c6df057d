"""Frame-to-keyframe where the map is thin: the newest keyframe's own depth, colour and semantics fill the pixels of a
model view that the Gaussians do not cover yet.

In ``worker.mode: async`` a keyframe's Gaussians join the map on the tracker's clock, before any optimisation, and a
map that has not been optimised renders a silhouette too faint to track against (below ``silhouette_threshold``).
The keyframe's measurements are what those Gaussians will come to render: each of its valid depth pixels is moved
into the model view's camera and lands on its nearest pixel, the nearest point winning where several land on one.
Rendered pixels keep their values.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from gausem_core.geometry import invert_pose
from gausem_core.slam.direct_alignment import ModelView
from gausem_core.slam.observation import Observation

FILL_MODES = ("async", "always", "never")


@dataclass(frozen=True)
class KeyframeView:
    """A keyframe's valid depth pixels as points in its camera (M, 3) with their colour and semantic colour (M, 3),
    and its camera-to-submap pose in the submap tracked against."""

    points: torch.Tensor
    rgb: torch.Tensor
    semantic: torch.Tensor
    cam_to_world: torch.Tensor

    @classmethod
    def of(cls, obs: Observation, cam_to_world: torch.Tensor) -> "KeyframeView":
        valid = obs.valid_depth
        rays = obs.camera.pixel_rays(obs.depth.dtype, obs.depth.device)
        return cls((rays * obs.depth[..., None])[valid], obs.rgb[valid], obs.semantic[valid], cam_to_world)

    def posed(self, cam_to_world: torch.Tensor) -> "KeyframeView":
        """The same keyframe at another camera-to-submap pose (in another submap's frame)."""
        return replace(self, cam_to_world=cam_to_world)


def fill_from_keyframe(view: ModelView, cam_to_world: torch.Tensor, keyframe: KeyframeView) -> ModelView:
    """``view`` (rendered at ``cam_to_world``) with the keyframe's points where its silhouette is missing."""
    camera, dtype = view.camera, view.depth.dtype
    moved = invert_pose(cam_to_world.to(dtype)) @ keyframe.cam_to_world.to(dtype)
    points = keyframe.points.to(dtype) @ moved[:3, :3].T + moved[:3, 3]
    z = points[:, 2]
    col = torch.floor(camera.fx * points[:, 0] / z.clamp_min(1e-6) + camera.cx)
    row = torch.floor(camera.fy * points[:, 1] / z.clamp_min(1e-6) + camera.cy)
    inside = (z > 1e-3) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    pixel = (row * camera.width + col).long()
    inside &= ~view.mask.reshape(-1)[pixel.clamp(0, view.mask.numel() - 1)]
    source = torch.nonzero(inside).squeeze(1)
    pixel, z = pixel[source], z[source]
    nearest = torch.full((view.mask.numel(),), float("inf"), dtype=dtype, device=z.device)
    nearest.scatter_reduce_(0, pixel, z, "amin")
    wins = z == nearest[pixel]  # ties (equal depths) carry equal values closely enough: the last write stays
    source, pixel = source[wins], pixel[wins]
    shape = view.mask.shape
    filled = torch.zeros(view.mask.numel(), dtype=torch.bool, device=z.device)
    filled[pixel] = True

    def put(image: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        out = image.reshape(view.mask.numel(), -1).clone()
        out[pixel] = values.reshape(len(values), -1)[source].to(out)
        return out.reshape(image.shape)

    depth = view.depth.reshape(-1).clone()
    depth[pixel] = nearest[pixel]
    return ModelView(put(view.color, keyframe.rgb), put(view.semantic, keyframe.semantic), depth.reshape(shape),
                     view.mask | filled.reshape(shape), camera, view.features)
