"""An occupancy grid as map_server files (ROS 1 map_server, Nav2's nav2_map_server): a PGM image and a YAML.

Trinary mode, ``negate: 0``: occupied cells black (0), free white (254), unknown grey (205); the image's top row is the
grid's last (map_server flips rows). ``free_thresh`` 0.1 (not map_saver's 0.196 or 0.25: Nav2's loader reads a pixel
as free when 1 - value / 255 is below it, which 205 is at 0.25, and equals at 0.196) and ``occupied_thresh`` 0.65.
``origin`` is in the floor frame (:mod:`gausem_core.maps.floor`): GauSem's map frame is its first camera's, whose
xy plane is not the floor, so the YAML also holds ``floor_frame``, that frame's pose in the map frame as
``[x, y, z, qx, qy, qz, qw]`` (map_server ignores the key; a static transform ``map`` -> floor frame with it puts the
served map in place).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from gausem_core.geometry import matrix_to_quaternion
from gausem_core.maps.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

FREE_THRESH, OCCUPIED_THRESH = 0.1, 0.65
PIXELS = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}


def write_map_server(grid: OccupancyGrid, yaml_path: str | Path) -> tuple[Path, Path]:
    """Write ``<name>.pgm`` and ``yaml_path`` (``<name>.yaml``); returns both paths."""
    yaml_path = Path(yaml_path)
    image_path = yaml_path.with_suffix(".pgm")
    image = np.full(grid.cells.shape, PIXELS[UNKNOWN], np.uint8)
    for value, pixel in PIXELS.items():
        image[grid.cells == value] = pixel
    if not cv2.imwrite(str(image_path), image[::-1]):
        raise OSError(f"could not write {image_path}")
    pose = grid.floor.pose
    quaternion = matrix_to_quaternion(torch.from_numpy(pose[:3, :3])).tolist()
    x, y, yaw = grid.origin
    yaml_path.write_text(
        f"image: {image_path.name}\nmode: trinary\nresolution: {grid.resolution:.6g}\n"
        f"origin: [{x:.6f}, {y:.6f}, {yaw:.6f}]  # in the floor frame\nnegate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n"
        f"floor_frame: [{', '.join(f'{v:.6f}' for v in [*pose[:3, 3], *quaternion])}]  # in the map frame, "
        f"x y z qx qy qz qw (floor from {grid.floor.source})\n")
    return image_path, yaml_path


def read_map_server(yaml_path: str | Path) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """(cells (rows, cols) int8, resolution, origin) of a trinary map_server map, read as map_server reads it."""
    yaml_path = Path(yaml_path)
    meta = yaml.safe_load(yaml_path.read_text())
    image = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise OSError(f"could not read {meta['image']} beside {yaml_path}")
    shade = image[::-1] / 255.0
    occupancy = shade if meta["negate"] else 1.0 - shade
    cells = np.full(image.shape, UNKNOWN, np.int8)
    cells[occupancy > meta["occupied_thresh"]] = OCCUPIED
    cells[occupancy < meta["free_thresh"]] = FREE
    return cells, float(meta["resolution"]), tuple(float(v) for v in meta["origin"])
