"""ScanNet scenes exported by ScanNet's SensReader: ``color/``, ``depth/``, ``pose/``, ``intrinsic/``, ``label-filt/``.

Frames are at the depth resolution with the depth intrinsics (colour and labels are resized to it, as NICE-SLAM and
SplaTAM do); depth PNGs hold millimetres. ``label-filt`` PNGs hold ScanNet's raw category ids; they are mapped to NYU40
with ``scannetv2-labels.combined.tsv`` (given, or found in the scene folder or its parent) or taken as NYU40 ids when
``label_map="nyu40"``. Without a mapping the frames carry no labels (and a warning says why).
"""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

import cv2
import numpy as np

from gausem_core.data.classes import NYU40_CLASSES, SCANNET20_CLASSES, nyu40_to_scannet20
from gausem_core.data.frame import Dataset, Frame, resize_nearest
from gausem_core.data.images import read_depth, read_matrix, read_rgb, read_uint16, require_file
from gausem_core.data.tum import camera_from_opencv

SCANNET_DEPTH_SCALE = 1000.0
LABEL_TSV = "scannetv2-labels.combined.tsv"


def read_raw_to_nyu40(path: Path) -> np.ndarray:
    """ScanNet's label tsv -> lookup array raw category id -> NYU40 id (unknown ids -> 0)."""
    with require_file(path).open(newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    if not rows or not {"id", "nyu40id"} <= set(rows[0]):
        raise ValueError(f"{path}: expected a tab-separated table with 'id' and 'nyu40id' columns")
    try:
        pairs = [(int(r["id"]), int(r["nyu40id"])) for r in rows]
    except ValueError as exc:
        raise ValueError(f"{path}: non-integer id ({exc})") from None
    lut = np.zeros(max(i for i, _ in pairs) + 1, dtype=np.int64)
    for raw, nyu in pairs:
        lut[raw] = nyu
    return lut


class ScanNetDataset(Dataset):
    """One exported ScanNet scene folder.

    classes: "nyu40" (41 classes, 0 = unlabelled) or "scannet20" (the benchmark's 20 + unlabelled);
    label_map: path of ``scannetv2-labels.combined.tsv``, "nyu40" when label PNGs already hold NYU40 ids, or None
    to look for the tsv next to the scene. Frames without a valid pose (ScanNet writes -inf) get gt_pose None.
    """

    def __init__(self, path: str | Path, *, classes: str = "nyu40", label_map: str | Path | None = None,
                 depth_scale: float = SCANNET_DEPTH_SCALE, fps: float = 30.0, **options):
        super().__init__(**options)
        self.root = Path(path)
        if not self.root.is_dir():
            raise FileNotFoundError(f"ScanNet folder {self.root} does not exist")
        if classes not in ("nyu40", "scannet20"):
            raise ValueError(f"classes must be 'nyu40' or 'scannet20', got {classes!r}")
        self.name, self.depth_scale, self.fps = self.root.name, float(depth_scale), float(fps)
        color_dir = self.root / "color"
        self.frame_ids = sorted(int(p.stem) for p in color_dir.glob("*.jpg") if p.stem.isdigit())
        if not self.frame_ids:
            raise ValueError(f"{self.root}: no colour frames color/<n>.jpg")
        for i in self.frame_ids:
            require_file(self.root / "depth" / f"{i}.png")
            require_file(self.root / "pose" / f"{i}.txt")
        k = read_matrix(self.root / "intrinsic" / "intrinsic_depth.txt", (4, 4))
        height, width = read_uint16(self.root / "depth" / f"{self.frame_ids[0]}.png").shape
        self.camera = camera_from_opencv(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
        require_file(self.root / "intrinsic" / "intrinsic_color.txt")
        self.label_lut = self._label_lut(label_map, classes)
        if self.label_lut is not None:
            self.class_table = NYU40_CLASSES if classes == "nyu40" else SCANNET20_CLASSES

    def _label_lut(self, label_map, classes: str) -> np.ndarray | None:
        if not (self.root / "label-filt").is_dir():
            return None
        if label_map == "nyu40":
            lut = np.arange(len(NYU40_CLASSES))
        else:
            candidates = [Path(label_map)] if label_map else [self.root / LABEL_TSV, self.root.parent / LABEL_TSV]
            tsv = next((p for p in candidates if p.is_file()), None)
            if tsv is None:
                if label_map:
                    raise FileNotFoundError(f"missing label map {label_map}")
                warnings.warn(f"{self.root}: label-filt/ present but no {LABEL_TSV} to map its raw ids to NYU40; "
                              "frames carry no labels (pass label_map=...)", stacklevel=3)
                return None
            lut = read_raw_to_nyu40(tsv)
        return nyu40_to_scannet20()[lut] if classes == "scannet20" else lut

    def _source_length(self) -> int:
        return len(self.frame_ids)

    def _labels(self, i: int) -> np.ndarray | None:
        if self.label_lut is None:
            return None
        raw = read_uint16(self.root / "label-filt" / f"{i}.png").astype(np.int64)
        if raw.max(initial=0) >= len(self.label_lut):
            raise ValueError(f"label-filt/{i}.png holds id {raw.max()}, "
                             f"beyond the label map's {len(self.label_lut) - 1}")
        labels = self.label_lut[raw]
        return resize_nearest(labels, self.camera.width, self.camera.height)

    def _load(self, index: int) -> Frame:
        i = self.frame_ids[index]
        depth = read_depth(self.root / "depth" / f"{i}.png", self.depth_scale)
        if depth.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"depth/{i}.png is {depth.shape[1]}x{depth.shape[0]}, expected "
                             f"{self.camera.width}x{self.camera.height}")
        rgb = read_rgb(self.root / "color" / f"{i}.jpg")
        rgb = cv2.resize(rgb, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        pose = read_matrix(self.root / "pose" / f"{i}.txt", (4, 4))
        return Frame(index, i / self.fps, rgb, depth, self._labels(i), self.camera,
                     pose if np.isfinite(pose).all() else None)
