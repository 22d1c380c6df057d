"""The tracking node in-process on a CUDA device (issue 22): frames from the player, a loop closed in the core (keyframes
moved, the submap re-mapped), the map published and saved, with the system's tensors on the GPU. Skipped without a GPU
or without rclpy."""
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
from ros_harness import Recorder, overrides, ros_session, spin_until  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.cuda, pytest.mark.slow,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

FRAMES = 3
# as test_ros_nodes' in-core loop test (keyframe 2 closes a loop to keyframe 0), on the GPU
SLAM = {"device": "cuda", "backend": "auto", "mapping.every": 2, "mapping.iterations": 10,
        "mapping.init_iterations": 30, "submaps.min_keyframes": 100, "loop.keyframe_every": 2,
        "loop.check_every": 1, "loop.exclude_recent": 0, "loop.max_fallback_descriptor_distance": 2.0,
        "loop.place_recognition": "descriptor",  # 80x60 frames hold too few ORB features for the bag of words
        "loop_closure": "core", "map_publish_period": 0.2}


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_the_tracking_node_runs_on_the_gpu(tmp_path):
    with ros_session(161) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**SLAM, "output_dir": str(tmp_path / "out")}))
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (PointCloud2, "gausem/map", LATCHED_QOS),
                                  (PointCloud2, "gausem/loop_constraints", EVENT_QOS)])
        player = Player(open_source("synthetic", size=(80, 60), max_frames=FRAMES), rate=0.0, lockstep=True,
                        timeout=60.0, context=ctx)
        for node in (tracking, recorder.node, player):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 180.0) and tracking.frames_processed == FRAMES
        assert spin_until(executor, lambda: recorder.messages["gausem/map"]
                          and recorder.messages["gausem/loop_constraints"], 10.0), tracking.slam.loop_closure.records
        assert tracking.slam.device.type == "cuda"
        assert_on_cuda(**system_results(tracking.slam))
        saved = recorder.node.create_client(Trigger, "gausem/save_map").call_async(Trigger.Request())
        assert spin_until(executor, saved.done, 30.0) and saved.result().success
    assert len(recorder.messages["gausem/odometry"]) == FRAMES and not tracking.drops.counts
    assert [(r.query_frame, r.match_frame, r.accepted) for r in tracking.slam.loop_closure.records] == [(2, 0, True)]
    assert (tmp_path / "out" / "map.ply").stat().st_size > 0
