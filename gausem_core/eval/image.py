"""Image metrics on [0, 1] images: PSNR, SSIM (:mod:`gausem_core.image_ops`), depth L1, LPIPS.

LPIPS needs a network GauSem does not ship: it runs a ``torch.export``-ed LPIPS program from a local file
(``lpips_weights``) and is reported as ``"not available"`` without one.
"""
from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import torch

from gausem_core.image_ops import as_bchw, check_pair, ssim

LPIPS_NOT_AVAILABLE = "not available"


def psnr(img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR (dB) of (H, W, C) images in [0, 1]: -10 log10(MSE) over all pixels, or over ``mask`` (H, W) pixels.

    Identical images give inf; an empty mask is a ValueError.
    """
    check_pair(img1, img2)
    if img1.ndim != 3:
        raise ValueError(f"psnr takes (H, W, C) images, got shape {tuple(img1.shape)}")
    sq = (img1.detach().double() - img2.detach().double()) ** 2
    if mask is not None:
        if tuple(mask.shape) != tuple(img1.shape[:2]):
            raise ValueError(f"psnr: mask shape {tuple(mask.shape)} differs from image size {tuple(img1.shape[:2])}")
        if not mask.any():
            raise ValueError("psnr: the mask selects no pixels")
        sq = sq[mask.bool()]
    mse = float(sq.mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def depth_l1(rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean |rendered - target| (metres) over pixels with a valid target depth (> 0), within ``mask`` if given."""
    check_pair(rendered, target)
    valid = target > 0
    if mask is not None:
        if mask.shape != target.shape:
            raise ValueError(f"depth_l1: mask shape {tuple(mask.shape)} differs from depth shape {tuple(target.shape)}")
        valid = valid & mask.bool()
    if not valid.any():
        raise ValueError("depth_l1: no pixel has a valid target depth")
    return float((rendered.detach().double() - target.detach().double()).abs()[valid].mean())


@lru_cache(maxsize=2)
def _load_lpips(path: Path) -> torch.nn.Module:
    return torch.export.load(str(path)).module()


def lpips(img1: torch.Tensor, img2: torch.Tensor, lpips_weights: str | Path | None) -> float:
    """LPIPS of (H, W, 3) images in [0, 1] with a local ``torch.export``-ed LPIPS program.

    ``lpips_weights`` is a ``.pt2`` file saved with ``torch.export.save`` from an LPIPS network (e.g. the ``lpips``
    package's VGG or Alex model) taking two (B, 3, H, W) images in [-1, 1] with dynamic H and W. GauSem does not ship
    the network (it would need torchvision); without the file this raises FileNotFoundError.
    """
    path = Path(lpips_weights) if lpips_weights is not None else None
    if path is None or not path.is_file():
        raise FileNotFoundError(f"LPIPS needs a local exported LPIPS program: lpips_weights={lpips_weights!r} "
                                "is not a file (report LPIPS as not available instead)")
    check_pair(img1, img2)
    x, y = (as_bchw(img, name).float().cpu() * 2 - 1 for img, name in ((img1, "img1"), (img2, "img2")))
    with torch.no_grad():
        return float(_load_lpips(path.resolve())(x, y).mean())


def image_metrics(rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
                  lpips_weights: str | Path | None = None) -> dict[str, float | str]:
    """PSNR (masked if ``mask``), SSIM and LPIPS (``"not available"`` without ``lpips_weights``) of (H, W, 3) images."""
    with torch.no_grad():
        scores: dict[str, float | str] = {"psnr": psnr(rendered, target, mask), "ssim": float(ssim(rendered, target))}
    scores["lpips"] = LPIPS_NOT_AVAILABLE if lpips_weights is None else lpips(rendered, target, lpips_weights)
    return scores
