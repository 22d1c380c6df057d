"""TUM RGB-D folders: ``rgb.txt``/``depth.txt``/``groundtruth.txt`` (or ``associations.txt``), optional intrinsics,
labels and class table.

Intrinsics come from ``calib.txt``, else ``camera.yaml`` (keys ``fx fy cx cy`` and optional ``width height
depth_scale`` and lens distortion ``k1 k2 p1 p2 k3``), else the published TUM values of the camera the folder name
names (fr1/fr2/fr3, distortion included for 640x480 images; freiburg1's intrinsics, without distortion, when it names
none). Frames of a camera with lens distortion (OpenCV's radial-tangential model; TUM's fr1 and fr2 images are not
undistorted) are undistorted at load (:class:`~gausem_core.data.undistortion.Undistortion`) into the largest pinhole
camera the lens covers, which becomes the dataset's ``camera``: colour bilinearly, depth and labels by nearest pixel
(depth the driver registered to the distorted colour image; depth re-projected with a depth calibration lands in
that pinhole camera already).
Labels (16-bit class ids, ``<rgb stem>.png``) come from ``labels/``, ``semantic/`` or ``label/``, the class
table from ``classes.txt``, ``classes.json`` or ``palette.txt`` (:func:`gausem_core.data.classes.load_class_table`);
labels without a table get generic classes up to their largest id. What was found or assumed is logged once, at
construction (``description``), with a warning when something was assumed.

Intrinsics in files (TUM, ScanNet, Replica) use the OpenCV convention, pixel centres at integer coordinates; GauSem's
:class:`PinholeCamera` puts them at integer + 0.5, so readers add 0.5 to cx and cy (writers subtract it).

``calib.txt``: the first numeric line is ``fx fy cx cy [depth_scale [width height]]``. An optional keyed line
``distortion k1 k2 p1 p2 [k3]`` gives the colour camera's lens distortion (a comment ``# distortion ...`` ending in
those numbers, as in the shared TUM folder, counts too). Optional keyed lines describe depth that is not registered to
colour: ``depth_registered 0``, ``depth_intrinsics fx fy cx cy [width height]`` and
``depth_to_color`` followed by 12 or 16 numbers (the rigid transform from depth-camera to colour-camera coordinates).
With both of the latter, depth is re-projected into the colour camera (:func:`register_depth`). A comment that says
"not registered" (as in the shared 7-Scenes folder) also means ``depth_registered 0``. Without a depth calibration,
unregistered depth is used as if it were registered (the usual 7-Scenes practice); the dataset then reports
``depth_registered = False`` and warns once, at construction.
"""
from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from gausem_core.data.classes import ClassTable, find_class_table, generic_table
from gausem_core.data.frame import Dataset, Frame
from gausem_core.data.images import read_depth, read_rgb, read_uint16, require_file
from gausem_core.data.undistortion import Undistortion
from gausem_core.geometry import PinholeCamera, quaternion_to_matrix

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
LABEL_DIRS = ("labels", "semantic", "label")  # looked for in this order
# Published TUM colour-camera intrinsics (fx, fy, cx, cy; OpenCV convention) at 640x480.
TUM_INTRINSICS = {"freiburg1": (517.3, 516.5, 318.6, 255.3), "freiburg2": (520.9, 521.0, 325.1, 249.7),
                  "freiburg3": (535.4, 539.2, 320.1, 247.6)}
