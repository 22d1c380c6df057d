"""An occupancy grid (:class:`~gausem_core.maps.occupancy.OccupancyGrid`) <-> nav_msgs/OccupancyGrid (the
``gausem/grid`` topic).

``info.origin`` is the pose of cell (0, 0)'s corner in ``header.frame_id``: in the floor frame (``floor_frame``) it is
level (x, y, yaw), as Nav2 reads it; in the map frame it is tilted, since the grid lies in the floor plane, which is
not the map frame's xy plane (the map frame is the first camera's); RViz draws either on the floor. ``data`` is filled
from bytes (an int8 array), not a list: large grids convert in microseconds.
"""
from __future__ import annotations

import array

import numpy as np
from nav_msgs.msg import MapMetaData, OccupancyGrid as OccupancyGridMsg
from std_msgs.msg import Header

from gausem_core.maps.occupancy import OccupancyGrid

from .poses import matrix_to_pose, pose_to_matrix


def grid_to_occupancy_grid(grid: OccupancyGrid, header: Header, floor_frame: bool = False) -> OccupancyGridMsg:
    """The message of ``grid`` in ``header``'s frame: the floor frame (``floor_frame``) or the map frame."""
    rows, cols = grid.cells.shape
    info = MapMetaData(map_load_time=header.stamp, resolution=float(grid.resolution), width=cols, height=rows,
                       origin=matrix_to_pose(grid.local_pose if floor_frame else grid.origin_pose))
    msg = OccupancyGridMsg(header=header, info=info)
    msg.data = array.array("b", np.ascontiguousarray(grid.cells, np.int8).tobytes())
    return msg


def occupancy_grid_to_cells(msg: OccupancyGridMsg) -> tuple[np.ndarray, float, np.ndarray]:
    """(cells (height, width) int8, resolution, origin pose (4, 4) in the header's frame)."""
    cells = np.frombuffer(bytes(msg.data), np.int8)
    if cells.size != msg.info.width * msg.info.height:
        raise ValueError(f"OccupancyGrid holds {cells.size} cells, its info says {msg.info.width}x{msg.info.height}")
    return cells.reshape(msg.info.height, msg.info.width), float(msg.info.resolution), pose_to_matrix(msg.info.origin)
