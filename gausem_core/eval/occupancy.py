"""An occupancy grid against a known layout: the synthetic room's walls and furniture rasterised into the grid's
cells, and the occupied cells' IoU.

A cell is truly occupied when a primitive of the scene (box, sphere, vertical cylinder) reaches into the grid's
height band over part of it, or when a wall (the room's boundary) crosses it; both tested at ``SUBSAMPLES`` x
``SUBSAMPLES`` points per cell. Cells wholly outside the room (behind the walls, where no ray reaches) are not
scored, nor are cells more than one cell away from any the grid knows (free or occupied): the scores are over what the
keyframes saw; ``coverage`` says which fraction of the room's truly occupied cells that holds.
"""
from __future__ import annotations

import numpy as np

from gausem_core.data.synthetic import ROOM_CENTRE, ROOM_HALF, Scene
from gausem_core.maps.occupancy import OCCUPIED, UNKNOWN, OccupancyGrid

SUBSAMPLES = 4


def scene_columns(scene: Scene, xy: np.ndarray, low: float, high: float) -> np.ndarray:
    """Whether the vertical column over each scene (x, y) (N, 2) holds a primitive between heights ``low`` and
    ``high`` above the floor (scene z)."""
    hit = np.zeros(len(xy), bool)
    for centre, half, cos, sin in zip(scene.box_centre, scene.box_half, scene.box_cos, scene.box_sin):
        if centre[2] + half[2] >= low and centre[2] - half[2] <= high:
            rel = xy - centre[:2]
            along, across = cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1]
            hit |= (np.abs(along) <= half[0]) & (np.abs(across) <= half[1])
    for centre, radius in zip(scene.sphere_centre, scene.sphere_radius):
        gap = max(low - centre[2], centre[2] - high, 0.0)  # from the centre's height to the band
        if gap < radius:
            hit |= ((xy - centre[:2]) ** 2).sum(-1) <= radius**2 - gap**2
    for base, radius, height in zip(scene.cylinder_base, scene.cylinder_radius, scene.cylinder_height):
        if base[2] + height >= low and base[2] <= high:
            hit |= ((xy - base[:2]) ** 2).sum(-1) <= radius**2
    return hit


def layout_cells(grid: OccupancyGrid, scene: Scene, scene_from_map: np.ndarray, low: float,
                 high: float) -> tuple[np.ndarray, np.ndarray]:
    """(truly occupied, in the room) (rows, cols) bool: the scene rasterised into ``grid``'s cells, the map frame
    placed in the scene by ``scene_from_map`` (4, 4): the first camera's true pose)."""
    rows, cols = grid.cells.shape
    offsets = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES
    j, i, v, u = np.meshgrid(np.arange(rows), np.arange(cols), offsets, offsets, indexing="ij")
    res = grid.resolution
    local = np.stack([(i + u) * res, (j + v) * res, np.zeros_like(u), np.ones_like(u)], -1)
    points = local.reshape(-1, 4) @ (scene_from_map @ grid.origin_pose).T
    xy = points[:, :2]
    inside = (np.abs(xy - ROOM_CENTRE[:2]) < ROOM_HALF[:2]).all(-1).reshape(rows, cols, -1)
    furniture = scene_columns(scene, xy, low, high).reshape(rows, cols, -1)
    in_room = inside.any(-1)
    return furniture.any(-1) | (in_room & ~inside.all(-1)), in_room


def occupancy_scores(grid: OccupancyGrid, truth: np.ndarray, in_room: np.ndarray) -> dict:
    """IoU, precision and recall of the grid's occupied cells against ``truth`` over the scored cells (in the room,
    within a cell of a known one), the coverage of the room's truly occupied cells, and the fraction of free cells
    that are truly occupied."""
    known = grid.cells != UNKNOWN
    near = np.zeros_like(known)
    padded = np.pad(known, 1)
    for dj in range(3):
        for di in range(3):
            near |= padded[dj:dj + known.shape[0], di:di + known.shape[1]]
    scored = in_room & near
    occupied, true = (grid.cells == OCCUPIED) & scored, truth & scored
    free = (grid.cells == 0) & scored
    both, either = int((occupied & true).sum()), int((occupied | true).sum())
    return {"iou": both / either if either else float("nan"),
            "precision": both / int(occupied.sum()) if occupied.any() else float("nan"),
            "recall": both / int(true.sum()) if true.any() else float("nan"),
            "coverage": int(true.sum()) / int((truth & in_room).sum()) if (truth & in_room).any() else float("nan"),
            "free_truly_occupied": int((free & truth).sum()) / int(free.sum()) if free.any() else float("nan"),
            "scored_cells": int(scored.sum())}
