"""The occupancy grid of a running :class:`~gausem_core.slam.system.GauSemSLAM`, cheap to rebuild after its map
changes: each keyframe's depth rays are taken once (a closed submap's images read from the store once) and placed at
the keyframes' current poses on every rebuild, so a loop correction moves them without any image being read."""
from __future__ import annotations

from collections.abc import Sequence

import torch

from gausem_core.config import GridConfig
from gausem_core.maps.occupancy import OccupancyGrid, RayView, depth_rays, opaque_grid


class KeyframeRays:
    """The keyframes' camera-frame depth rays (:func:`~gausem_core.maps.occupancy.depth_rays`), by submap and
    frame; one per map (a new map needs a new one)."""

    def __init__(self, pixel_stride: int):
        self.pixel_stride = pixel_stride
        self._points: dict[tuple[int, int], torch.Tensor] = {}

    def views(self, slam) -> list[RayView]:
        """Every keyframe's rays at its current world pose (poses read under the map's lock)."""
        with slam.lock:
            keyframes = [(s, kf, s.world_pose(kf).clone()) for s in slam.submaps for kf in s.keyframes]
        views = []
        for submap, keyframe, pose in keyframes:
            key = (submap.submap_id, keyframe.frame_id)
            if key not in self._points:
                obs = submap.observation(keyframe)
                self._points[key] = depth_rays(obs.depth, obs.camera, self.pixel_stride)
            views.append(RayView(pose, self._points[key]))
        return views


def floor_class_id(names: Sequence[str] | None, floor_class: str) -> int | None:
    """The id of ``floor_class`` in a class table's ``names``; None without a table, a name, or that class."""
    return names.index(floor_class) if names and floor_class and floor_class in names else None


def slam_grid(slam, cfg: GridConfig, palette: torch.Tensor | None = None, floor_class: int | None = None,
              rays: KeyframeRays | None = None) -> OccupancyGrid:
    """The grid of ``slam``'s map now; the floor from the Gaussians of class ``floor_class`` (their class: the
    nearest ``palette`` colour) when given. ``rays``: the map's ray cache, kept between rebuilds. The map is read a
    submap at a time, keeping only the opaque Gaussians' centres (what :func:`build_grid` of the whole map uses)."""
    views = (rays or KeyframeRays(cfg.pixel_stride)).views(slam)
    centres, floor = [], []
    for submap in list(slam.submaps):
        cloud = submap.load_cloud(slam.device).transformed(submap.anchor)
        opaque = cloud.opacities >= cfg.occupied_opacity
        centres.append(cloud.means[opaque])
        if palette is not None and floor_class is not None:
            floor.append(cloud.class_ids(palette)[opaque] == floor_class)
    means = torch.cat(centres) if centres else torch.zeros(0, 3, device=slam.device)
    return opaque_grid(means, views, cfg, torch.cat(floor) if floor else None)
