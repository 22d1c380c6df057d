"""The colour that Gauss-Newton tracking compares: each channel divided by its local mean (issue #25).

A camera's vignetting, auto-exposure and auto-white-balance multiply the image by a gain that is smooth over it
(vignetting) or constant over it (exposure; white balance per channel). The map is built from such images, so its
rendered colour carries a blend of the gains under which the keyframes saw each surface, the observed frame its own:
direct alignment on raw colour is pulled towards poses where the two gains agree (with vignetting: towards no motion).
Dividing each channel by its Gaussian-weighted local mean cancels any gain that is about constant over the window, in
the model view and in the observation alike, and keeps the texture that constrains the pose.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from gausem_core.image_ops import gaussian_blur, gaussian_window

_DARK = 0.05  # added to the local mean, so that noise in dark regions is amplified at most 1 / _DARK times
_LEVEL = 0.5  # scale of the result, _LEVEL * colour / (local mean + _DARK): about the range of the raw colours
_COARSE_SIGMA = 4.0  # pixels: a wider local mean is blurred at a lower resolution where its sigma is at least this


def local_contrast(color: torch.Tensor, width_fraction: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """(H, W, C) colour over its local mean: a Gaussian of sigma ``width_fraction`` times the image width, over the
    pixels of ``mask`` (H, W) only when given (elsewhere the result is meaningless); ``color`` itself when
    ``width_fraction`` is 0. A sigma of several times ``_COARSE_SIGMA`` pixels is applied at a lower resolution
    (area-averaged, then upsampled bilinearly): the mean is smooth, and the filter costs a fraction."""
    if width_fraction <= 0:
        return color
    height, width = color.shape[:2]
    sigma = width_fraction * width
    scale = max(1, int(sigma // _COARSE_SIGMA))
    weight = torch.ones_like(color[..., :1]) if mask is None else mask[..., None].to(color.dtype)
    x = torch.cat([color * weight, weight], -1).permute(2, 0, 1)[None]
    if scale > 1:
        x = F.interpolate(x, size=(math.ceil(height / scale), math.ceil(width / scale)), mode="area")
    sigma /= scale
    blurred = gaussian_blur(x, gaussian_window(2 * math.ceil(3 * sigma) + 1, sigma, color.dtype, color.device))
    if scale > 1:
        blurred = F.interpolate(blurred, size=(height, width), mode="bilinear", align_corners=False)
    blurred = blurred[0].permute(1, 2, 0)
    mean = blurred[..., :-1] / blurred[..., -1:].clamp_min(1e-6)
    return _LEVEL * color / (mean + _DARK)

