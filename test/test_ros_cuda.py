"""The tracking node in-process on a CUDA device (issue 22): frames from the player, loops closed in the core, the map
published, a pose-graph update applied and the map saved, with the system's tensors on the GPU throughout. Skipped
without a GPU or without rclpy."""
import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import msg_adapters as ma  # noqa: E402
from device_check import assert_on_cuda, system_results  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from gausem_ros.qos import EVENT_QOS, LATCHED_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_until  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.cuda, pytest.mark.slow,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

FRAMES = 5
SLAM = {**FAST_SLAM, "device": "cuda", "backend": "auto", "mapping.every": 2, "mapping.iterations": 10,
        "mapping.init_iterations": 30, "submaps.min_keyframes": 100, "loop.keyframe_every": 2,
        "loop.check_every": 1, "loop.exclude_recent": 0, "loop.max_fallback_descriptor_distance": 2.0,
        "loop_closure": "core", "map_publish_period": 0.2}


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_the_tracking_node_runs_on_the_gpu(tmp_path):
    shift = np.eye(4)
    shift[0, 3] = 0.5
    with ros_session(131) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**SLAM, "output_dir": str(tmp_path / "out")}))
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (PointCloud2, "gausem/map", LATCHED_QOS),
                                  (PointCloud2, "gausem/loop_constraints", EVENT_QOS)])
        player = Player(open_source("synthetic", size=(160, 120), max_frames=FRAMES), rate=0.0, lockstep=True,
                        timeout=60.0, context=ctx)
        for node in (tracking, recorder.node, player):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 180.0) and tracking.frames_processed == FRAMES
        assert spin_until(executor, lambda: recorder.messages["gausem/map"]
                          and recorder.messages["gausem/loop_constraints"], 10.0)
        assert tracking.slam.device.type == "cuda"
        assert_on_cuda(**system_results(tracking.slam))
        before = [pose.clone() for _, pose in tracking.slam.trajectory()]

        update = ma.PoseGraphUpdate([ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, 0, shift)])
        recorder.node.create_publisher(PointCloud2, "gausem/pose_graph", EVENT_QOS).publish(
            ma.pose_graph_update_to_pointcloud2(update, ma.make_header(1.0, "map")))
        assert spin_until(executor, lambda: tracking.pose_graph_updates, 10.0)
        after = [pose for _, pose in tracking.slam.trajectory()]
        assert_on_cuda(**system_results(tracking.slam))
        shift_gpu = torch.as_tensor(shift, dtype=before[0].dtype, device="cuda")
        torch.testing.assert_close(torch.stack(after), shift_gpu @ torch.stack(before), atol=1e-5, rtol=0)

        saved = recorder.node.create_client(Trigger, "gausem/save_map").call_async(Trigger.Request())
        assert spin_until(executor, saved.done, 30.0) and saved.result().success
    assert len(recorder.messages["gausem/odometry"]) == FRAMES and not tracking.drops.counts
    assert [(r.query_frame, r.match_frame, r.accepted) for r in tracking.slam.loop_closure.records][:1] == \
        [(2, 0, True)]
    assert (tmp_path / "out" / "map.ply").stat().st_size > 0
