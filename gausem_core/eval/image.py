"""Image metrics on [0, 1] images: PSNR, SSIM (differentiable, also a mapping loss), depth L1, LPIPS.

SSIM follows 3DGS / SplaTAM: 11x11 Gaussian window (sigma 1.5), zero padding, C1 = 0.01^2, C2 = 0.03^2, mean of
the SSIM map over pixels and channels. LPIPS needs a network GauSem does not ship: it runs a ``torch.export``-ed
LPIPS program from a local file (``lpips_weights``) and is reported as ``"not available"`` without one.
"""
from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F

LPIPS_NOT_AVAILABLE = "not available"
_WINDOW_SIZE, _WINDOW_SIGMA = 11, 1.5
_C1, _C2 = 0.01**2, 0.03**2


def _as_bchw(image: torch.Tensor, name: str) -> torch.Tensor:
    """(H, W, C) -> (1, C, H, W); (B, C, H, W) unchanged."""
    if image.ndim == 3:
        return image.permute(2, 0, 1)[None]
    if image.ndim == 4:
        return image
    raise ValueError(f"{name} must be (H, W, C) or (B, C, H, W), got shape {tuple(image.shape)}")


def _check_pair(img1: torch.Tensor, img2: torch.Tensor) -> None:
    if img1.shape != img2.shape:
        raise ValueError(f"images differ in shape: {tuple(img1.shape)} vs {tuple(img2.shape)}")


def gaussian_window(size: int = _WINDOW_SIZE, sigma: float = _WINDOW_SIGMA, dtype=torch.float32,
                    device=None) -> torch.Tensor:
    """Normalised 1-D Gaussian (size,); the 2-D SSIM window is its outer product."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def gaussian_blur(x: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Separable zero-padded Gaussian filter of every channel of (B, C, H, W)."""
    c, k = x.shape[1], window.numel()
    x = F.conv2d(x, window.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, k // 2), groups=c)
    return F.conv2d(x, window.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(k // 2, 0), groups=c)


def ssim_map(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM (B, C, H, W) of (H, W, C) or (B, C, H, W) images in [0, 1]; differentiable.
    Channels are independent, so one call on stacked images costs half of two calls on their halves."""
    _check_pair(img1, img2)
    x, y = _as_bchw(img1, "img1"), _as_bchw(img2, "img2")
    window = gaussian_window(dtype=x.dtype, device=x.device)
    mu_x, mu_y = gaussian_blur(x, window), gaussian_blur(y, window)
    var_x = gaussian_blur(x * x, window) - mu_x**2
    var_y = gaussian_blur(y * y, window) - mu_y**2
    cov = gaussian_blur(x * y, window) - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * cov + _C2)
    den = (mu_x**2 + mu_y**2 + _C1) * (var_x + var_y + _C2)
    return num / den


def ssim(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of (H, W, C) or (B, C, H, W) images in [0, 1]; a differentiable scalar tensor (1 = identical)."""
    return ssim_map(img1, img2).mean()


def psnr(img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR (dB) of (H, W, C) images in [0, 1]: -10 log10(MSE) over all pixels, or over ``mask`` (H, W) pixels.

    Identical images give inf; an empty mask is a ValueError.
    """
    _check_pair(img1, img2)
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
    _check_pair(rendered, target)
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
    _check_pair(img1, img2)
    x, y = (_as_bchw(img, name).float().cpu() * 2 - 1 for img, name in ((img1, "img1"), (img2, "img2")))
    with torch.no_grad():
        return float(_load_lpips(path.resolve())(x, y).mean())


def image_metrics(rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
                  lpips_weights: str | Path | None = None) -> dict[str, float | str]:
    """PSNR (masked if ``mask``), SSIM and LPIPS (``"not available"`` without ``lpips_weights``) of (H, W, 3) images."""
    with torch.no_grad():
        scores: dict[str, float | str] = {"psnr": psnr(rendered, target, mask), "ssim": float(ssim(rendered, target))}
    scores["lpips"] = LPIPS_NOT_AVAILABLE if lpips_weights is None else lpips(rendered, target, lpips_weights)
    return scores
