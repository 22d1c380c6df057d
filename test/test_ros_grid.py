"""tracking_mapping publishes the occupancy grid (gausem/grid, nav_msgs/OccupancyGrid, latched) in a level frame on
the floor, that frame's pose in the map frame on /tf_static."""
import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from nav_msgs.msg import OccupancyGrid  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.maps.occupancy import OCCUPIED  # noqa: E402
from gausem_core.data.classes import SYNTHETIC_CLASSES  # noqa: E402
from gausem_core.maps.slam_grid import floor_class_id, slam_grid  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from gausem_ros.qos import LATCHED_QOS  # noqa: E402

try:
    from tf2_msgs.msg import TFMessage
except ImportError:  # the set-up builds it (tools/build_tf2_msgs.sh); without it there is no /tf_static to check
    TFMessage = None
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_for, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_the_node_publishes_the_occupancy_grid_latched_in_the_floor_frame():
    """A lock-step replay of a few synthetic frames: grids come after new keyframes (at most once per
    grid_publish_period), none while the map is unchanged; a subscriber that joins after the last one still gets it
    (transient local); it is the core's grid of the map, level in the floor frame (grid_frame), whose pose in the map
    frame is on /tf_static, together composing to the grid's pose in the map."""
    static_tf = [(TFMessage, "/tf_static", LATCHED_QOS)] if TFMessage is not None else []
    with ros_session(185) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "mapping.every": 2, "worker.mode": "sync", "grid_publish_period": 0.2}))
        player = Player(open_source("synthetic", size=(80, 60), max_frames=6), rate=0.0, lockstep=True,
                        timeout=30.0, context=ctx)
        early = Recorder(ctx, [(OccupancyGrid, "gausem/grid", LATCHED_QOS)] + static_tf, name="early")
        for node in (tracking, player, early.node):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 50.0)
        assert spin_until(executor, lambda: not tracking.map_outputs.grid_dirty, 10.0)
        keyframes = sum(len(s.keyframes) for s in tracking.slam.submaps)
        spin_for(executor, 1.0)  # five periods: an unchanged map publishes no new grid
        assert 1 <= len(early.messages["gausem/grid"]) <= keyframes
        late = Recorder(ctx, [(OccupancyGrid, "gausem/grid", LATCHED_QOS)], name="late")
        executor.add_node(late.node)
        assert spin_until(executor, lambda: late.messages["gausem/grid"], 10.0)
        msg = late.messages["gausem/grid"][-1]
        assert msg.header.frame_id == "floor"
        cells, resolution, origin = ma.occupancy_grid_to_cells(msg)
        assert resolution == pytest.approx(tracking.cfg.grid.resolution)
        assert (cells == OCCUPIED).any() and (cells == 0).any() and (cells == -1).any()
        grid = slam_grid(tracking.slam, tracking.cfg.grid, tracking.palette,
                         floor_class_id(SYNTHETIC_CLASSES.names, tracking.cfg.grid.floor_class))
        assert np.array_equal(cells, grid.cells) and np.allclose(origin, grid.local_pose, atol=1e-6)
        assert abs(origin[2, 3]) < 1e-9 and np.allclose(origin[:3, 2], [0, 0, 1])  # level: x, y, yaw only
        if static_tf:
            floor = [t for m in early.messages["/tf_static"] for t in m.transforms if t.child_frame_id == "floor"][-1]
            assert floor.header.frame_id == "map"
            assert np.allclose(ma.transform_to_matrix(floor) @ origin, grid.origin_pose, atol=1e-5)
