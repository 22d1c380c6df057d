"""Projection of isotropic Gaussians to the image: the per-Gaussian screen quantities both back-ends rasterise.

A Gaussian of world-space standard deviation ``r`` at camera depth ``z`` becomes an axis-aligned screen Gaussian of
standard deviations ``sigma_x = r fx / z`` and ``sigma_y = r fy / z`` pixels centred on the projected centre
(``u = fx x / z + cx``, pixel ``j`` has its centre at ``j + 0.5``). Gaussians whose centre is not in front of the near
plane get opacity 0 here, which leaves them out of every back-end. Everything is differentiable w.r.t. the cloud
tensors and ``world_to_cam``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera

ALPHA_MIN = 1.0 / 255.0  # contributions with a smaller alpha are ignored (as in 3DGS and gsplat)
ALPHA_MAX = 0.99  # alpha is clamped to this value (paper / 3DGS)


@dataclass
class ScreenGaussians:
    """A cloud's N Gaussians in screen space (all tensors have N rows; those not in front of the near plane have
    opacity 0)."""

    u: torch.Tensor  # pixel x of the centre
    v: torch.Tensor  # pixel y of the centre
    inv_var_x: torch.Tensor  # 1 / sigma_x^2 (pixels^-2)
    inv_var_y: torch.Tensor  # 1 / sigma_y^2
    opacity: torch.Tensor
    depth: torch.Tensor  # camera-frame z of the centre (the compositing order)
    features: torch.Tensor  # (M, 7): RGB, semantic RGB, depth -- the channels that are composited

    def __len__(self) -> int:
        return self.u.shape[0]

    @torch.no_grad()
    def footprint_radii(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Half-extents (x, y) in pixels of the ellipse where ``opacity * exp(-d^2 / 2) >= ALPHA_MIN``.

        That is ``k sigma`` with ``k = sqrt(2 ln(255 opacity)) <= 3.33``: outside it every alpha is below 1/255, so
        cutting the footprint there changes nothing beyond the 1/255 rule. Zero for opacities below 1/255.
        """
        k = (2.0 * torch.log(self.opacity / ALPHA_MIN)).clamp_min(0.0).sqrt()
        return k * self.inv_var_x.rsqrt(), k * self.inv_var_y.rsqrt()


def check_render_inputs(cloud: GaussianCloud, world_to_cam: torch.Tensor, camera: PinholeCamera, near: float) -> None:
    """Raise ValueError for arguments ``render`` cannot use."""
    if not isinstance(cloud, GaussianCloud):
        raise ValueError(f"render: cloud must be a GaussianCloud, got {type(cloud).__name__}")
    if not isinstance(camera, PinholeCamera):
        raise ValueError(f"render: camera must be a PinholeCamera, got {type(camera).__name__}")
    if not isinstance(world_to_cam, torch.Tensor) or tuple(world_to_cam.shape) != (4, 4):
        shape = tuple(world_to_cam.shape) if isinstance(world_to_cam, torch.Tensor) else type(world_to_cam).__name__
        raise ValueError(f"render: world_to_cam must be a (4, 4) tensor, got {shape}")
    if world_to_cam.device != cloud.device:
        raise ValueError(f"render: world_to_cam is on {world_to_cam.device} but the cloud is on {cloud.device}")
    if not cloud.dtype.is_floating_point:
        raise ValueError(f"render: the cloud must hold floating-point tensors, got {cloud.dtype}")
    if not (math.isfinite(near) and near > 0):
        raise ValueError(f"render: near must be a positive distance in metres, got {near}")


def project(cloud: GaussianCloud, world_to_cam: torch.Tensor, camera: PinholeCamera, near: float) -> ScreenGaussians:
    """Screen-space Gaussians of ``cloud`` seen through ``camera`` at ``world_to_cam``, one per Gaussian.

    Gaussians whose centre is not in front of the near plane get opacity 0 (so an empty footprint and no gradients)
    and a placeholder depth of 1: masking instead of gathering keeps the backward free of scatters."""
    pose = world_to_cam.to(cloud.dtype)
    cam = cloud.means @ pose[:3, :3].T + pose[:3, 3]
    x, y, z = cam.unbind(-1)
    opacity = torch.sigmoid(cloud.opacity_logits)
    in_front = z > near  # masked unconditionally: testing for any Gaussian behind would be a host sync per render
    z = torch.where(in_front, z, torch.ones_like(z))
    opacity = torch.where(in_front, opacity, torch.zeros_like(opacity))
    radii = cloud.log_radii.exp()
    return ScreenGaussians(
        u=camera.fx * x / z + camera.cx,
        v=camera.fy * y / z + camera.cy,
        inv_var_x=(z / (camera.fx * radii)) ** 2,
        inv_var_y=(z / (camera.fy * radii)) ** 2,
        opacity=opacity,
        depth=z,
        features=torch.cat([cloud.colors, cloud.semantics, z[:, None]], 1),
    )
