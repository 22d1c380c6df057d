"""Exact front-to-back alpha compositing of sorted (Gaussian, pixel) pairs, with a hand-written backward.

For the pairs ``i = 1..n`` of one pixel, front to back: ``alpha_i = min(0.99, o_i exp(-q_i / 2))`` with
``q_i = dx^2 / sigma_x^2 + dy^2 / sigma_y^2``, ``T_i = prod_{j<i} (1 - alpha_j)``, ``w_i = alpha_i T_i``; the pixel
gets ``sum_i w_i f_i`` for every feature channel and ``sum_i w_i`` as its alpha. The per-pixel (segmented) exclusive
product is an exclusive cumulative sum of ``log(1 - alpha)`` in float64 minus its value at the segment start.

The backward needs, per pair, ``dL/dalpha_i = T_i h_i - S_i / (1 - alpha_i)`` with ``h_i = f_i . G + G_alpha`` and
``S_i = sum_{k>i} w_k h_k`` (a segmented suffix sum, again a float64 cumulative sum). Only the pair indices, the
unclamped alphas and the transmittances are saved (24 bytes a pair in float32), not an autograd graph over pairs.
"""
from __future__ import annotations

import torch

from gausem_core.render.pairs import take
from gausem_core.render.projection import ALPHA_MAX


def _segments(pixel: torch.Tensor, n_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For pairs sorted by pixel: the index of each pair's first and last pair in its pixel."""
    ends = torch.bincount(pixel, minlength=n_pixels).cumsum(0)
    starts = torch.cat([ends.new_zeros(1), ends[:-1]])
    first, last = take(pixel, starts, ends)
    return first, last - 1


def _scatter_rows(rows: list[torch.Tensor], index: torch.Tensor, size: int) -> torch.Tensor:
    """K rows of P values summed into (K, size) by ``index`` (one 1-D index_add each: much faster on CPU than 2-D)."""
    out = rows[0].new_zeros(len(rows), size)
    for target, source in zip(out, rows):
        target.index_add_(0, index, source)
    return out


def _with_ones(features: torch.Tensor) -> torch.Tensor:
    """(M, C) features -> (C + 1, M) channel-major, with a row of ones (the alpha channel)."""
    return torch.cat([features, features.new_ones(features.shape[0], 1)], 1).T.contiguous()


class CompositeBand(torch.autograd.Function):
    """Composite one band of pixels. Inputs are per screen Gaussian (M rows) except the pair tensors.

    ``apply(u, v, inv_var_x, inv_var_y, opacity, features, gaussian, pixel, alpha, row0, width, n_pixels)`` ->
    ``(C + 1, n_pixels)``: the composited feature channels and, last, the alpha. ``gaussian``/``pixel``/``alpha``
    come from :func:`gausem_core.render.pairs.band_pairs` (sorted by pixel, front to back; unclamped alpha).
    """

    @staticmethod
    def forward(ctx, u, v, inv_var_x, inv_var_y, opacity, features, gaussian, pixel, alpha, row0, width, n_pixels):
        clamped = alpha.clamp_max(ALPHA_MAX)
        log_keep = torch.log1p(-clamped).double()
        first, _ = _segments(pixel, n_pixels)
        exclusive = log_keep.cumsum(0) - log_keep
        transmittance = (exclusive - exclusive.index_select(0, first)).to(alpha.dtype).exp()
        weight = clamped * transmittance
        out = _scatter_rows([row * weight for row in take(gaussian, *_with_ones(features))], pixel, n_pixels)
        ctx.save_for_backward(u, v, inv_var_x, inv_var_y, opacity, features, gaussian, pixel, alpha, transmittance)
        ctx.geometry = (row0, width, n_pixels)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        u, v, inv_var_x, inv_var_y, opacity, features, gaussian, pixel, alpha, transmittance = ctx.saved_tensors
        row0, width, n_pixels = ctx.geometry
        _, last = _segments(pixel, n_pixels)
        clamped = alpha.clamp_max(ALPHA_MAX)
        weight = clamped * transmittance
        grad_pair = take(pixel, *grad_out)  # C + 1 rows of P
        h = sum(f * g for f, g in zip(take(gaussian, *_with_ones(features)), grad_pair))
        inclusive = (weight * h).double().cumsum(0)
        behind = (inclusive.index_select(0, last) - inclusive).to(alpha.dtype)
        grad_alpha = transmittance * h - behind / (1.0 - clamped)
        grad_alpha = torch.where(alpha > ALPHA_MAX, 0.0, grad_alpha)  # clamped: no gradient
        # alpha = o exp(-q / 2), q = dx^2 a + dy^2 b, dx = col + 0.5 - u, dy = row + 0.5 - v
        u, v, inv_var_x, inv_var_y, opacity = take(gaussian, u, v, inv_var_x, inv_var_y, opacity)
        dx = (pixel % width) + 0.5 - u
        dy = torch.div(pixel, width, rounding_mode="floor") + (row0 + 0.5) - v
        g_q = grad_alpha * alpha  # dL/d(-q/2)
        rows = [g_q * inv_var_x * dx, g_q * inv_var_y * dy, -0.5 * g_q * dx * dx, -0.5 * g_q * dy * dy, g_q / opacity]
        grads = _scatter_rows(rows + [g * weight for g in grad_pair[:-1]], gaussian, features.shape[0])
        g_u, g_v, g_a, g_b, g_o = grads[:5]
        return g_u, g_v, g_a, g_b, g_o, grads[5:].T, None, None, None, None, None, None
