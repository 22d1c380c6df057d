"""Image operations shared by training and evaluation: SSIM (differentiable, a mapping loss and a metric).

SSIM follows 3DGS / SplaTAM: 11x11 Gaussian window (sigma 1.5), zero padding, C1 = 0.01^2, C2 = 0.03^2, mean of
the SSIM map over pixels and channels.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

_WINDOW_SIZE, _WINDOW_SIGMA = 11, 1.5
_C1, _C2 = 0.01**2, 0.03**2


def as_bchw(image: torch.Tensor, name: str) -> torch.Tensor:
    """(H, W, C) -> (1, C, H, W); (B, C, H, W) unchanged."""
    if image.ndim == 3:
        return image.permute(2, 0, 1)[None]
    if image.ndim == 4:
        return image
    raise ValueError(f"{name} must be (H, W, C) or (B, C, H, W), got shape {tuple(image.shape)}")


def check_pair(img1: torch.Tensor, img2: torch.Tensor) -> None:
    """ValueError unless the two images have the same shape."""
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
    check_pair(img1, img2)
    x, y = as_bchw(img1, "img1"), as_bchw(img2, "img2")
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
