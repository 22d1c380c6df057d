"""PNG montage for humans: one row per frame, input | rendered colour | rendered semantics | depth-error heat map.

Layout: a title strip of ``HEADER_HEIGHT`` pixels, then one row of four W x H panels per frame, and on the right a
colour bar ``COLORBAR_WIDTH`` pixels wide labelled in metres. Depth error is |rendered - ground truth| on pixels with
ground-truth depth, black elsewhere, on one scale for all rows.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

HEADER_HEIGHT = 24
COLORBAR_WIDTH = 72
_TITLES = ("input", "rendered", "semantics", "abs depth error")
_FONT, _FONT_SCALE = cv2.FONT_HERSHEY_SIMPLEX, 0.45
_COLORMAP = cv2.COLORMAP_INFERNO


def _numpy(a) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def _rgb8(image, name: str) -> np.ndarray:
    """(H, W, 3) float in [0, 1] or uint8 -> uint8."""
    image = _numpy(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"montage: {name} must be (H, W, 3), got shape {image.shape}")
    if image.dtype == np.uint8:
        return image
    return (np.clip(image.astype(np.float64), 0, 1) * 255 + 0.5).astype(np.uint8)


@dataclass
class MontageRow:
    """One frame: images (H, W, 3) float in [0, 1] or uint8; depths (H, W) in metres (ground truth 0 = none)."""

    input_rgb: np.ndarray | torch.Tensor
    rendered_rgb: np.ndarray | torch.Tensor
    rendered_semantic: np.ndarray | torch.Tensor
    rendered_depth: np.ndarray | torch.Tensor
    gt_depth: np.ndarray | torch.Tensor
    label: str = ""

    def depth_error(self) -> np.ndarray:
        """(H, W) |rendered - ground truth| depth, NaN where the ground truth has no depth."""
        rendered, gt = _numpy(self.rendered_depth).astype(np.float64), _numpy(self.gt_depth).astype(np.float64)
        if rendered.shape != gt.shape or rendered.ndim != 2:
            raise ValueError(f"montage: depths must be (H, W) of one size, got {rendered.shape} and {gt.shape}")
        return np.where(gt > 0, np.abs(rendered - gt), np.nan)


def _heat(values: np.ndarray, vmax: float) -> np.ndarray:
    """(H, W) values in [0, vmax] (NaN = none) -> RGB uint8 heat map, black for NaN."""
    scaled = (np.clip(np.nan_to_num(values, nan=0.0) / vmax, 0, 1) * 255 + 0.5).astype(np.uint8)
    heat = cv2.cvtColor(cv2.applyColorMap(scaled, _COLORMAP), cv2.COLOR_BGR2RGB)
    heat[np.isnan(values)] = 0
    return heat


def _text(image: np.ndarray, text: str, x: int, y: int) -> None:
    cv2.putText(image, text, (x, y), _FONT, _FONT_SCALE, (255, 255, 255), 1, cv2.LINE_AA)


def _colorbar(height: int, vmax: float) -> np.ndarray:
    bar = np.zeros((height, COLORBAR_WIDTH, 3), np.uint8)
    top, bottom = HEADER_HEIGHT + 8, height - 8
    ramp = np.linspace(vmax, 0, max(bottom - top, 1))[:, None].repeat(14, 1)
    bar[top:bottom, 6:20] = _heat(ramp, vmax)
    _text(bar, f"{vmax:.3g} m", 23, top + 10)
    _text(bar, "0 m", 23, bottom)
    return bar


def render_montage(rows: Sequence[MontageRow], max_depth_error: float | None = None) -> np.ndarray:
    """The montage as an RGB uint8 image of (HEADER_HEIGHT + rows * H) x (4 W + COLORBAR_WIDTH) pixels.

    max_depth_error: top of the colour scale (m); default the 99th percentile of all valid depth errors.
    """
    if not rows:
        raise ValueError("montage: no rows")
    errors = [row.depth_error() for row in rows]
    if max_depth_error is None:
        valid = np.concatenate([e[np.isfinite(e)] for e in errors])
        max_depth_error = float(np.percentile(valid, 99)) if valid.size else 1.0
    vmax = max(max_depth_error, 1e-6)
    grid = [[_rgb8(row.input_rgb, "input_rgb"), _rgb8(row.rendered_rgb, "rendered_rgb"),
             _rgb8(row.rendered_semantic, "rendered_semantic"), _heat(error, vmax)] for row, error in zip(rows, errors)]
    sizes = {image.shape[:2] for images in grid for image in images}
    if len(sizes) != 1:
        raise ValueError(f"montage: panels of several sizes {sorted(sizes)}; all images must share one size")
    panels = [np.concatenate(images, axis=1) for images in grid]
    for row, panel in zip(rows, panels):
        if row.label:
            _text(panel, row.label, 4, 14)
    body = np.concatenate(panels, axis=0)
    header = np.zeros((HEADER_HEIGHT, body.shape[1], 3), np.uint8)
    width = body.shape[1] // 4
    for k, title in enumerate(_TITLES):
        _text(header, title, k * width + 4, HEADER_HEIGHT - 8)
    image = np.concatenate([header, body], axis=0)
    return np.concatenate([image, _colorbar(image.shape[0], vmax)], axis=1)


def write_montage(path: str | Path, rows: Sequence[MontageRow], max_depth_error: float | None = None) -> np.ndarray:
    """Render the montage (see :func:`render_montage`), write it as PNG and return it (RGB uint8)."""
    image = render_montage(rows, max_depth_error)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write the montage to {path}")
    return image
