"""Features of SEMANTIC COLOUR images (paper §III-B/C): a global 384-d descriptor per keyframe for loop detection and
SGR pair selection (Algorithm 1, Eq. 5), and a dense patch-feature map for the feature terms of Eq. 6 and L_refine.

``Dinov2Descriptor`` (the paper's method): the DINOv2 ViT-S/14 CLS token of the semantic image, L2-normalised;
dense features are the (un-normalised, post-LayerNorm) patch tokens, differentiable w.r.t. the input image.

``ColourLayoutDescriptor`` (the deterministic fallback when no DINOv2 weights exist):

- global: the image is split into a 2 x 3 grid (rows x columns); each cell gets a 64-bin colour histogram (each RGB
  channel quantised to 4 levels), normalised to the cell's pixel fractions; the 6 x 64 = 384 values are square-rooted
  (Hellinger) and the vector L2-normalised. On a semantic image it is the coarse layout of the classes: where each
  class lies and how much of each cell it covers. What it loses against DINOv2: no learned invariance to viewpoint or
  appearance (a large viewpoint change moves classes between cells and changes the descriptor a lot), no notion of
  object shape or context, and palette colours that quantise to the same bin are merged (e.g. the 41 NYU40 colours
  fall into 20 bins; the 12 synthetic-scene colours stay distinct). Distances are on a different scale than DINOv2's,
  so a loop threshold tuned for one does not transfer to the other.
- dense: random Fourier features of the pixel colours, ``sqrt(2/384) cos(W c + b)`` with a fixed seeded W ~ N(0,
  1/0.2^2), b ~ U(0, 2 pi), averaged over each 14 x 14 patch of the resized image (the same grid as DINOv2). The
  squared distance between two patches' features approximates the MMD (Gaussian kernel, bandwidth 0.2 in RGB) between
  their colour distributions: it compares semantic colours patch by patch, without any learned context.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np
import torch
import torch.nn.functional as F

from gausem_core.semantics.backbone import image_batch, load_dinov2, resize_for_patches

DESCRIPTOR_DIM = 384
PATCH_SIZE = 14


class DescriptorExtractor(ABC):
    """Global descriptor (384,) and dense patch features (h, w, 384) of semantic colour images.

    Images: (H, W, 3) uint8 (0..255) or float (0..1), numpy or torch.
    """

    dim = DESCRIPTOR_DIM

    @abstractmethod
    def describe(self, semantic_rgb) -> np.ndarray:
        """(384,) float32, unit L2 norm."""

    @abstractmethod
    def dense_features(self, semantic_rgb) -> torch.Tensor:
        """(h, w, 384) patch features ((B, h, w, 384) for a (B, H, W, 3) batch), differentiable w.r.t. the image."""


class Dinov2Descriptor(DescriptorExtractor):
    """DINOv2 CLS token (global) and patch tokens (dense) of the semantic image; ``short_side``: backbone input short
    side (rounded to a multiple of 14)."""

    def __init__(self, dinov2_weights: str, short_side: int = 224, device: torch.device | str = "cpu"):
        self.backbone = load_dinov2(dinov2_weights, device)
        if self.backbone.hidden_size != DESCRIPTOR_DIM:
            raise ValueError(f"dinov2_weights gives {self.backbone.hidden_size}-d tokens; descriptors are "
                             f"{DESCRIPTOR_DIM}-d (ViT-S/14)")
        self.short_side = int(short_side)

    def describe(self, semantic_rgb) -> np.ndarray:
        images = image_batch(semantic_rgb)
        if len(images) != 1:
            raise ValueError(f"describe takes one image, got a batch of {len(images)}")
        with torch.inference_mode():
            cls, _ = self.backbone.tokens(images, self.short_side)
            return F.normalize(cls[0].float(), dim=0).cpu().numpy()

    def dense_features(self, semantic_rgb) -> torch.Tensor:
        images = image_batch(semantic_rgb)
        _, patches = self.backbone.tokens(images, self.short_side)
        return patches if semantic_rgb.ndim == 4 else patches[0]


class ColourLayoutDescriptor(DescriptorExtractor):
    """Deterministic, weight-free fallback (see the module docstring for what it is and what it loses)."""

    GRID = (2, 3)
    LEVELS = 4
    BANDWIDTH = 0.2

    def __init__(self, short_side: int = 224):
        self.short_side = int(short_side)
        generator = torch.Generator().manual_seed(0)
        self._frequencies = torch.randn(3, DESCRIPTOR_DIM, generator=generator, dtype=torch.float64) / self.BANDWIDTH
        self._phases = torch.rand(DESCRIPTOR_DIM, generator=generator, dtype=torch.float64) * 2 * math.pi

    def describe(self, semantic_rgb) -> np.ndarray:
        images = image_batch(semantic_rgb)
        if len(images) != 1:
            raise ValueError(f"describe takes one image, got a batch of {len(images)}")
        image = images[0].detach().cpu().double().clamp(0, 1)
        levels = (image * (self.LEVELS - 1)).round().long()
        bins = (levels[..., 0] * self.LEVELS + levels[..., 1]) * self.LEVELS + levels[..., 2]
        height, width = bins.shape
        rows = torch.arange(height) * self.GRID[0] // height
        cols = torch.arange(width) * self.GRID[1] // width
        cells = rows[:, None] * self.GRID[1] + cols[None, :]
        n_bins = self.LEVELS ** 3
        counts = torch.bincount((cells * n_bins + bins).flatten(), minlength=self.GRID[0] * self.GRID[1] * n_bins)
        counts = counts.reshape(-1, n_bins).double()
        fractions = counts / counts.sum(1, keepdim=True).clamp_min(1)
        return F.normalize(fractions.sqrt().flatten(), dim=0).float().numpy()

    def dense_features(self, semantic_rgb) -> torch.Tensor:
        images = image_batch(semantic_rgb)
        pixels = resize_for_patches(images, self.short_side, PATCH_SIZE)  # (B, 3, h, w)
        frequencies = self._frequencies.to(pixels.device, pixels.dtype)
        phases = self._phases.to(pixels.device, pixels.dtype)
        features = math.sqrt(2 / DESCRIPTOR_DIM) * torch.cos(pixels.permute(0, 2, 3, 1) @ frequencies + phases)
        patches = F.avg_pool2d(features.permute(0, 3, 1, 2), PATCH_SIZE).permute(0, 2, 3, 1)
        return patches if semantic_rgb.ndim == 4 else patches[0]


def make_descriptor(kind: str = "auto", dinov2_weights: str | None = None, short_side: int = 224,
                    device: torch.device | str = "cpu") -> DescriptorExtractor:
    """``auto``: DINOv2 when ``dinov2_weights`` is given (a given path that does not exist is an error, never a silent
    fallback), else the colour-layout fallback. ``device`` places the DINOv2 model; the fallback computes wherever
    its input lies."""
    if kind not in ("auto", "dinov2", "fallback"):
        raise ValueError(f"unknown descriptor kind {kind!r}; expected 'auto', 'dinov2' or 'fallback'")
    if kind == "dinov2" or (kind == "auto" and dinov2_weights):
        return Dinov2Descriptor(dinov2_weights, short_side, device)
    return ColourLayoutDescriptor(short_side)
