"""The photometric, semantic and geometric losses of tracking (Eq. 2) and mapping (Eq. 3-4)."""
from __future__ import annotations

import torch

from gausem_core.image_ops import ssim_map
from gausem_core.render import RenderOutput
from gausem_core.slam.observation import Observation


def tracking_loss(out: RenderOutput, obs: Observation, w_color: float, w_depth: float, w_semantic: float,
                  silhouette_threshold: float) -> torch.Tensor:
    """Eq. 2: L1 colour + semantic + depth on pixels the map explains well (silhouette > threshold, valid depth)."""
    mask = (out.alpha.detach() > silhouette_threshold) & obs.valid_depth
    if not mask.any():
        return (out.color.sum() + out.depth.sum()) * 0.0
    color = (out.color - obs.rgb).abs().sum(-1)
    semantic = (out.semantic - obs.semantic).abs().sum(-1)
    depth = (out.expected_depth - obs.depth).abs()
    return (w_color * color + w_semantic * semantic + w_depth * depth)[mask].sum() / mask.sum()


def valid_depth_pixels(obs: Observation) -> torch.Tensor:
    """Flat indices of ``obs.valid_depth`` (their count is read to the host: a sync on a GPU)."""
    return obs.valid_depth.reshape(-1).nonzero()[:, 0]


def mapping_loss(out: RenderOutput, obs: Observation, w_color: float, w_depth: float, w_semantic: float,
                 ssim_lambda: float, valid_pixels: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 3: depth L1 on valid pixels + weighted SSIM losses (Eq. 4) for colour and semantics.

    The depth term compares the expected depth of the covered part (``depth / alpha``) and adds the uncovered
    fraction ``1 - alpha``: comparing the alpha-weighted depth sum itself would pull Gaussians behind the surface
    wherever the silhouette stays below 1. ``valid_pixels``: :func:`valid_depth_pixels` of ``obs`` when the caller
    keeps them (then the loss makes no host sync).
    """
    if valid_pixels is None:
        valid_pixels = valid_depth_pixels(obs)
    if len(valid_pixels):
        depth = ((out.expected_depth - obs.depth).abs().take(valid_pixels).mean()
                 + (1 - out.alpha).take(valid_pixels).mean())
    else:
        depth = out.depth.sum() * 0.0
    # Eq. 4 per channel, lam * L1 + (1 - lam) * (1 - SSIM), for colour and semantics in one SSIM pass
    rendered, target = torch.cat([out.color, out.semantic], -1), torch.cat([obs.rgb, obs.semantic], -1)
    l1 = (rendered - target).abs().mean(dim=(0, 1))
    dssim = 1 - ssim_map(rendered, target).mean(dim=(0, 2, 3))
    per_channel = ssim_lambda * l1 + (1 - ssim_lambda) * dssim
    return w_depth * depth + w_color * per_channel[:3].mean() + w_semantic * per_channel[3:].mean()
