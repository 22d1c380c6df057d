"""What a front end (the offline pipeline, a ROS node) derives from the configuration before its first frame."""
from __future__ import annotations

import torch

from gausem_core.config import SlamConfig


def resolve_device(name: str) -> torch.device:
    """The torch device of the ``device`` parameter: ``auto`` is CUDA when present, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available (set device: auto or cpu)")
    return torch.device(name)


def smallest_image_side(cfg: SlamConfig) -> int:
    """The smallest image side the image pyramids can take (each level halves it and must keep a pixel): tracking's,
    and loop registration's at the keyframe resolution divided by ``loop.registration.downsample``."""
    reg = cfg.loop.registration
    return max(2 ** (cfg.tracking.gauss_newton.pyramid_levels - 1), reg.downsample * 2 ** (reg.pyramid_levels - 1))
