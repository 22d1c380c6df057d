"""The map's outputs: ``gausem/map`` (PointCloud2 of the Gaussians, latched, at most once per ``map_publish_period``
s, after new frames; with ``map_voxel_size`` one per voxel of each submap, the most opaque) and ``gausem/grid``
(nav_msgs/OccupancyGrid, latched, rebuilt after new keyframes and map corrections at most once per
``grid_publish_period`` s: ``gausem_core.maps``, parameters ``grid.*``; in ``grid_frame``, level on the estimated
floor, ``map_frame -> grid_frame`` on /tf_static).

Both are built on their timers' own callback group, off the frame path: with a multi-threaded executor (every GauSem
entry point's) a frame never waits for a rebuild (a grid takes 140-190 ms at 160x120 on a 2-core CPU); they read the
map as the mapping worker leaves it, under its lock where poses must agree (``slam.lock``). The points of an inactive
submap are kept (in its frame) while its Gaussians stay the same (``Submap.version``): a map message reads only the
active submaps' Gaussians, not the ones spilled to disk, and its size is bounded by the voxels the submaps cover."""
from __future__ import annotations

import threading
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import torch
from nav_msgs.msg import OccupancyGrid
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from msg_adapters.pointcloud2 import structured_to_pointcloud2
from gausem_core.config import GridConfig
from gausem_core.maps.slam_grid import KeyframeRays, slam_grid
from gausem_core.slam.system import GauSemSLAM

from ...qos import LATCHED_QOS


class MapPublisher:
    """Publishes the map and its grid when they changed (:meth:`map_changed`, :meth:`grid_changed`); ``stamp()``:
    the stamp they go out with; ``floor_class``: the class id of the floor (None: the lowest level plane);
    ``tf_static``: the node's /tf_static broadcaster (the grid frame's pose)."""

    def __init__(self, node, params: SimpleNamespace, grid: GridConfig, palette: torch.Tensor,
                 floor_class: int | None, tf_static, stamp: Callable[[], float]):
        self._logger, self._params, self._grid_cfg = node.get_logger(), params, grid
        self._palette, self._floor_class, self._tf_static, self._stamp = palette, floor_class, tf_static, stamp
        self._map_pub = node.create_publisher(PointCloud2, "gausem/map", LATCHED_QOS)
        self._grid_pub = node.create_publisher(OccupancyGrid, "gausem/grid", LATCHED_QOS)
        self._building = threading.RLock()  # one build at a time (the timers' or finish's); held to replace the map
        group = MutuallyExclusiveCallbackGroup()  # off the frame path
        node.create_timer(params.map_publish_period, self.publish_map, callback_group=group)
        if params.grid_publish_period:
            node.create_timer(params.grid_publish_period, self.publish_grid, callback_group=group)

    def paused(self) -> threading.RLock:
        """Held while the map is replaced: no build reads it meanwhile (one in progress is waited for)."""
        return self._building

    def reset(self, slam: GauSemSLAM) -> None:
        """A new map (or a loaded one), not changed yet."""
        with self._building:
            self._slam = slam
            self._rays = KeyframeRays(self._grid_cfg.pixel_stride)  # the map's keyframe rays, for its grids
            self._points: dict[tuple[int, int], np.ndarray] = {}  # (submap id, version): an inactive submap's points
            self.map_dirty = self.grid_dirty = False
            self._grid_floor: str | None = None  # where the last grid's floor came from (logged when it changes)
            self._grid_floor_pose: np.ndarray | None = None  # map-from-floor last sent on /tf_static (grid_frame)

    def map_changed(self) -> None:
        """The Gaussians changed: the map goes out with the next period."""
        self.map_dirty = True

    def grid_changed(self) -> None:
        """Keyframes came or the map was corrected: the grid (if any) is rebuilt with the next period."""
        self.grid_dirty = bool(self._params.grid_publish_period)

    def publish_now(self) -> None:
        """Publish the map and the grid now, changed or not (a caller that finishes may stop spinning right
        after)."""
        self.map_changed()
        self.grid_changed()
        self.publish_map()
        self.publish_grid()

    def publish_map(self) -> None:
        with self._building:
            if not self.map_dirty:
                return
            self.map_dirty = False
            header = ma.make_header(self._stamp(), self._params.map_frame)
            self._map_pub.publish(structured_to_pointcloud2(self.map_points(), header))

    def map_points(self) -> np.ndarray:
        """The map message's points (``msg_adapters.MAP_DTYPE``) in the map frame: each submap's in its frame (an
        inactive one's as kept, else from its Gaussians), moved by its anchor."""
        with self._slam.lock:
            submaps = [(s, s.version, s.is_active, s.anchor.detach().cpu().double().numpy())
                       for s in self._slam.submaps]
        kept, parts = {}, []
        for submap, version, active, anchor in submaps:
            key = (submap.submap_id, version)
            points = None if active else self._points.get(key)
            if points is None:
                points = ma.cloud_to_points(submap.load_cloud("cpu"), self._palette, self._params.map_voxel_size)
            if not active:
                kept[key] = points
            parts.append(ma.transform_points(points, anchor))
        self._points = kept  # what a later version or a gone submap replaced is dropped
        return np.concatenate(parts) if parts else np.empty(0, ma.MAP_DTYPE)

    def publish_grid(self) -> None:
        """The occupancy grid, when keyframes or a correction changed the map since the last one (none while the
        map shows no floor: said once)."""
        with self._building:
            if not self.grid_dirty:
                return
            self.grid_dirty = False
            try:
                grid = slam_grid(self._slam, self._grid_cfg, self._palette, self._floor_class, self._rays)
            except ValueError as err:
                self._logger.warning(f"no occupancy grid yet: {err}", once=True)
                return
            if grid.floor.source != self._grid_floor:
                self._grid_floor = grid.floor.source
                where = "the floor class" if grid.floor.source == "class" else "the lowest level plane"
                self._logger.info(f"occupancy grid: the floor from {where} ({grid.floor.inliers} Gaussians)")
            stamp, frame, map_frame = self._stamp(), self._params.grid_frame, self._params.map_frame
            if frame and (self._grid_floor_pose is None or not np.array_equal(self._grid_floor_pose,
                                                                                grid.floor.pose)):
                self._grid_floor_pose = grid.floor.pose
                self._tf_static.sendTransform(ma.matrix_to_transform(grid.floor.pose, ma.make_header(stamp, map_frame),
                                                                     frame))
            header = ma.make_header(stamp, frame or map_frame)
            self._grid_pub.publish(ma.grid_to_occupancy_grid(grid, header, floor_frame=bool(frame)))
