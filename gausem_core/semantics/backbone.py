"""The DINOv2 backbone: offline loading from a local directory, image preprocessing, CLS and patch tokens.

Accepted weights: a Hugging Face ``Dinov2Model`` directory (``config.json`` + ``model.safetensors`` or
``pytorch_model.bin``, or their sharded ``*.index.json`` form), e.g. a snapshot of ``facebook/dinov2-small``
(ViT-S/14, 384-d tokens). The original facebookresearch ``.pth`` checkpoints are not read. Nothing is ever downloaded.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json",
                 "pytorch_model.bin.index.json")


def image_batch(image) -> torch.Tensor:
    """(H, W, 3) or (B, H, W, 3) image, uint8 (0..255) or float (0..1), numpy or torch -> (B, H, W, 3) float tensor.

    Float tensors keep their dtype, device and autograd graph; everything else becomes float32.
    """
    if isinstance(image, np.ndarray):
        image = torch.from_numpy(np.ascontiguousarray(image))
    if not isinstance(image, torch.Tensor):
        raise ValueError(f"expected an image array or tensor, got {type(image).__name__}")
    if image.ndim not in (3, 4) or image.shape[-1] != 3 or min(image.shape[-3:-1]) < 1:
        raise ValueError(f"expected an (H, W, 3) or (B, H, W, 3) image, got shape {tuple(image.shape)}")
    if image.dtype == torch.uint8:
        image = image.float() / 255.0
    elif not image.is_floating_point():
        raise ValueError(f"expected a uint8 or float image, got dtype {image.dtype}")
    return image if image.ndim == 4 else image[None]


def model_input_size(height: int, width: int, short_side: int, patch_size: int) -> tuple[int, int]:
    """(height, width) of the network input: the short side becomes ``short_side`` rounded to a multiple of the
    patch size, the long side keeps the aspect ratio, rounded to a multiple of the patch size (at least one patch)."""
    if short_side < patch_size:
        raise ValueError(f"short_side {short_side} is smaller than the patch size {patch_size}")
    short = round(short_side / patch_size) * patch_size
    scale = short / min(height, width)
    return (max(patch_size, round(height * scale / patch_size) * patch_size),
            max(patch_size, round(width * scale / patch_size) * patch_size))


def resize_for_patches(images: torch.Tensor, short_side: int, patch_size: int) -> torch.Tensor:
    """(B, H, W, 3) in [0, 1] -> (B, 3, h, w) bilinearly resized to :func:`model_input_size` (differentiable)."""
    size = model_input_size(images.shape[1], images.shape[2], short_side, patch_size)
    pixels = images.permute(0, 3, 1, 2)
    if tuple(pixels.shape[-2:]) == size:
        return pixels
    return F.interpolate(pixels, size=size, mode="bilinear", align_corners=False, antialias=True)


class Dinov2Backbone:
    """A frozen ``transformers.Dinov2Model``: images -> CLS token and the patch-token grid."""

    def __init__(self, model):
        self.model = model.eval().requires_grad_(False)
        self.hidden_size = int(model.config.hidden_size)
        self.patch_size = int(model.config.patch_size)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def tokens(self, images: torch.Tensor, short_side: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, H, W, 3) float in [0, 1] -> CLS (B, D) and patch tokens (B, h, w, D), both after the final LayerNorm.

        Differentiable w.r.t. ``images`` unless called under ``torch.no_grad`` / ``torch.inference_mode``.
        """
        pixels = resize_for_patches(images.to(self.device, torch.float32), short_side, self.patch_size)
        mean = pixels.new_tensor(IMAGENET_MEAN)[:, None, None]
        std = pixels.new_tensor(IMAGENET_STD)[:, None, None]
        hidden = self.model(pixel_values=(pixels - mean) / std).last_hidden_state
        grid_h, grid_w = pixels.shape[2] // self.patch_size, pixels.shape[3] // self.patch_size
        return hidden[:, 0], hidden[:, 1:].reshape(len(hidden), grid_h, grid_w, self.hidden_size)


def check_dinov2_dir(path: str | Path | None) -> Path:
    """The weights directory, or FileNotFoundError telling the user what ``dinov2_weights`` must point to."""
    hint = ("set `semantics.dinov2_weights` (gausem train-head: --dinov2-weights) to a local directory holding a "
            "Hugging Face DINOv2 checkpoint (config.json + model.safetensors or pytorch_model.bin, e.g. a snapshot of "
            "facebook/dinov2-small); no download is attempted")
    if not path:
        raise FileNotFoundError(f"dinov2_weights is not set: {hint}")
    directory = Path(path).expanduser()
    if not directory.is_dir():
        raise FileNotFoundError(f"dinov2_weights: directory {directory} does not exist: {hint}")
    if not (directory / "config.json").is_file() or not any((directory / f).is_file() for f in _WEIGHT_FILES):
        raise FileNotFoundError(f"dinov2_weights: {directory} lacks config.json or a weights file "
                                f"({', '.join(_WEIGHT_FILES)}): {hint}")
    return directory.resolve()


def load_dinov2(path: str | Path | None, device: torch.device | str = "cpu") -> Dinov2Backbone:
    """Load (once per process, per directory and device) the DINOv2 backbone from a local directory, offline."""
    return _load_cached(str(check_dinov2_dir(path)), str(torch.device(device)))


@functools.lru_cache(maxsize=4)
def _load_cached(directory: str, device: str) -> Dinov2Backbone:
    from transformers import Dinov2Model

    model, info = Dinov2Model.from_pretrained(directory, local_files_only=True, output_loading_info=True)
    if info["missing_keys"] or info["mismatched_keys"]:
        raise ValueError(f"dinov2_weights: {directory} is not a complete Dinov2Model checkpoint "
                         f"(missing: {sorted(info['missing_keys'])[:5]}, "
                         f"mismatched: {sorted(info['mismatched_keys'])[:5]})")
    return Dinov2Backbone(model.to(device))
