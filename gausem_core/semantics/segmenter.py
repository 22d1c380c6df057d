"""Segmenters: an RGB image (plus, where the data has them, its class ids) -> class-id map (paper §III-A, S in Eq. 2).

Kinds (:func:`make_segmenter`):

- ``labels``: the class ids that arrive with the data (dataset annotations, another robot stack's segmentation
  topic), validated and passed through, optionally through an id remap table.
- ``dinov2``: DINOv2 ViT-S/14 patch tokens + a linear head (``gausem train-head``), logits bilinearly upsampled to
  the image size, argmax.
- ``ade20k``: a pretrained DeepLabV3 + MobileNetV2 on ADE20K (LiteRT), its classes mapped to NYU40
  (:mod:`gausem_core.semantics.ade20k`).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from gausem_core.config import SemanticsConfig
from gausem_core.semantics.ade20k import Ade20kSegmenter
from gausem_core.semantics.backbone import image_batch, load_dinov2
from gausem_core.semantics.base import Segmenter, check_rgb
from gausem_core.semantics.head import load_head


class LabelsSegmenter(Segmenter):
    """Passes through the class ids that arrive with each image.

    remap: optional table, ``remap[source_id]`` = class id, for sources whose ids differ from the class table
    (e.g. raw dataset ids); every source id must be covered.
    """

    def __init__(self, num_classes: int, remap: Sequence[int] | np.ndarray | None = None):
        if num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {num_classes}")
        self.num_classes = int(num_classes)
        self.remap = None
        if remap is not None:
            table = np.asarray(remap)
            if table.ndim != 1 or not table.size or not np.issubdtype(table.dtype, np.integer):
                raise ValueError(f"remap must be a non-empty 1-D integer table, got {table.dtype} {table.shape}")
            if table.min() < 0 or table.max() >= num_classes:
                raise ValueError(f"remap maps to ids in [{table.min()}, {table.max()}], outside 0..{num_classes - 1}")
            self.remap = table.astype(np.int64)

    def segment(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        check_rgb(rgb)
        if labels is None:
            raise ValueError("segmenter 'labels' needs the class ids that come with each image, and this image has "
                             "none; use a dataset or topic that provides labels, or segmenter 'dinov2'")
        labels = np.asarray(labels)
        if labels.shape != rgb.shape[:2]:
            raise ValueError(f"labels shape {labels.shape} differs from the image size {rgb.shape[:2]}")
        if not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"labels must be integer class ids, got dtype {labels.dtype}")
        if not labels.size:
            return labels.astype(np.int64)
        limit = self.num_classes if self.remap is None else len(self.remap)
        low, high = labels.min(), labels.max()
        if low < 0 or high >= limit:
            what = "the remap table's" if self.remap is not None else "the class"
            raise ValueError(f"labels hold ids in [{low}, {high}], outside {what} range 0..{limit - 1}")
        return labels.astype(np.int64) if self.remap is None else self.remap[labels]


class Dinov2Segmenter(Segmenter):
    """DINOv2 patch tokens -> linear head -> bilinear upsampling to the image size -> argmax.

    dinov2_weights: local Hugging Face DINOv2 directory (see :mod:`gausem_core.semantics.backbone`);
    head_weights: head file from ``gausem train-head``; short_side: backbone input short side (rounded to a multiple
    of the patch size), by default the one the head was trained at.
    """

    def __init__(self, dinov2_weights: str | None, head_weights: str | None, short_side: int | None = None,
                 device: torch.device | str = "cpu"):
        self.backbone = load_dinov2(dinov2_weights, device)
        head, info = load_head(head_weights)
        if (info.feature_dim, info.patch_size) != (self.backbone.hidden_size, self.backbone.patch_size):
            raise ValueError(f"head_weights expects {info.feature_dim}-d tokens of {info.patch_size}-px patches, "
                             f"the backbone in dinov2_weights gives {self.backbone.hidden_size}-d tokens of "
                             f"{self.backbone.patch_size}-px patches")
        self.head = head.to(self.backbone.device).eval()
        self.num_classes = info.num_classes
        self.class_names = info.class_names
        self.short_side = info.input_short_side if short_side is None else int(short_side)

    def logits(self, rgb: np.ndarray) -> torch.Tensor:
        """(C, H, W) class scores at the image resolution."""
        check_rgb(rgb)
        with torch.inference_mode():
            _, patches = self.backbone.tokens(image_batch(rgb), self.short_side)
            scores = self.head(patches).permute(0, 3, 1, 2)
            return F.interpolate(scores, size=rgb.shape[:2], mode="bilinear", align_corners=False)[0]

    def segment(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        del labels  # the image alone decides
        return self.logits(rgb).argmax(0).cpu().numpy().astype(np.int64)


_KINDS = {"labels": LabelsSegmenter, "dinov2": Dinov2Segmenter, "ade20k": Ade20kSegmenter}


def make_segmenter(kind: str, **params) -> Segmenter:
    """``make_segmenter("labels", num_classes=C, remap=None)``,
    ``make_segmenter("dinov2", dinov2_weights=DIR, head_weights=FILE, short_side=None, device="cpu")`` or
    ``make_segmenter("ade20k", model=None, threads=1)``."""
    if kind not in _KINDS:
        raise ValueError(f"unknown segmenter kind {kind!r}; expected one of {', '.join(_KINDS)}")
    return _KINDS[kind](**params)


def segmenter_from_config(cfg: SemanticsConfig, device: torch.device | str = "cpu",
                          num_classes: int | None = None) -> Segmenter:
    """The segmenter ``semantics.segmenter`` names: ``dinov2`` from ``semantics.dinov2_weights`` and
    ``semantics.head_weights``, ``ade20k`` from ``semantics.ade20k_model`` on ``semantics.segmenter_threads``
    threads, or ``labels`` for a class table of ``num_classes`` classes."""
    if cfg.segmenter == "dinov2":
        return Dinov2Segmenter(cfg.dinov2_weights or None, cfg.head_weights or None, device=device)
    if cfg.segmenter == "ade20k":
        return Ade20kSegmenter(cfg.ade20k_model or None, cfg.segmenter_threads)
    if cfg.segmenter == "labels":
        if num_classes is None:
            raise ValueError("semantics.segmenter 'labels' needs the class table's size (num_classes)")
        return LabelsSegmenter(num_classes)
    raise ValueError(f"semantics.segmenter must be one of {', '.join(_KINDS)}, got {cfg.segmenter!r}")
