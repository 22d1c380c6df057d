"""The linear segmentation head on DINOv2 patch tokens: training, and the head file (weights + metadata).

A head file is a ``torch.save`` dict: ``weight`` (C, D), ``bias`` (C,), ``num_classes`` C, ``feature_dim`` D,
``patch_size``, ``input_short_side`` (the backbone input size it was trained at) and ``class_names`` (list or None).
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

_HEAD_FORMAT = "gausem-linear-head-v1"


@dataclass(frozen=True)
class HeadInfo:
    """What a head was trained for: the backbone's token size and patch size, and the input short side."""

    num_classes: int
    feature_dim: int
    patch_size: int
    input_short_side: int
    class_names: tuple[str, ...] | None = None


def save_head(path: str | Path, head: nn.Linear, info: HeadInfo) -> None:
    """Write ``head`` and ``info`` as a head file (format in the module docstring)."""
    if (head.out_features, head.in_features) != (info.num_classes, info.feature_dim):
        raise ValueError(f"head is {head.in_features}->{head.out_features}, info says "
                         f"{info.feature_dim}->{info.num_classes}")
    if info.class_names is not None and len(info.class_names) != info.num_classes:
        raise ValueError(f"{len(info.class_names)} class names for {info.num_classes} classes")
    torch.save({"format": _HEAD_FORMAT, "weight": head.weight.detach().cpu(), "bias": head.bias.detach().cpu(),
                "num_classes": info.num_classes, "feature_dim": info.feature_dim, "patch_size": info.patch_size,
                "input_short_side": info.input_short_side,
                "class_names": None if info.class_names is None else list(info.class_names)}, Path(path))


def load_head(path: str | Path | None) -> tuple[nn.Linear, HeadInfo]:
    """Read a head file; FileNotFoundError names the ``head_weights`` parameter, ValueError a malformed file."""
    hint = "set `semantics.head_weights` to a head file written by `gausem train-head`; no download is attempted"
    if not path:
        raise FileNotFoundError(f"head_weights is not set: {hint}")
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"head_weights: file {path} does not exist: {hint}")
    data = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(data, dict) or data.get("format") != _HEAD_FORMAT:
        raise ValueError(f"head_weights: {path} is not a GauSem linear-head file ({_HEAD_FORMAT})")
    info = HeadInfo(int(data["num_classes"]), int(data["feature_dim"]), int(data["patch_size"]),
                    int(data["input_short_side"]),
                    None if data["class_names"] is None else tuple(data["class_names"]))
    weight, bias = data["weight"], data["bias"]
    if tuple(weight.shape) != (info.num_classes, info.feature_dim) or tuple(bias.shape) != (info.num_classes,):
        raise ValueError(f"head_weights: {path} holds weight {tuple(weight.shape)} / bias {tuple(bias.shape)}, "
                         f"inconsistent with {info.num_classes} classes of {info.feature_dim}-d features")
    head = nn.Linear(info.feature_dim, info.num_classes)
    with torch.no_grad():
        head.weight.copy_(weight)
        head.bias.copy_(bias)
    return head, info


def patch_majority_labels(labels: np.ndarray, grid: tuple[int, int], num_classes: int) -> torch.Tensor:
    """(H, W) class ids -> (h, w) int64: the most frequent class in each cell of an h x w grid over the image."""
    labels = torch.as_tensor(np.asarray(labels), dtype=torch.int64)
    if labels.ndim != 2:
        raise ValueError(f"labels must be (H, W), got shape {tuple(labels.shape)}")
    if labels.numel() and (labels.min() < 0 or labels.max() >= num_classes):
        raise ValueError(f"labels hold ids in [{labels.min()}, {labels.max()}], outside 0..{num_classes - 1}")
    one_hot = F.one_hot(labels, num_classes).permute(2, 0, 1).float()[None]
    return F.adaptive_avg_pool2d(one_hot, grid)[0].argmax(0)


def encode_labelled(encode: Callable[[np.ndarray], torch.Tensor], samples: Iterable[tuple[np.ndarray, np.ndarray]],
                    num_classes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Patch tokens (N, D) and their majority labels (N,) of (rgb (H, W, 3) uint8, labels (H, W)) pairs.

    encode: rgb -> patch tokens (h, w, D) (the frozen backbone). Images are consumed one at a time, so ``samples`` may
    be a lazy generator over a dataset.
    """
    features, targets = [], []
    with torch.no_grad():
        for rgb, label in samples:
            if np.shape(label) != np.shape(rgb)[:2]:
                raise ValueError(f"label map {np.shape(label)} does not match image {np.shape(rgb)}")
            tokens = encode(rgb)
            features.append(tokens.reshape(-1, tokens.shape[-1]).float())
            targets.append(patch_majority_labels(label, tuple(tokens.shape[:2]), num_classes).to(tokens.device))
    if not features:
        raise ValueError("no labelled images to encode")
    return torch.cat(features), torch.cat([t.flatten() for t in targets])


def fit_linear_head(features: torch.Tensor, targets: torch.Tensor, num_classes: int, *, epochs: int = 20,
                    lr: float = 1e-3, batch_size: int = 4096, seed: int = 0) -> tuple[nn.Linear, list[float]]:
    """Cross-entropy fit of a linear layer (D -> num_classes) on tokens (N, D) with labels (N,): Adam over shuffled
    mini-batches. Returns the layer (on the tokens' device) and the mean loss of each epoch."""
    if num_classes < 2 or epochs < 1 or lr <= 0 or batch_size < 1:
        raise ValueError(f"need num_classes >= 2, epochs >= 1, lr > 0, batch_size >= 1; got {num_classes}, "
                         f"{epochs}, {lr}, {batch_size}")
    if features.ndim != 2 or targets.shape != (len(features),):
        raise ValueError(f"need tokens (N, D) and labels (N,), got {tuple(features.shape)} and {tuple(targets.shape)}")
    head = nn.Linear(features.shape[1], num_classes).to(features.device)
    optimizer = torch.optim.Adam(head.parameters(), lr=lr)
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for _ in range(epochs):
        total = 0.0
        for batch in torch.randperm(len(features), generator=generator).split(batch_size):
            batch = batch.to(features.device)
            loss = F.cross_entropy(head(features[batch]), targets[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += loss.item() * len(batch)
        losses.append(total / len(features))
    return head, losses


def train_linear_head(encode: Callable[[np.ndarray], torch.Tensor], images: Sequence[np.ndarray],
                      labels: Sequence[np.ndarray], num_classes: int, *, epochs: int = 20,
                      lr: float = 1e-3) -> tuple[nn.Linear, list[float]]:
    """:func:`encode_labelled` then :func:`fit_linear_head` on in-memory images and label maps."""
    if len(images) != len(labels):
        raise ValueError(f"{len(images)} images but {len(labels)} label maps")
    features, targets = encode_labelled(encode, zip(images, labels), num_classes)
    return fit_linear_head(features, targets, num_classes, epochs=epochs, lr=lr)
