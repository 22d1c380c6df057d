"""A 2D occupancy grid from the Gaussian map, for navigation (nav_msgs/OccupancyGrid, the map_server files).

The grid lies in the floor frame (:mod:`gausem_core.maps.floor`). A cell is occupied (100) where the centre of a
Gaussian at least ``grid.occupied_opacity`` opaque lies between ``grid.min_height`` and ``grid.max_height`` above the
floor; free (0) where a keyframe's depth ray (every ``grid.pixel_stride``-th pixel) crossed it between those heights
(up to one cell before the ray's end, and at most ``grid.max_range`` along it; of each keyframe's rays in one
bearing, the one that clears farthest); unknown (-1) elsewhere. Occupied wins over free. The lattice is the floor
frame's (cell (i, j) spans [i, i + 1) x [j, j + 1) cells of ``grid.resolution``), so successive grids of one floor line
up cell for cell.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from gausem_core.config import GridConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera
from gausem_core.maps.floor import FloorPlane, fit_floor

OCCUPIED, FREE, UNKNOWN = 100, 0, -1  # nav_msgs/OccupancyGrid's values
SAMPLES_PER_CELL = 2  # free space: points sampled along each ray per cell width
RAY_CHUNK = 65536  # free space: rays sampled at once (bounds the memory)


@dataclass
class RayView:
    """A keyframe's depth rays: its world pose (4, 4) and the rays' ends (M, 3) in its camera frame."""

    cam_to_world: torch.Tensor
    points: torch.Tensor


@dataclass
class OccupancyGrid:
    """``cells`` (rows, cols) int8 in nav_msgs/OccupancyGrid's row-major order: row j, column i is the cell whose
    corner nearest the origin is at floor-frame (x, y) = ``origin[:2] + (i, j) * resolution``. ``origin``: (x, y, yaw)
    of cell (0, 0)'s corner in the floor frame (map_server's ``origin``; yaw is 0: the lattice is the floor frame's).
    ``floor``: the plane and frame the grid lies in."""

    cells: np.ndarray
    resolution: float
    origin: tuple[float, float, float]
    floor: FloorPlane

    @property
    def local_pose(self) -> np.ndarray:
        """Floor-from-grid (4, 4): cell (0, 0)'s corner and the grid's axes in the floor frame (level: x, y, yaw)."""
        x, y, yaw = self.origin
        local = np.eye(4)
        local[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        local[:2, 3] = x, y
        return local

    @property
    def origin_pose(self) -> np.ndarray:
        """Map-from-grid (4, 4): cell (0, 0)'s corner and the grid's axes in the map frame (tilted: the map frame is
        the first camera's)."""
        return self.floor.pose @ self.local_pose

    def counts(self) -> dict[str, int]:
        """Cells per state."""
        return {name: int((self.cells == value).sum())
                for name, value in (("occupied", OCCUPIED), ("free", FREE), ("unknown", UNKNOWN))}


def depth_rays(depth: torch.Tensor, camera: PinholeCamera, stride: int) -> torch.Tensor:
    """Camera-frame ends (M, 3) of the rays through every ``stride``-th pixel (both ways) with a valid depth."""
    rays = camera.pixel_rays(depth.dtype, depth.device)[::stride, ::stride]
    depth = depth[::stride, ::stride]
    return (rays * depth[..., None])[depth > 0]


def build_grid(cloud: GaussianCloud, views: list[RayView], cfg: GridConfig,
               floor_mask: torch.Tensor | None = None) -> OccupancyGrid:
    """The occupancy grid of a world-frame ``cloud`` and keyframe rays ``views``; ``floor_mask`` (N,) marks the floor
    class's Gaussians (None: no class ids; see :func:`~gausem_core.maps.floor.fit_floor`). ValueError without views
    or a floor."""
    opaque = cloud.opacities.detach() >= cfg.occupied_opacity
    return opaque_grid(cloud.means.detach()[opaque], views, cfg, None if floor_mask is None else floor_mask[opaque])


def opaque_grid(means: torch.Tensor, views: list[RayView], cfg: GridConfig,
                floor_mask: torch.Tensor | None = None) -> OccupancyGrid:
    """:func:`build_grid` of the world-frame centres ``means`` (M, 3) of a cloud's opaque Gaussians (opacity at least
    ``cfg.occupied_opacity``); ``floor_mask`` (M,) marks the floor class's among them."""
    if not views:
        raise ValueError("an occupancy grid needs at least one keyframe")
    if cfg.resolution <= 0 or cfg.pixel_stride < 1 or not cfg.min_height < cfg.max_height:
        raise ValueError("grid: resolution must be > 0, pixel_stride >= 1 and min_height < max_height, got "
                         f"{cfg.resolution}, {cfg.pixel_stride}, {cfg.min_height}, {cfg.max_height}")
    poses = torch.stack([v.cam_to_world.to(means) for v in views])
    floor = fit_floor(means, floor_mask, poses, cfg.max_tilt_deg, cfg.plane_threshold)
    to_floor = torch.as_tensor(np.linalg.inv(floor.pose), dtype=means.dtype, device=means.device)
    local = means @ to_floor[:3, :3].T + to_floor[:3, 3]
    occupied = local[(local[:, 2] >= cfg.min_height) & (local[:, 2] <= cfg.max_height), :2]
    origins, ends, owners = [], [], []
    for k, (view, pose) in enumerate(zip(views, to_floor @ poses)):
        ends.append(view.points.to(means) @ pose[:3, :3].T + pose[:3, 3])
        origins.append(pose[:3, 3].expand_as(ends[-1]))
        owners.append(torch.full((len(ends[-1]),), k, device=means.device))
    starts, stops = _free_segments(torch.cat(origins), torch.cat(ends), torch.cat(owners), cfg)
    return _rasterise(occupied, starts, stops, cfg.resolution, floor)


def _free_segments(origins: torch.Tensor, ends: torch.Tensor, owners: torch.Tensor,
                   cfg: GridConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Floor-frame (x, y) starts and stops (S, 2) of the free parts of rays ``origins`` -> ``ends`` (R, 3, floor
    frame) of the keyframes ``owners`` (R,): where they pass between the band's heights, before the last cell before
    their end and within ``max_range``; of each keyframe's rays in one bearing (bins of ``resolution / max_range``
    rad, a cell at the farthest range) only the one that clears farthest (a laser scan of the view: the others'
    cells lie on it when, as usual, the camera is within the band)."""
    delta = ends - origins
    length = delta.norm(dim=-1).clamp_min(1e-9)
    rising = delta[:, 2]
    flat = rising.abs() < 1e-9
    safe = torch.where(flat, torch.ones_like(rising), rising)
    low, high = (cfg.min_height - origins[:, 2]) / safe, (cfg.max_height - origins[:, 2]) / safe
    in_band = ((origins[:, 2] >= cfg.min_height) & (origins[:, 2] <= cfg.max_height)).to(rising)
    enter = torch.where(flat, 1.0 - in_band, torch.minimum(low, high).clamp_min(0.0))
    leave = torch.where(flat, in_band, torch.maximum(low, high).clamp_max(1.0))
    leave = torch.minimum(leave, torch.minimum((length - cfg.resolution) / length, cfg.max_range / length))
    keep = leave > enter
    origins, delta, enter, leave, owners = origins[keep, :2], delta[keep, :2], enter[keep], leave[keep], owners[keep]
    bins = math.ceil(2 * math.pi * cfg.max_range / cfg.resolution)
    bearing = ((torch.atan2(delta[:, 1], delta[:, 0]) + math.pi) / (2 * math.pi) * bins).long().clamp_max(bins - 1)
    farthest = _last_per_group(owners * bins + bearing, leave * delta.norm(dim=-1))
    origins, delta = origins[farthest], delta[farthest]
    return origins + enter[farthest, None] * delta, origins + leave[farthest, None] * delta


def _last_per_group(groups: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Indices of the largest of ``values`` within each group of equal ``groups`` (one per group)."""
    order = torch.argsort(values)
    order = order[torch.argsort(groups[order], stable=True)]
    sorted_groups = groups[order]
    last = torch.ones_like(sorted_groups, dtype=torch.bool)
    last[:-1] = sorted_groups[1:] != sorted_groups[:-1]
    return order[last]


def _rasterise(occupied: torch.Tensor, starts: torch.Tensor, stops: torch.Tensor, resolution: float,
               floor: FloorPlane) -> OccupancyGrid:
    """The grid spanning the occupied points (N, 2) and the free segments (S, 2 each), floor-frame (x, y)."""
    corners = [(p / resolution).floor().long() for p in (occupied, starts, stops)]
    both = torch.cat(corners)
    if len(both) == 0:
        return OccupancyGrid(np.full((1, 1), UNKNOWN, np.int8), resolution, (0.0, 0.0, 0.0), floor)
    first = both.min(0).values
    cols, rows = (both.max(0).values - first + 1).tolist()

    def cells_of(points: torch.Tensor) -> torch.Tensor:
        ij = (points / resolution).floor().long() - first
        return ij[:, 1] * cols + ij[:, 0]

    free = torch.zeros(rows * cols, dtype=torch.bool, device=occupied.device)
    for begin in range(0, len(starts), RAY_CHUNK):
        free[cells_of(_samples(starts[begin:begin + RAY_CHUNK], stops[begin:begin + RAY_CHUNK], resolution))] = True
    cells = np.full((rows, cols), UNKNOWN, np.int8)
    cells[free.reshape(rows, cols).cpu().numpy()] = FREE
    cells.reshape(-1)[cells_of(occupied).cpu().numpy()] = OCCUPIED
    x0, y0 = (first.double() * resolution).tolist()
    return OccupancyGrid(cells, resolution, (x0, y0, 0.0), floor)


def _samples(starts: torch.Tensor, stops: torch.Tensor, resolution: float) -> torch.Tensor:
    """Points (P, 2) along segments ``starts`` -> ``stops`` (S, 2), :data:`SAMPLES_PER_CELL` per cell width or more,
    at least one per segment."""
    delta = stops - starts
    count = (delta.norm(dim=-1) * SAMPLES_PER_CELL / resolution).floor().long() + 1
    segment = torch.repeat_interleave(torch.arange(len(count), device=count.device), count)
    step = torch.arange(len(segment), device=count.device) - torch.repeat_interleave(count.cumsum(0) - count, count)
    t = (step + 0.5).to(delta) / count[segment].to(delta)
    return starts[segment] + t[:, None] * delta[segment]
