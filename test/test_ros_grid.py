"""tracking_mapping publishes the occupancy grid (gausem/grid, nav_msgs/OccupancyGrid, latched, in the map frame)."""
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from nav_msgs.msg import OccupancyGrid  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.maps.occupancy import OCCUPIED  # noqa: E402
from gausem_core.maps.slam_grid import slam_grid  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from gausem_ros.qos import LATCHED_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_for, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_the_node_publishes_the_occupancy_grid_latched_in_the_map_frame():
    """A lock-step replay of a few synthetic frames: grids come after new keyframes (at most once per
    grid_publish_period), none while the map is unchanged; a subscriber that joins after the last one still gets it
    (transient local); it is the core's grid of the map, with its floor-aligned origin."""
    with ros_session(185) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "mapping.every": 2, "worker.mode": "sync", "grid_publish_period": 0.2}))
        player = Player(open_source("synthetic", size=(80, 60), max_frames=6), rate=0.0, lockstep=True,
                        timeout=30.0, context=ctx)
        early = Recorder(ctx, [(OccupancyGrid, "gausem/grid", LATCHED_QOS)], name="early")
        for node in (tracking, player, early.node):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 50.0)
        assert spin_until(executor, lambda: not tracking._grid_dirty, 10.0)
        keyframes = sum(len(s.keyframes) for s in tracking.slam.submaps)
        spin_for(executor, 1.0)  # five periods: an unchanged map publishes no new grid
        assert 1 <= len(early.messages["gausem/grid"]) <= keyframes
        late = Recorder(ctx, [(OccupancyGrid, "gausem/grid", LATCHED_QOS)], name="late")
        executor.add_node(late.node)
        assert spin_until(executor, lambda: late.messages["gausem/grid"], 10.0)
        msg = late.messages["gausem/grid"][-1]
        assert msg.header.frame_id == "map"
        cells, resolution, origin = ma.occupancy_grid_to_cells(msg)
        assert resolution == pytest.approx(tracking.cfg.grid.resolution)
        assert (cells == OCCUPIED).any() and (cells == 0).any() and (cells == -1).any()
        grid = slam_grid(tracking.slam, tracking.cfg.grid, tracking.palette, tracking._floor_class)
        assert np.array_equal(cells, grid.cells) and np.allclose(origin, grid.origin_pose, atol=1e-6)
