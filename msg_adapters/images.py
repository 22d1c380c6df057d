"""sensor_msgs/Image <-> numpy.

Reading respects ``step`` (row padding) and ``is_bigendian`` and returns views of ``msg.data`` where the layout
allows (no copy; writing to them writes the message). Building uses ``ndarray.tobytes()``: assigning an ndarray to
``msg.data`` costs ~100 ms per VGA frame in rclpy (docs/DESIGN.md §4). Built images are little-endian and
unpadded. Conventions: colour is RGB uint8 (H, W, 3); depth is float32 metres (H, W) with 0 = invalid (16UC1 holds
millimetres, 32FC1 metres); labels are class ids (H, W).
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

# encoding -> (dtype, channels)
ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3), "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4), "bgra8": (np.dtype(np.uint8), 4),
    "mono8": (np.dtype(np.uint8), 1), "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1), "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
}
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
LABEL_ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1")
_MAX_DEPTH_MM = np.iinfo(np.uint16).max
MAX_DEPTH_M = 1e4  # 32FC1 readings beyond are corrupt data, not distances (near 1e38 the renderer's float32 overflows)


class ImageEncodingError(ValueError):
    """An image encoding that the called conversion does not support."""

    def __init__(self, encoding: str, supported, what: str = "image"):
        super().__init__(f"unsupported {what} encoding {encoding!r}; supported: {', '.join(supported)}")
        self.encoding = encoding


def _require(encoding: str, supported, what: str) -> None:
    if encoding not in supported:
        raise ImageEncodingError(encoding, supported, what)


def image_to_numpy(msg: Image) -> np.ndarray:
    """The raw pixels: (H, W) for one channel, else (H, W, C), in the encoding's dtype and channel order."""
    _require(msg.encoding, ENCODINGS, "image")
    dtype, channels = ENCODINGS[msg.encoding]
    h, w, step = msg.height, msg.width, msg.step
    row_bytes = w * channels * dtype.itemsize
    if step < row_bytes:
        raise ValueError(f"{msg.encoding} image {w}x{h}: step {step} is shorter than a row ({row_bytes} bytes)")
    if len(msg.data) != h * step:
        raise ValueError(f"{msg.encoding} image {w}x{h}: data holds {len(msg.data)} bytes, "
                         f"expected height*step = {h}*{step} = {h * step}")
    rows = np.frombuffer(msg.data, np.uint8).reshape(h, step)[:, :row_bytes]
    wire = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    pixels = rows.view(wire) if step == row_bytes or dtype.itemsize == 1 else rows.copy().view(wire)
    if wire != dtype.newbyteorder("="):
        pixels = pixels.astype(dtype.newbyteorder("="))
    return pixels.reshape((h, w) if channels == 1 else (h, w, channels))


def numpy_to_image(pixels: np.ndarray, encoding: str, header: Header) -> Image:
    """Pixels (H, W) or (H, W, C) matching ``encoding`` -> a little-endian, unpadded Image."""
    _require(encoding, ENCODINGS, "image")
    dtype, channels = ENCODINGS[encoding]
    pixels = np.asarray(pixels)
    shape_ok = pixels.ndim == 2 if channels == 1 else (pixels.ndim == 3 and pixels.shape[2] == channels)
    if not shape_ok or pixels.dtype != dtype:
        want = "(H, W)" if channels == 1 else f"(H, W, {channels})"
        raise ValueError(f"{encoding} needs a {dtype} array of shape {want}, got {pixels.dtype} {pixels.shape}")
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels, dtype=dtype.newbyteorder("<")).tobytes()
    return Image(header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                 step=w * channels * dtype.itemsize, data=data)


def image_to_rgb(msg: Image) -> np.ndarray:
    """Colour image -> C-contiguous RGB uint8 (H, W, 3) (BGR reordered, alpha dropped): a reordered view would have
    negative strides, which torch cannot take."""
    _require(msg.encoding, COLOR_ENCODINGS, "colour image")
    pixels = image_to_numpy(msg)
    return np.ascontiguousarray(pixels[..., 2::-1] if msg.encoding.startswith("bgr") else pixels[..., :3])


def rgb_to_image(rgb: np.ndarray, header: Header, encoding: str = "rgb8") -> Image:
    """RGB uint8 (H, W, 3) -> rgb8 or bgr8 Image."""
    _require(encoding, ("rgb8", "bgr8"), "colour output")
    rgb = np.asarray(rgb)
    return numpy_to_image(rgb[..., ::-1] if encoding == "bgr8" and rgb.ndim == 3 else rgb, encoding, header)


def image_to_depth(msg: Image) -> np.ndarray:
    """Depth image -> float32 metres (H, W); 0 marks invalid (0 mm; NaN, inf, negative or beyond ``MAX_DEPTH_M``
    metres)."""
    _require(msg.encoding, DEPTH_ENCODINGS, "depth image")
    raw = image_to_numpy(msg)
    if msg.encoding == "16UC1":
        return raw.astype(np.float32) * np.float32(1e-3)
    valid = np.isfinite(raw) & (raw > 0) & (raw <= MAX_DEPTH_M)
    return np.where(valid, raw, np.float32(0)).astype(np.float32, copy=False)


def depth_to_image(depth: np.ndarray, header: Header, encoding: str = "32FC1") -> Image:
    """Depth in metres (H, W) (0, NaN or negative = invalid) -> 32FC1 (metres) or 16UC1 (rounded millimetres)."""
    _require(encoding, DEPTH_ENCODINGS, "depth output")
    depth = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    if encoding == "32FC1":
        return numpy_to_image(np.where(valid, depth, np.float32(0)), encoding, header)
    mm = np.where(valid, np.rint(np.where(valid, depth, 0) * 1000.0), 0)
    if mm.max(initial=0) > _MAX_DEPTH_MM:
        raise ValueError(f"depth {float(depth[valid].max()):.3f} m exceeds the 16UC1 range (65.535 m)")
    return numpy_to_image(mm.astype(np.uint16), encoding, header)


def image_to_labels(msg: Image) -> np.ndarray:
    """Label image (class ids) -> int64 (H, W)."""
    _require(msg.encoding, LABEL_ENCODINGS, "label image")
    return image_to_numpy(msg).astype(np.int64)


def labels_to_image(labels: np.ndarray, header: Header, encoding: str = "mono16") -> Image:
    """Class ids (H, W) -> mono8 or mono16 Image; ids outside the encoding's range are an error."""
    _require(encoding, ("mono8", "mono16"), "label output")
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise ValueError(f"labels must be integers, got {labels.dtype}")
    dtype = ENCODINGS[encoding][0]
    info = np.iinfo(dtype)
    if labels.size and (labels.min() < info.min or labels.max() > info.max):
        raise ValueError(f"labels span [{labels.min()}, {labels.max()}], outside {encoding}'s {info.min}..{info.max}")
    return numpy_to_image(labels.astype(dtype), encoding, header)
