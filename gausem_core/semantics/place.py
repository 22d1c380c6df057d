"""A learned global place descriptor of an RGB image: EfficientNet-Lite0's head features (ImageNet weights,
:mod:`gausem_core.semantics.efficientnet_lite`), generalised-mean pooled (GeM, p = 3: the strong activations count
most, as in image retrieval), L2-normalised; two views of one place lie close (L2 distance in [0, 2])."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from gausem_core.semantics.efficientnet_lite import image_tensor, load_efficientnet_lite0

GEM_POWER = 3.0


class LearnedPlaceDescriptor:
    """``describe(rgb)`` -> (1280,) float32 unit vector; ``weights``: the .pth file (default: the installed
    package's); ``short_side``: the image is resized to this short side first (the network saw 224)."""

    def __init__(self, weights: str | None = None, short_side: int = 224):
        self.model = load_efficientnet_lite0(weights)
        self.short_side = int(short_side)

    def describe(self, rgb) -> np.ndarray:
        rgb = np.asarray(rgb)
        h, w = rgb.shape[:2]
        scale = self.short_side / min(h, w)
        resized = cv2.resize(rgb, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
        with torch.inference_mode():
            features = self.model.features(image_tensor(resized))[0]
        pooled = features.clamp_min(1e-6).pow(GEM_POWER).mean((1, 2)).pow(1.0 / GEM_POWER)
        return torch.nn.functional.normalize(pooled, dim=0).numpy().astype(np.float32)
