"""An input frame as the SLAM core consumes it: float tensors on the compute device."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gausem_core.geometry import PinholeCamera

MAX_COLOR = 2.0  # colours the system maps lie in [0, MAX_COLOR]: a frame's colour in [0, 1] divided by the camera's
# vignetting (slam.vignetting, corner brightness down to 1 / MAX_COLOR) exceeds 1 in bright, darkened regions


@dataclass
class Observation:
    """rgb (H,W,3) and semantic colour (H,W,3) in [0,1], depth (H,W) metres (0 = invalid), labels (H,W) class ids."""

    rgb: torch.Tensor
    depth: torch.Tensor
    semantic: torch.Tensor
    labels: torch.Tensor
    camera: PinholeCamera
    timestamp: float = 0.0

    @classmethod
    def from_arrays(cls, rgb: np.ndarray, depth: np.ndarray, labels: np.ndarray, camera: PinholeCamera,
                    palette: torch.Tensor, timestamp: float = 0.0, device=None) -> "Observation":
        """Build from uint8 RGB, metric depth and class ids; the semantic colour is ``palette[labels]``."""
        h, w = depth.shape
        if rgb.shape != (h, w, 3) or labels.shape != (h, w):
            raise ValueError(f"rgb {rgb.shape}, depth {depth.shape} and labels {labels.shape} sizes differ")
        if (camera.width, camera.height) != (w, h):
            raise ValueError(f"camera is {camera.width}x{camera.height} but the images are {w}x{h}")
        labels_t = torch.as_tensor(np.asarray(labels, dtype=np.int64), device=device)
        if labels_t.numel() and (labels_t.min() < 0 or labels_t.max() >= len(palette)):
            raise ValueError(f"labels must lie in [0, {len(palette) - 1}], got [{labels_t.min()}, {labels_t.max()}]")
        depth_t = torch.as_tensor(np.asarray(depth, dtype=np.float32), device=device)
        depth_t = torch.where(torch.isfinite(depth_t) & (depth_t > 0), depth_t, torch.zeros_like(depth_t))
        return cls(rgb=torch.as_tensor(rgb, device=device).float() / 255.0, depth=depth_t,
                   semantic=palette.to(device=device, dtype=torch.float32)[labels_t], labels=labels_t,
                   camera=camera, timestamp=timestamp)

    @property
    def valid_depth(self) -> torch.Tensor:
        return self.depth > 0
