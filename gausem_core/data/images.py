"""Image and small text-file IO shared by the readers, with errors that name the offending file."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def require_file(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"missing file {path}")
    return path


def _read(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(require_file(path)), flags)
    if image is None:
        raise ValueError(f"cannot decode image {path} (corrupt or not an image)")
    return image


def read_rgb(path: Path) -> np.ndarray:
    """Colour image -> (H, W, 3) uint8 RGB (8-bit images only)."""
    image = _read(path, cv2.IMREAD_COLOR)
    return np.ascontiguousarray(image[..., ::-1])


def read_uint16(path: Path) -> np.ndarray:
    """Single-channel 16-bit PNG -> (H, W) uint16 (TUM/ScanNet/Replica depth, label maps)."""
    image = _read(path, cv2.IMREAD_UNCHANGED)
    if image.ndim != 2 or image.dtype not in (np.uint16, np.uint8):
        raise ValueError(f"{path}: expected a single-channel 8/16-bit image, got shape {image.shape} {image.dtype}")
    return image.astype(np.uint16, copy=False)


def read_depth(path: Path, scale: float) -> np.ndarray:
    """Depth PNG in units of 1/scale metres -> (H, W) float32 metres (0 stays 0 = invalid)."""
    return read_uint16(path).astype(np.float32) / np.float32(scale)


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise ValueError(f"cannot write image {path}")


def write_uint16(path: Path, image: np.ndarray) -> None:
    if image.min(initial=0) < 0 or image.max(initial=0) > 65535:
        raise ValueError(f"{path}: values outside 0..65535 do not fit a 16-bit PNG")
    if not cv2.imwrite(str(path), image.astype(np.uint16)):
        raise ValueError(f"cannot write image {path}")


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Whitespace-separated numbers (e.g. a 4x4 pose or intrinsic matrix) -> float64 array of ``shape``."""
    try:
        values = np.array(require_file(path).read_text().split(), dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: not a numeric matrix ({exc})") from None
    if values.size != shape[0] * shape[1]:
        raise ValueError(f"{path}: expected {shape[0]}x{shape[1]} numbers, found {values.size}")
    return values.reshape(shape)
