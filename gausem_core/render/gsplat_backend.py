"""The CUDA back-end: gsplat's tile rasteriser fed with our own isotropic projection.

We call gsplat's low-level ``isect_tiles`` / ``isect_offset_encode`` / ``rasterize_to_pixels`` rather than
``gsplat.rasterization``: the latter projects with the full EWA Jacobian (off-axis Gaussians get stretched by up to
``1 + (x/z)^2`` in variance) and adds a 0.3 px^2 anti-aliasing blur, so it renders a different model from the torch
back-end. With our means2d/conics both back-ends evaluate the same screen Gaussians and share the 1/255 alpha rule
(gsplat skips ``alpha < 1/255``; our footprint radius is exactly where alpha drops below 1/255). What remains:

- gsplat clamps alpha at 0.999, we at 0.99 (differs only where ``opacity * exp(-d^2/2) > 0.99``);
- gsplat stops a pixel once the transmittance would fall to <= 1e-4, dropping that last Gaussian; we composite
  every pair (difference <= ``1e-4 * alpha / (1 - alpha)`` + 1e-4 of remaining weight);
- float32 arithmetic in a different order.

gsplat is imported lazily: the module loads without it, and calling the back-end without it raises ImportError.
"""
from __future__ import annotations

import math

import torch

from gausem_core.render.projection import ScreenGaussians

TILE_SIZE = 16


def _import_gsplat():
    try:
        import gsplat
    except ImportError as exc:
        raise ImportError("render backend 'gsplat' needs the gsplat package (pip install gsplat; CUDA only)") from exc
    return gsplat


def gsplat_available() -> bool:
    """True when gsplat imports (it still needs a CUDA device to run)."""
    try:
        _import_gsplat()
    except ImportError:
        return False
    return True


def _radii_per_axis(gsplat) -> bool:
    """gsplat >= 1.5 takes (x, y) radii of shape (..., N, 2); earlier versions one radius per Gaussian."""
    major, minor = (int(part) for part in gsplat.__version__.split(".")[:2])
    return (major, minor) >= (1, 5)


def rasterize_gsplat(screen: ScreenGaussians, width: int, height: int) -> torch.Tensor:
    """Composite ``screen`` (float32 CUDA tensors) into an (height, width, C + 1) image: features, then alpha."""
    gsplat = _import_gsplat()
    if screen.u.device.type != "cuda" or screen.u.dtype != torch.float32:
        raise ValueError(f"render backend 'gsplat' needs float32 CUDA tensors, got {screen.u.dtype} on "
                         f"{screen.u.device}; use backend='torch'")
    means2d = torch.stack([screen.u, screen.v], -1)[None]
    conics = torch.stack([screen.inv_var_x, torch.zeros_like(screen.u), screen.inv_var_y], -1)[None]
    with torch.no_grad():
        rx, ry = screen.footprint_radii()
        radii = torch.stack([rx, ry], -1).ceil().int()
        radii = torch.where((radii > 0).all(-1, keepdim=True), radii, 0)
        radii = radii[None] if _radii_per_axis(gsplat) else radii.amax(-1)[None]
        tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
        _, isect_ids, flatten_ids = gsplat.isect_tiles(means2d.detach(), radii, screen.depth.detach()[None],
                                                       TILE_SIZE, tiles_x, tiles_y)
        offsets = gsplat.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    features, alpha = gsplat.rasterize_to_pixels(means2d, conics, screen.features[None], screen.opacity[None],
                                                 width, height, TILE_SIZE, offsets, flatten_ids)
    return torch.cat([features[0], alpha[0]], -1)
