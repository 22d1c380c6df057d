"""What every segmenter is: an RGB image (plus, where the data has them, its class ids) -> class-id map."""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class Segmenter(ABC):
    """Produces (H, W) int64 class ids in ``0..num_classes-1`` for an (H, W, 3) uint8 RGB image; ``class_names``:
    their names where the segmenter knows them."""

    num_classes: int
    class_names: tuple[str, ...] | None = None

    @abstractmethod
    def segment(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        """Class ids for ``rgb``; ``labels`` are the ids that came with the image (used by ``labels`` only)."""


def check_rgb(rgb: np.ndarray) -> None:
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 array, got {getattr(rgb, 'shape', type(rgb).__name__)} "
                         f"{getattr(rgb, 'dtype', '')}")
