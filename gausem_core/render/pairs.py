"""(Gaussian, pixel) pair lists for the torch back-end: footprint boxes, row bands, per-band sorted pairs.

Nothing here is differentiable: it decides *which* pairs are composited and in which order; the values and their
gradients are computed by :mod:`gausem_core.render.composite`.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.render.projection import ALPHA_MIN, ScreenGaussians


_SAME_SIZE_INTEGER = {torch.float32: torch.int32, torch.float64: torch.int64}


@dataclass
class Boxes:
    """Inclusive integer pixel boxes (clipped to the image) of the footprints of screen Gaussians."""

    x0: torch.Tensor
    x1: torch.Tensor
    y0: torch.Tensor
    y1: torch.Tensor

    def nonempty(self) -> torch.Tensor:
        return (self.x0 <= self.x1) & (self.y0 <= self.y1)


@dataclass
class Band:
    """Image rows ``[row0, row1)`` and the Gaussians (indices into the screen Gaussians, front to back) touching them."""

    row0: int
    row1: int
    gaussians: torch.Tensor


def take(index: torch.Tensor, *tensors: torch.Tensor) -> list[torch.Tensor]:
    """``t[index]`` of 1-D tensors, by one 1-D ``index_select`` each (several times faster on CPU than a gather on a
    stacked (K, M) tensor along dim 1, or advanced indexing)."""
    return [t.index_select(0, index) for t in tensors]


@torch.no_grad()
def footprint_boxes(screen: ScreenGaussians, width: int, height: int) -> Boxes:
    """Pixels whose centre ``(j + 0.5, i + 0.5)`` lies within the footprint ellipse's bounding box (empty for
    Gaussians without a footprint)."""
    rx, ry = screen.footprint_radii()
    u, v = screen.u.detach(), screen.v.detach()

    def span(centre, radius, size):
        lo = torch.ceil(centre - radius - 0.5).clamp(0, size).long()
        hi = torch.floor(centre + radius - 0.5).clamp(-1, size - 1).long()
        return lo, torch.where(radius > 0, hi, lo - 1)  # no footprint (opacity below 1/255): an empty span

    x0, x1 = span(u, rx, width)
    y0, y1 = span(v, ry, height)
    return Boxes(x0, x1, y0, y1)


@torch.no_grad()
def depth_order(screen: ScreenGaussians, boxes: Boxes) -> torch.Tensor:
    """Indices of the Gaussians with a non-empty box, front to back (stable in their index for equal depths).

    Depths are positive (in front of the near plane), so they sort like their IEEE bit patterns read as integers:
    the same order, by torch's integer radix sort (several times faster on CPU than a float comparison sort).
    """
    depth = screen.depth.detach()
    as_integers = _SAME_SIZE_INTEGER.get(depth.dtype)
    order = torch.argsort(depth.view(as_integers) if as_integers else depth, stable=True)
    return order[boxes.nonempty()[order]]


@torch.no_grad()
def plan_bands(screen: ScreenGaussians, boxes: Boxes, height: int, max_pairs_per_band: int) -> list[Band]:
    """Split the rows into bands of about ``max_pairs_per_band`` box pixels and bucket the Gaussians per band once.

    A single row with more pairs than the budget gets a band of its own. Gaussians are listed front to back (stable
    in their index for equal depths), which makes a stable sort by pixel a per-pixel front-to-back order.
    """
    order = depth_order(screen, boxes)
    x0, x1, y0, y1 = (t[order] for t in (boxes.x0, boxes.x1, boxes.y0, boxes.y1))
    width = x1 - x0 + 1
    diff = torch.zeros(height + 1, dtype=torch.long, device=order.device)
    diff.index_add_(0, y0, width).index_add_(0, y1 + 1, -width)
    per_row = diff.cumsum(0)[:height]
    band_of_row = torch.div(per_row.cumsum(0) - per_row, max_pairs_per_band, rounding_mode="floor")
    band_of_row = torch.unique_consecutive(band_of_row, return_inverse=True)[1]
    rows_per_band = torch.bincount(band_of_row).tolist()

    b0, b1 = band_of_row[y0], band_of_row[y1]
    n_bands = b1 - b0 + 1
    member = torch.repeat_interleave(order, n_bands)
    first = torch.repeat_interleave(b0 - (n_bands.cumsum(0) - n_bands), n_bands)
    band = first + torch.arange(member.shape[0], device=order.device)
    band, perm = torch.sort(band, stable=True)
    members = torch.split(member[perm], torch.bincount(band, minlength=len(rows_per_band)).tolist())

    bands, row = [], 0
    for rows, gaussians in zip(rows_per_band, members):
        bands.append(Band(row, row + rows, gaussians))
        row += rows
    return bands


@torch.no_grad()
def band_pairs(screen: ScreenGaussians, boxes: Boxes, band: Band, width: int):
    """Pairs of ``band`` with alpha >= 1/255, sorted by pixel and front to back within a pixel.

    Returns ``(gaussian, pixel, alpha)``: screen-Gaussian index (int64), pixel index within the band
    (``(row - row0) * width + col``, int64) and the unclamped alpha ``opacity * exp(-d^2 / 2 sigma^2)``.
    """
    members = band.gaussians
    x0 = boxes.x0.index_select(0, members)
    y0 = boxes.y0.index_select(0, members).clamp_min(band.row0)
    box_w = boxes.x1.index_select(0, members) - x0 + 1
    count = box_w * (boxes.y1.index_select(0, members).clamp_max(band.row1 - 1) - y0 + 1)
    local = torch.repeat_interleave(torch.arange(members.shape[0], device=members.device), count)
    corner = x0 + (y0 - band.row0) * width  # band-local pixel index of the box's first pixel
    g, corner, box_w, start = take(local, members, corner, box_w, count.cumsum(0) - count)
    offset = torch.arange(local.shape[0], device=g.device) - start
    row_in_box = torch.div(offset, box_w, rounding_mode="floor")
    col_in_box = offset - row_in_box * box_w
    u, v, inv_var_x, inv_var_y, opacity = take(members, *(t.detach() for t in (
        screen.u, screen.v, screen.inv_var_x, screen.inv_var_y, screen.opacity)))
    # per Gaussian: offset of the box's first pixel centre from the centre; then per pair
    x_off, y_off, inv_var_x, inv_var_y, opacity = take(local, x0 + 0.5 - u, y0 + 0.5 - v, inv_var_x, inv_var_y,
                                                       opacity)
    dx = x_off + col_in_box
    dy = y_off + row_in_box
    alpha = opacity * torch.exp(-0.5 * (dx * dx * inv_var_x + dy * dy * inv_var_y))
    pixel = corner + offset + row_in_box * (width - box_w)
    kept = (alpha >= ALPHA_MIN).nonzero().squeeze(1)
    pixel, order = torch.sort(pixel.index_select(0, kept).int(), stable=True)
    g, alpha = take(kept.index_select(0, order), g, alpha)
    return g, pixel.long(), alpha
