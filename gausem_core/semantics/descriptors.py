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
- dense: on the same patch grid as DINOv2 (input short side rounded to 14-px patches), the image is area-averaged
  to 4 x 4 colour samples per patch; each sample c is mapped to random Fourier features
  ``sqrt(2/384) cos(W c + b)`` with a fixed seeded W ~ N(0, 1/0.2^2), b ~ U(0, 2 pi), and the 16 samples of a patch
  are averaged. The squared distance between two patches' features approximates the MMD (Gaussian kernel, bandwidth
  0.2 in RGB) between their colour distributions: semantic colours compared patch by patch, without learned context.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np
import torch
import torch.nn.functional as F

from gausem_core.semantics.backbone import image_batch, load_dinov2, model_input_size

DESCRIPTOR_DIM = 384
PATCH_SIZE = 14


class DescriptorExtractor(ABC):
    """Global descriptor (384,) and dense patch features (h, w, 384) of semantic colour images.

    Images: (H, W, 3) uint8 (0..255) or float (0..1), numpy or torch.
    """

    dim = DESCRIPTOR_DIM
    kind: str  # "dinov2" or "fallback": distances of different kinds are on different scales

    @abstractmethod
    def describe(self, semantic_rgb) -> np.ndarray:
        """(384,) float32, unit L2 norm."""

    @abstractmethod
    def dense_features(self, semantic_rgb) -> torch.Tensor:
        """(h, w, 384) patch features ((B, h, w, 384) for a (B, H, W, 3) batch), differentiable w.r.t. the image."""


class Dinov2Descriptor(DescriptorExtractor):
    """DINOv2 CLS token (global) and patch tokens (dense) of the semantic image; ``short_side``: backbone input short
    side (rounded to a multiple of 14)."""

    kind = "dinov2"

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

    kind = "fallback"
    GRID = (2, 3)
    LEVELS = 4
    BANDWIDTH = 0.2
    SAMPLES_PER_PATCH = 4  # colour samples per patch side for the dense features

    def __init__(self, short_side: int = 224):
        self.short_side = int(short_side)
        generator = torch.Generator().manual_seed(0)
        self._frequencies = torch.randn(3, DESCRIPTOR_DIM, generator=generator, dtype=torch.float64) / self.BANDWIDTH
        self._phases = torch.rand(DESCRIPTOR_DIM, generator=generator, dtype=torch.float64) * 2 * math.pi

    def describe(self, semantic_rgb) -> np.ndarray:
        images = image_batch(semantic_rgb)
        if len(images) != 1:
            raise ValueError(f"describe takes one image, got a batch of {len(images)}")
        levels = np.rint(np.clip(images[0].detach().cpu().numpy(), 0, 1) * (self.LEVELS - 1)).astype(np.int64)
        bins = levels @ np.array([self.LEVELS ** 2, self.LEVELS, 1])
        height, width = bins.shape
        cells = (np.arange(height) * self.GRID[0] // height)[:, None] * self.GRID[1] + \
            (np.arange(width) * self.GRID[1] // width)[None, :]
        n_bins = self.LEVELS ** 3
        counts = np.bincount((cells * n_bins + bins).ravel(), minlength=self.GRID[0] * self.GRID[1] * n_bins)
        fractions = counts.reshape(-1, n_bins) / np.maximum(counts.reshape(-1, n_bins).sum(1, keepdims=True), 1)
        descriptor = np.sqrt(fractions).ravel()
        return (descriptor / np.linalg.norm(descriptor)).astype(np.float32)

    def dense_features(self, semantic_rgb) -> torch.Tensor:
        images = image_batch(semantic_rgb)
        grid_h, grid_w = (n // PATCH_SIZE for n in model_input_size(images.shape[1], images.shape[2],
                                                                    self.short_side, PATCH_SIZE))
        samples = self.SAMPLES_PER_PATCH
        pixels = F.adaptive_avg_pool2d(images.permute(0, 3, 1, 2), (grid_h * samples, grid_w * samples))
        frequencies = self._frequencies.to(pixels.device, pixels.dtype)
        phases = self._phases.to(pixels.device, pixels.dtype)
        features = math.sqrt(2 / DESCRIPTOR_DIM) * torch.cos(pixels.permute(0, 2, 3, 1) @ frequencies + phases)
        patches = F.avg_pool2d(features.permute(0, 3, 1, 2), samples).permute(0, 2, 3, 1)
        return patches if semantic_rgb.ndim == 4 else patches[0]


def descriptor_kind(kind: str = "auto", dinov2_weights: str | None = None) -> str:
    """The kind of extractor :func:`make_descriptor` builds for these settings, without building it: "dinov2" (asked
    for, or ``auto`` with ``dinov2_weights``) or "fallback"."""
    if kind not in ("auto", "dinov2", "fallback"):
        raise ValueError(f"unknown descriptor kind {kind!r}; expected 'auto', 'dinov2' or 'fallback'")
    return "dinov2" if kind == "dinov2" or (kind == "auto" and dinov2_weights) else "fallback"


def make_descriptor(kind: str = "auto", dinov2_weights: str | None = None, short_side: int = 224,
                    device: torch.device | str = "cpu") -> DescriptorExtractor:
    """``auto``: DINOv2 when ``dinov2_weights`` is given (a given path that does not exist is an error, never a silent
    fallback), else the colour-layout fallback. ``device`` places the DINOv2 model; the fallback computes wherever
    its input lies."""
    if descriptor_kind(kind, dinov2_weights) == "dinov2":
        return Dinov2Descriptor(dinov2_weights, short_side, device)
    return ColourLayoutDescriptor(short_side)
