"""The tracking node's ``viewer`` parameter: a lock-step replay recorded for Rerun, as ``gausem run --viewer`` does."""
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from ros_harness import FAST_SLAM, overrides, ros_session, spin_until  # noqa: E402
from test_viewer import read_recording  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def test_the_viewer_parameter_records_the_frames_the_node_processes(tmp_path):
    pytest.importorskip("rerun")
    frames = 4
    with ros_session(193) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "worker.mode": "sync", "viewer": "record", "viewer_colors": "class",
             "output_dir": str(tmp_path)}))
        player = Player(open_source("synthetic", size=(80, 60), max_frames=frames), rate=0.0, lockstep=True,
                        timeout=30.0, context=ctx)
        for node in (tracking, player):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 60.0)
        tracking.finish()
        processed = tracking.frames_processed
    rows = read_recording(tmp_path / "gausem.rrd")  # default viewer_path: output_dir/gausem.rrd, closed on destroy
    assert processed == frames
    for entity in ("/world/camera/image/rgb", "/world/camera/image/semantic", "/world/camera"):
        assert [r["frame"] for r in rows[entity]] == list(range(frames)), entity
    assert len(rows["/world/trajectory"][-1]["LineStrips3D:strips"][0]) == frames
    assert rows["/world/map"][-1]["Points3D:class_ids"] and rows["/world/map"][-1].get("Points3D:colors") is None


def test_an_unknown_viewer_mode_is_refused_naming_the_parameter():
    with ros_session(194) as (ctx, _), pytest.raises(ValueError, match="tracking_mapping: viewer 'browser'"):
        TrackingMappingNode(context=ctx, parameter_overrides=overrides({**FAST_SLAM, "viewer": "browser"}))