# ... and their lens distortion (k1 k2 p1 p2 k3; freiburg3's images are undistorted already)
TUM_DISTORTION = {"freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
                  "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), "freiburg3": (0.0, 0.0, 0.0, 0.0, 0.0)}


def camera_from_opencv(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> PinholeCamera:
    """A :class:`PinholeCamera` from intrinsics stated with pixel centres at integer coordinates."""
    return PinholeCamera(float(fx), float(fy), float(cx) + 0.5, float(cy) + 0.5, int(width), int(height))


def read_timestamped(path: Path, fields: int) -> list[tuple[float, list[str]]]:
    """Lines ``timestamp field...`` (``#`` comments skipped) -> [(timestamp, [fields])]."""
    rows = []
    for number, line in enumerate(require_file(path).read_text().splitlines(), 1):
        parts = line.replace(",", " ").split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            stamp = float(parts[0])
        except ValueError:
            raise ValueError(f"{path}:{number}: expected a timestamp first, got {line!r}") from None
        if len(parts) != fields + 1:
            raise ValueError(f"{path}:{number}: expected {fields + 1} fields, got {len(parts)}: {line!r}")
        rows.append((stamp, parts[1:]))
    return rows


def associate(first: np.ndarray, second: np.ndarray, max_difference: float = 0.02) -> list[tuple[int, int]]:
    """Unique pairs (i, j) with |first[i] - second[j]| < max_difference, as TUM's associate.py makes them.

    Candidate pairs are taken greedily from the closest; each stamp is used at most once. Sorted by i.
    """
    first, second = np.asarray(first, np.float64), np.asarray(second, np.float64)
    order = np.argsort(second)
    sorted_second = second[order]
    lo = np.searchsorted(sorted_second, first - max_difference, side="left")
    hi = np.searchsorted(sorted_second, first + max_difference, side="right")
    candidates = [(abs(first[i] - sorted_second[k]), i, int(order[k]))
                  for i in range(len(first)) for k in range(lo[i], hi[i])
                  if abs(first[i] - sorted_second[k]) < max_difference]
    used_first, used_second, pairs = set(), set(), []
    for _, i, j in sorted(candidates):
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def nearest_within(queries: np.ndarray, stamps: np.ndarray, max_difference: float = 0.02) -> np.ndarray:
    """Index of the nearest entry of sorted ``stamps`` for each query, or -1 when none lies within max_difference."""
    stamps = np.asarray(stamps, np.float64)
    if stamps.size == 0:
        return np.full(len(queries), -1)
    queries = np.asarray(queries, np.float64)
    right = np.clip(np.searchsorted(stamps, queries), 0, len(stamps) - 1)
    left = np.maximum(right - 1, 0)
    best = np.where(np.abs(stamps[left] - queries) <= np.abs(stamps[right] - queries), left, right)
    return np.where(np.abs(stamps[best] - queries) < max_difference, best, -1)


def tum_pose(values) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` -> 4x4 float64 cam_to_world."""
    v = np.asarray(values, dtype=np.float64)
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(torch.from_numpy(v[3:7])).numpy()
    pose[:3, 3] = v[:3]
    return pose


@dataclass(frozen=True)
class TumCalibration:
    """What a ``calib.txt`` states (None where it is silent)."""

    intrinsics: tuple[float, float, float, float] | None = None  # OpenCV convention
    depth_scale: float | None = None
    size: tuple[int, int] | None = None  # (width, height)
    depth_registered: bool | None = None
    depth_intrinsics: tuple[float, ...] | None = None  # fx fy cx cy [width height], OpenCV convention
    depth_to_color: np.ndarray | None = None
    distortion: tuple[float, ...] | None = None  # k1 k2 p1 p2 [k3] of the colour camera


def _distortion(path: Path, number: int, words: list[str]) -> tuple[float, ...]:
    values = _numbers(path, number, words)
    if len(values) not in (4, 5):
        raise ValueError(f"{path}:{number}: distortion needs k1 k2 p1 p2 [k3]")
    return tuple(values)


def _numbers(path: Path, number: int, words: list[str]) -> list[float]:
    try:
        return [float(w) for w in words]
    except ValueError:
        raise ValueError(f"{path}:{number}: expected numbers, got {' '.join(words)!r}") from None


def read_calibration(path: Path) -> TumCalibration:
    """Parse a ``calib.txt`` (format in the module docstring)."""
    found: dict = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        words = line.split()
        if not words:
            continue
        if words[0].startswith("#"):
            if re.search(r"not\s+registered", line, re.IGNORECASE):
                found.setdefault("depth_registered", False)
            stated = re.match(r"#\s*distortion\b.*?((?:\s+[-+0-9.eE]+){4,5})\s*$", line)
            if stated:
                found.setdefault("distortion", _distortion(path, number, stated.group(1).split()))
            continue
        key = words[0]
        if key == "depth_registered":
            if words[1:] not in (["0"], ["1"]):
                raise ValueError(f"{path}:{number}: depth_registered must be 0 or 1")
            found["depth_registered"] = words[1] == "1"
        elif key == "distortion":
            found["distortion"] = _distortion(path, number, words[1:])
        elif key == "depth_intrinsics":
            values = _numbers(path, number, words[1:])
            if len(values) not in (4, 6):
                raise ValueError(f"{path}:{number}: depth_intrinsics needs fx fy cx cy [width height]")
            found["depth_intrinsics"] = tuple(values)
        elif key == "depth_to_color":
            values = _numbers(path, number, words[1:])
            if len(values) not in (12, 16):
                raise ValueError(f"{path}:{number}: depth_to_color needs 12 or 16 numbers (a 3x4 or 4x4 matrix)")
            found["depth_to_color"] = np.vstack([np.reshape(values[:12], (3, 4)), [0, 0, 0, 1]])
        elif "intrinsics" not in found:
            values = _numbers(path, number, words)
            if len(values) not in (4, 5, 7):
                raise ValueError(f"{path}:{number}: expected 'fx fy cx cy [depth_scale [width height]]'")
            found["intrinsics"] = tuple(values[:4])
            if len(values) >= 5:
                found["depth_scale"] = values[4]
            if len(values) == 7:
                found["size"] = (int(values[5]), int(values[6]))
        else:
            raise ValueError(f"{path}:{number}: unexpected line {line!r}")
    return TumCalibration(**found)


def read_camera_yaml(path: Path) -> TumCalibration:
    """Parse a ``camera.yaml``: ``fx fy cx cy`` (OpenCV convention) and optional ``width height depth_scale`` and
    ``k1 k2 p1 p2 k3`` (missing ones 0)."""
    doc = yaml.safe_load(path.read_text())
    if not isinstance(doc, dict) or not all(k in doc for k in ("fx", "fy", "cx", "cy")):
        raise ValueError(f"{path}: expected the keys fx, fy, cx, cy (and optionally width, height, depth_scale)")
    try:
        intrinsics = tuple(float(doc[k]) for k in ("fx", "fy", "cx", "cy"))
        size = (int(doc["width"]), int(doc["height"])) if "width" in doc and "height" in doc else None
        depth_scale = float(doc["depth_scale"]) if "depth_scale" in doc else None
        distortion = (tuple(float(doc.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3"))
                      if any(k in doc for k in ("k1", "k2", "p1", "p2", "k3")) else None)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {err}") from None
    return TumCalibration(intrinsics, depth_scale, size, distortion=distortion)


def register_depth(depth: np.ndarray, depth_camera: PinholeCamera, color_camera: PinholeCamera,
                   depth_to_color: np.ndarray) -> np.ndarray:
    """Re-project a depth image into the colour camera (nearest surface wins; unseen pixels stay 0)."""
    valid = depth > 0
    points = depth_camera.backproject(torch.from_numpy(depth.astype(np.float64))).numpy()[valid]
    points = points @ depth_to_color[:3, :3].T + depth_to_color[:3, 3]
    z = points[:, 2]
    u = np.floor(color_camera.fx * points[:, 0] / np.where(z > 0, z, 1) + color_camera.cx).astype(np.int64)
    v = np.floor(color_camera.fy * points[:, 1] / np.where(z > 0, z, 1) + color_camera.cy).astype(np.int64)
    inside = (z > 0) & (u >= 0) & (u < color_camera.width) & (v >= 0) & (v < color_camera.height)
    flat, z = v[inside] * color_camera.width + u[inside], z[inside]
    order = np.lexsort((z, flat))
    flat, z = flat[order], z[order]
    first = np.unique(flat, return_index=True)[1]
    out = np.zeros(color_camera.height * color_camera.width, np.float32)
    out[flat[first]] = z[first]
    return out.reshape(color_camera.height, color_camera.width)


class TumDataset(Dataset):
    """A TUM RGB-D folder (also what :func:`write_tum_folder` writes, with ``labels/`` and ``classes.txt``).

    camera: overrides the intrinsics (else the files, see the module doc); depth_scale: units per metre (else
    calib.txt or camera.yaml, else 5000); depth_registered: overrides what calib.txt says (default: registered);
    max_time_difference: association tolerance (s) for rgb/depth and ground truth. ``description`` says where the
    intrinsics, labels and classes came from.
    """

    def __init__(self, path: str | Path, *, camera: PinholeCamera | None = None, depth_scale: float | None = None,
                 depth_registered: bool | None = None, max_time_difference: float = 0.02, **options):
        super().__init__(**options)
        self.root = Path(path)
        if not self.root.is_dir():
            raise FileNotFoundError(f"TUM folder {self.root} does not exist")
        self.name = self.root.name
        calib, calib_source = self._calibration()
        self.depth_scale = float(depth_scale or calib.depth_scale or TUM_DEPTH_SCALE)
        self.stamps, self.rgb_files, self.depth_files = self._associated_files(max_time_difference)
        self.camera, distortion, intrinsics_source = ((camera, None, "given") if camera else
                                                      self._camera(calib, calib_source))
        self.undistortion = Undistortion(self.camera, distortion) if distortion and any(distortion) else None
        calibrated = self.camera
        if self.undistortion is not None:
            self.camera = self.undistortion.camera
        self._depth_calibration = None
        registered = calib.depth_registered if depth_registered is None else depth_registered
        self.depth_registered = registered is not False
        if not self.depth_registered and calib.depth_intrinsics is not None and calib.depth_to_color is not None:
            fx, fy, cx, cy, *wh = calib.depth_intrinsics
            width, height = wh or (self.camera.width, self.camera.height)
            self._depth_calibration = (camera_from_opencv(fx, fy, cx, cy, width, height), calib.depth_to_color)
            self.depth_registered = True
        elif not self.depth_registered:
            warnings.warn(f"{self.root}: depth is not registered to colour and no depth calibration is given; "
                          "depth pixels are used as if aligned with colour pixels (an approximation)", stacklevel=2)
        self.gt_poses = self._ground_truth(max_time_difference)
        self.labels_dir = next((self.root / d for d in LABEL_DIRS if (self.root / d).is_dir()), None)
        self.class_table, classes_source = self._classes()
        def intrinsics(c: PinholeCamera) -> str:
            return f"fx {c.fx:.1f} fy {c.fy:.1f} cx {c.cx - 0.5:.1f} cy {c.cy - 0.5:.1f}"

        undistorted = "" if self.undistortion is None else (
            f", lens distortion {' '.join(f'{k:g}' for k in distortion)}; undistorted at load into the pinhole "
            f"{intrinsics(self.camera)}")
        self.description = (f"{self.name}: intrinsics {intrinsics_source} ({intrinsics(calibrated)}, "
                            f"{calibrated.width}x{calibrated.height}{undistorted}), depth scale "
                            f"{self.depth_scale:g}; labels {classes_source}")
        if "assumed" in self.description:
            warnings.warn(self.description, stacklevel=2)
        else:
            log.info(self.description)

    def _calibration(self) -> tuple[TumCalibration, str | None]:
        """What ``calib.txt``, else ``camera.yaml``, states, and which file said it (None: neither exists)."""
        for name, read in (("calib.txt", read_calibration), ("camera.yaml", read_camera_yaml)):
            if (self.root / name).is_file():
                return read(self.root / name), f"from {name}"
        return TumCalibration(), None

    def _classes(self) -> tuple[ClassTable | None, str]:
        """The class table, and a description of the labels and where the table came from."""
        found = find_class_table(self.root)
        if self.labels_dir is None:
            return (found[0], f"none (no labels/, semantic/ or label/ folder), {len(found[0])} classes from "
                              f"{found[1].name}") if found else (None, "none (no labels/, semantic/ or label/ folder)")
        where = f"from {self.labels_dir.name}/"
        if found:
            return found[0], f"{where}, {len(found[0])} classes from {found[1].name}"
        count = 1 + max(int(read_uint16(self.labels_dir / (f.stem + ".png")).max()) for f in self.rgb_files)
        return generic_table(count), (f"{where}, {count} generic classes assumed (no classes.txt, classes.json or "
                                      "palette.txt)")

    def _associated_files(self, max_difference: float):
        assoc = self.root / "associations.txt"
        if assoc.is_file():
            rows = read_timestamped(assoc, 3)
            stamps = [t for t, _ in rows]
            rgb, depth = [r[0] for _, r in rows], [r[2] for _, r in rows]
        else:
            rgb_rows = read_timestamped(self.root / "rgb.txt", 1)
            depth_rows = read_timestamped(self.root / "depth.txt", 1)
            pairs = associate([t for t, _ in rgb_rows], [t for t, _ in depth_rows], max_difference)
            stamps = [rgb_rows[i][0] for i, _ in pairs]
            rgb, depth = [rgb_rows[i][1][0] for i, _ in pairs], [depth_rows[j][1][0] for _, j in pairs]
        if not stamps:
            raise ValueError(f"{self.root}: no associated rgb/depth frames")
        for name in rgb + depth:
            require_file(self.root / name)
        return np.array(stamps), [self.root / n for n in rgb], [self.root / n for n in depth]

    def _camera(self, calib: TumCalibration, source: str | None) -> tuple[PinholeCamera, tuple | None, str]:
        """The colour camera, its lens distortion (None: none stated) and where they came from."""
        if calib.intrinsics is not None:
            intrinsics, distortion = calib.intrinsics, calib.distortion
        else:
            match = re.search(r"(?:freiburg|fr)([123])", self.root.name.lower())
            camera = f"freiburg{match.group(1) if match else 1}"
            intrinsics, distortion = TUM_INTRINSICS[camera], TUM_DISTORTION[camera] if match else None
            source = (f"published TUM {camera} values (named by the folder)" if match else
                      "published TUM freiburg1 values, assumed (no calib.txt or camera.yaml, no fr1/fr2/fr3 in the "
                      "folder name)")
        width, height = calib.size or read_rgb(self.rgb_files[0]).shape[1::-1]
        if calib.intrinsics is None and distortion and (width, height) != (640, 480):
            distortion = None  # the published values describe the 640x480 images
            source += f", its published distortion not applied to {width}x{height} images"
        return camera_from_opencv(*intrinsics, width, height), distortion, source

    def _ground_truth(self, max_difference: float) -> list[np.ndarray | None]:
        path = self.root / "groundtruth.txt"
        if not path.is_file():
            return [None] * len(self.stamps)
        rows = sorted(read_timestamped(path, 7))
        nearest = nearest_within(self.stamps, [t for t, _ in rows], max_difference)
        return [None if k < 0 else tum_pose(rows[k][1]) for k in nearest]

    def _source_length(self) -> int:
        return len(self.stamps)

    def _load(self, index: int) -> Frame:
        rgb = read_rgb(self.rgb_files[index])
        depth = read_depth(self.depth_files[index], self.depth_scale)
        if self.undistortion is not None:
            if rgb.shape[1::-1] != self.undistortion.size:
                raise ValueError(f"{self.rgb_files[index]}: size {rgb.shape[1::-1]} differs from the calibration's "
                                 f"{self.undistortion.size}, which the lens distortion refers to")
            rgb = self.undistortion.color(rgb)
            if self._depth_calibration is None:  # registered to the distorted colour image by the driver
                depth = self.undistortion.nearest(depth)
        if self._depth_calibration is not None:
            depth_camera, depth_to_color = self._depth_calibration
            if depth.shape != (depth_camera.height, depth_camera.width):
                raise ValueError(f"{self.depth_files[index]}: size {depth.shape[::-1]} differs from the depth "
                                 f"calibration's {depth_camera.width}x{depth_camera.height}")
            depth = register_depth(depth, depth_camera, self.camera, depth_to_color)
        labels = None
        if self.labels_dir is not None:
            labels = read_uint16(self.labels_dir / (self.rgb_files[index].stem + ".png"))
            labels = (labels if self.undistortion is None else self.undistortion.nearest(labels)).astype(np.int64)
        return Frame(index, float(self.stamps[index]), rgb, depth, labels, self.camera, self.gt_poses[index])
