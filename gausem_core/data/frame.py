"""One RGB-D frame, and the base class every dataset reader shares (indexing, stride, frame limit, resizing)."""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gausem_core.data.classes import ClassTable
from gausem_core.geometry import PinholeCamera


@dataclass
class Frame:
    """An RGB-D frame. Construction validates shapes and maps invalid depth (NaN, inf, negative) to 0.

    index: position in the source sequence (before any stride); timestamp: seconds; rgb (H, W, 3) uint8;
    depth (H, W) float32 metres, 0 = no reading; labels (H, W) int64 class ids or None; camera: intrinsics of this
    image; gt_pose: 4x4 float64 cam_to_world ground truth or None (for evaluation and players only).
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray | None
    camera: PinholeCamera
    gt_pose: np.ndarray | None = None

    def __post_init__(self):
        if self.rgb.ndim != 3 or self.rgb.shape[2] != 3 or self.rgb.dtype != np.uint8:
            raise ValueError(f"frame {self.index}: rgb must be (H, W, 3) uint8, got {self.rgb.shape} {self.rgb.dtype}")
        size = self.rgb.shape[:2]
        if self.depth.shape != size:
            raise ValueError(f"frame {self.index}: depth size {self.depth.shape} differs from rgb size {size}")
        if (self.camera.height, self.camera.width) != size:
            raise ValueError(f"frame {self.index}: camera is {self.camera.width}x{self.camera.height}, "
                             f"image is {size[1]}x{size[0]}")
        depth = np.asarray(self.depth, dtype=np.float32)
        self.depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0))
        if self.labels is not None:
            if self.labels.shape != size:
                raise ValueError(f"frame {self.index}: labels size {self.labels.shape} differs from rgb size {size}")
            self.labels = self.labels.astype(np.int64, copy=False)
        if self.gt_pose is not None:
            pose = np.asarray(self.gt_pose, dtype=np.float64)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise ValueError(f"frame {self.index}: gt_pose must be a finite 4x4 matrix")
            self.gt_pose = pose

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.camera.width, self.camera.height


def resize_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize (H, W, ...) by taking, for each output pixel centre, the input pixel that contains it."""
    rows = np.minimum(((np.arange(height) + 0.5) * image.shape[0] / height).astype(np.int64), image.shape[0] - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * image.shape[1] / width).astype(np.int64), image.shape[1] - 1)
    return image[rows[:, None], cols]


def resize_frame(frame: Frame, width: int, height: int) -> Frame:
    """The frame at ``width`` x ``height``: rgb by area averaging, depth and labels by nearest pixel, camera scaled."""
    if (width, height) == frame.size:
        return frame
    shrinking = width <= frame.camera.width and height <= frame.camera.height
    rgb = cv2.resize(frame.rgb, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    labels = None if frame.labels is None else resize_nearest(frame.labels, width, height)
    return replace(frame, rgb=rgb, depth=resize_nearest(frame.depth, width, height), labels=labels,
                   camera=frame.camera.scaled(width, height))


class Dataset(ABC):
    """A sequence of frames: ``len(ds)``, ``ds[i] -> Frame``, iteration, ``name`` and ``class_table`` (or None).

    Options shared by every reader: ``size`` (width, height) resizes every frame (see :func:`resize_frame`),
    ``start`` is the first source frame, ``stride`` keeps every stride-th frame from there, ``max_frames`` caps the
    length. A reader implements
    :meth:`_source_length` and :meth:`_load` (source index -> frame at its native resolution).
    """

    name: str = "dataset"
    class_table: ClassTable | None = None

    def __init__(self, *, size: tuple[int, int] | None = None, stride: int = 1, max_frames: int | None = None,
                 start: int = 0):
        if size is not None and (len(size) != 2 or min(size) <= 0):
            raise ValueError(f"size must be (width, height) with positive entries, got {size}")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
        if start < 0:
            raise ValueError(f"start must be >= 0, got {start}")
        self.size = None if size is None else (int(size[0]), int(size[1]))
        self.stride = int(stride)
        self.max_frames = max_frames
        self.start = int(start)

    @abstractmethod
    def _source_length(self) -> int:
        """Number of frames in the source sequence."""

    @abstractmethod
    def _load(self, index: int) -> Frame:
        """Frame ``index`` of the source sequence at native resolution."""

    def __len__(self) -> int:
        n = max(0, math.ceil((self._source_length() - self.start) / self.stride))
        return n if self.max_frames is None else min(n, self.max_frames)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name}: frame {i} out of range (length {n})")
        source_index = self.start + (i % n) * self.stride
        try:
            frame = self._load(source_index)
        except (ValueError, FileNotFoundError) as exc:
            raise type(exc)(f"{self.name}, frame {source_index}: {exc}") from exc
        return frame if self.size is None else resize_frame(frame, *self.size)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)})"
