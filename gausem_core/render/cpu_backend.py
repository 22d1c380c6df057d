"""The compiled CPU back-end: the torch back-end's exact model in C++ loops (``gausem_core/native/raster.cpp``).

Gaussians are ordered front to back by a radix sort of their depths (the order of ``pairs.depth_order``), pairs are
bucketed by pixel with a counting sort (the Gaussians are visited front to back, so each pixel's list is already in
compositing order) and every pixel is composited, and differentiated, in one pass (without gradients, the Gaussians
are composited as they are visited, no pairs kept); the torch back-end
needs a comparison sort and a dozen gathers/scatters over all pairs instead. Memory: about 8 bytes per (Gaussian,
pixel) pair plus one float64 gradient buffer of (5 + C) values per Gaussian with a footprint in the image, and
thread. Rows run in parallel on torch's intra-op threads. The kernel is built on first use (:mod:`gausem_core.native`);
when it cannot be, ``backend="auto"`` uses the torch back-end.
"""
from __future__ import annotations

import torch

from gausem_core.native import require_kernel
from gausem_core.render.pairs import footprint_boxes
from gausem_core.render.projection import ScreenGaussians


class _RasterizeCpu(torch.autograd.Function):
    """``apply(u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height)`` ->
    ``(height * width, C + 1)``."""

    @staticmethod
    def forward(ctx, u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height):
        image, offsets, slots, alpha = require_kernel().rasterize_forward(
            u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height)
        ctx.save_for_backward(u, v, inv_var_x, inv_var_y, opacity, features, order, offsets, slots, alpha)
        ctx.width = width
        return image

    @staticmethod
    def backward(ctx, grad_image):
        grads = require_kernel().rasterize_backward(*ctx.saved_tensors, grad_image, ctx.width)
        return (*grads, None, None, None, None, None, None, None)


def rasterize_cpu(screen: ScreenGaussians, width: int, height: int) -> torch.Tensor:
    """Composite ``screen`` (CPU tensors) into an (height, width, C + 1) image: the feature channels, then alpha."""
    kernel = require_kernel()
    if screen.u.device.type != "cpu":
        raise ValueError(f"render backend 'cpu' needs CPU tensors, got {screen.u.device}")
    boxes = footprint_boxes(screen, width, height)
    order = kernel.depth_order(screen.depth.detach(), boxes.nonempty())  # pairs.depth_order, by a radix sort
    inputs = (screen.u, screen.v, screen.inv_var_x, screen.inv_var_y, screen.opacity, screen.features)
    if torch.is_grad_enabled() and any(t.requires_grad for t in inputs):
        image = _RasterizeCpu.apply(*inputs, order, boxes.x0, boxes.x1, boxes.y0, boxes.y1, width, height)
    else:  # no gradients wanted: no pairs kept for a backward
        image = kernel.rasterize_image(*inputs, order, boxes.x0, boxes.x1, boxes.y0, boxes.y1, width, height)
    return image.reshape(height, width, -1)

