"""The tracking node reports tracking health: diagnostics values and level, odometry covariance, lost frames dropped."""
import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_core.slam.health import TrackingHealth  # noqa: E402
from gausem_ros.nodes.tracking.trajectory import DEGRADED_VARIANCE  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.qos import EVENT_QOS, IMAGE_QOS, LATCHED_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_for, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def frame(stamp: float):
    """rgb, depth and labels of a textured plane 2 m away (40x30)."""
    header = ma.make_header(stamp, "cam")
    rgb = np.random.default_rng(0).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    return (ma.rgb_to_image(rgb, header), ma.numpy_to_image(np.full((30, 40), 2.0, np.float32), "32FC1", header),
            ma.labels_to_image(np.zeros((30, 40), np.int64), header))


def test_tracking_health_reaches_diagnostics_and_odometry_and_a_lost_frame_is_dropped(tmp_path):
    """The node reports the health its core returns (injected here; the core's own never says lost)."""
    with ros_session(160) as (ctx, executor):
        never_lost = {"health.lost_inlier_fraction": 0.0, "health.lost_jump": 1e9, "health.lost_valid_depth": 0.0,
                      "health.lost_coverage": 0.0}
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides({**FAST_SLAM, **never_lost}))
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (Path, "gausem/path", LATCHED_QOS),
                                  (DiagnosticArray, "gausem/diagnostics", EVENT_QOS)])
        node = recorder.node
        pubs = [node.create_publisher(Image, t, IMAGE_QOS) for t in ("rgb/image", "depth/image", "semantic/labels")]
        info_pub = node.create_publisher(CameraInfo, "rgb/camera_info", IMAGE_QOS)
        executor.add_node(tracking)
        executor.add_node(node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs + [info_pub]), 5.0)
        info_pub.publish(ma.camera_to_camera_info(PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30),
                                                  ma.make_header(1.0, "cam")))
        spin_for(executor, 0.3)
        process = tracking.slam.process

        def judged(health):
            def process_judged(obs, skipped=0):
                result = process(obs, skipped)
                tracking.slam.frames[-1].lost = health.status == "lost"  # as the core records a lost frame
                return dataclasses.replace(result, health=health)
            return process_judged

        def send(stamp, health=None, expect=None):
            tracking.slam.process = process if health is None else judged(health)
            for pub, msg in zip(pubs, frame(stamp)):
                pub.publish(msg)
            assert spin_until(executor, expect, 20.0), dict(tracking.drops.counts)

        def latest():
            return recorder.messages["gausem/diagnostics"][-1].status[0]

        send(1.0, expect=lambda: tracking.frames_processed == 1)
        send(1.1, TrackingHealth("degraded", inlier_fraction=0.5, reasons=("inlier_fraction",)),
             lambda: tracking.frames_processed == 2)
        assert spin_until(executor, lambda: len(recorder.messages["gausem/odometry"]) == 2, 5.0)
        ok, degraded = recorder.messages["gausem/odometry"]
        assert not np.any(ok.pose.covariance)
        assert np.array_equal(np.reshape(degraded.pose.covariance, (6, 6)), DEGRADED_VARIANCE * np.eye(6))
        assert spin_until(executor, lambda: latest().level == DiagnosticStatus.WARN, 5.0)
        values = {kv.key: kv.value for kv in latest().values}
        assert values["tracking.status"] == "degraded" and values["tracking.inlier_fraction"] == "0.5"
        assert float(values["camera.vignetting_corner_gain"]) == math.exp(tracking.slam.vignetting.a)
        assert "tracking degraded" in latest().message

        send(1.2, TrackingHealth("lost", jump=40.0, reasons=("jump",)),
             lambda: tracking.drops.counts["tracking_lost"] == 1)
        spin_for(executor, 0.3)
        assert len(recorder.messages["gausem/odometry"]) == 2 and tracking.frames_processed == 2
        paths = len(recorder.messages["gausem/path"])
        tracking.trajectory.path_corrected()  # as after a correction: rebuilt from the trajectory, the lost frame not
        tracking.trajectory.publish_path()  # in it
        assert spin_until(executor, lambda: len(recorder.messages["gausem/path"]) > paths, 5.0)
        assert len(tracking.slam.frames) == 3 and len(recorder.messages["gausem/path"][-1].poses) == 2
        _, written = tracking.save_map(tmp_path)
        assert len(written.read_text().splitlines()) == 1 + 2  # a header line, the two published poses
        assert latest().level == DiagnosticStatus.ERROR and "tracking lost" in latest().message


def test_a_scaled_camera_is_resized_to_the_map_and_another_camera_is_rejected():
    """Mid-run, frames at twice the size with a camera_info scaled alike go on in the map's 40x30 camera; frames whose
    camera is not a scaling of the map's are dropped as camera_changed."""
    with ros_session(169) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(FAST_SLAM))
        sizes, process = [], tracking.slam.process
        tracking.slam.process = lambda obs, skipped=0: sizes.append(tuple(obs.depth.shape)) or process(obs, skipped)
        node = Recorder(ctx, []).node
        pubs = [node.create_publisher(Image, t, IMAGE_QOS) for t in ("rgb/image", "depth/image", "semantic/labels")]
        info_pub = node.create_publisher(CameraInfo, "rgb/camera_info", IMAGE_QOS)
        executor.add_node(tracking)
        executor.add_node(node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs + [info_pub]), 5.0)

        def send(stamp, camera, expect):
            info_pub.publish(ma.camera_to_camera_info(camera, ma.make_header(stamp, "cam")))
            spin_for(executor, 0.2)
            header = ma.make_header(stamp, "cam")
            rgb = np.random.default_rng(0).integers(0, 256, (camera.height, camera.width, 3), dtype=np.uint8)
            for pub, msg in zip(pubs, (ma.rgb_to_image(rgb, header), ma.numpy_to_image(
                    np.full((camera.height, camera.width), 2.0, np.float32), "32FC1", header),
                    ma.labels_to_image(np.zeros((camera.height, camera.width), np.int64), header))):
                pub.publish(msg)
            assert spin_until(executor, expect, 20.0), dict(tracking.drops.counts)

        send(1.0, PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30), lambda: tracking.frames_processed == 1)
        send(1.1, PinholeCamera(80.0, 80.0, 40.0, 30.0, 80, 60), lambda: tracking.frames_processed == 2)
        assert sizes == [(30, 40), (30, 40)]  # tracked in the map's camera
        send(1.2, PinholeCamera(60.0, 60.0, 20.0, 15.0, 40, 30), lambda: tracking.drops.counts["camera_changed"] == 1)
        assert tracking.frames_processed == 2
