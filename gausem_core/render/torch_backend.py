"""The pure-torch reference rasteriser (CPU and CUDA): exact, memory-bounded by row bands."""
from __future__ import annotations

import torch

from gausem_core.render.composite import CompositeBand
from gausem_core.render.pairs import band_pairs, footprint_boxes, plan_bands
from gausem_core.render.projection import ScreenGaussians

DEFAULT_PAIRS_PER_BAND = 1 << 21  # ~2 M box pixels per band: a few hundred MB of temporaries at most


def rasterize_torch(screen: ScreenGaussians, width: int, height: int,
                    max_pairs_per_band: int = DEFAULT_PAIRS_PER_BAND) -> torch.Tensor:
    """Composite ``screen`` into an (height, width, C + 1) image: the feature channels, then alpha."""
    if max_pairs_per_band < 1:
        raise ValueError(f"max_pairs_per_band must be positive, got {max_pairs_per_band}")
    boxes = footprint_boxes(screen, width, height)
    tensors = (screen.u, screen.v, screen.inv_var_x, screen.inv_var_y, screen.opacity, screen.features)
    rows = []
    for band in plan_bands(screen, boxes, height, max_pairs_per_band):
        gaussian, pixel, alpha = band_pairs(screen, boxes, band, width)
        n_pixels = (band.row1 - band.row0) * width
        rows.append(CompositeBand.apply(*tensors, gaussian, pixel, alpha, band.row0, width, n_pixels))
    return torch.cat(rows, 1).T.reshape(height, width, -1)
