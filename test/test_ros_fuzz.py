"""No input kills a node (issue 24): every documented encoding reaches the core, image size limits, exceptions on one
input are counted and the node goes on, and a seeded fuzz of every node's inputs."""
import time

import cv2
import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.data import SYNTHETIC_CLASSES  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_core.semantics import Segmenter  # noqa: E402
from gausem_ros.nodes.loop_detection import LoopDetectionNode  # noqa: E402
from gausem_ros.nodes.pose_graph import PoseGraphNode  # noqa: E402
from gausem_ros.nodes.segmentation import SegmentationNode  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.qos import EVENT_QOS, IMAGE_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_until  # noqa: E402

pytestmark = pytest.mark.ros
CAMERA = PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30)
FRAME_TOPICS = ("rgb/image", "depth/image", "semantic/labels")


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _encode(pixels: np.ndarray, encoding: str, stamp: float, bigendian: bool = False, pad: int = 0) -> Image:
    """An Image of ``pixels`` in ``encoding``, in either byte order, with ``pad`` junk bytes after every row."""
    h, w = pixels.shape[:2]
    rows = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<")).reshape(h, -1).view(np.uint8)
    data = np.concatenate([rows, np.full((h, pad), 0xEE, np.uint8)], 1)
    return Image(header=ma.make_header(stamp, "cam"), height=h, width=w, encoding=encoding,
                 is_bigendian=int(bigendian), step=data.shape[1], data=data.tobytes())


def _scene(camera: PinholeCamera, seed: int):
    """rgb (uint8), depth (metres, mm-exact) and labels of a random frame of ``camera``'s size."""
    rng = np.random.default_rng(seed)
    h, w = camera.height, camera.width
    return (rng.integers(0, 256, (h, w, 3), dtype=np.uint8), rng.integers(1000, 3000, (h, w)).astype(np.float32) / 1e3,
            rng.integers(0, len(SYNTHETIC_CLASSES), (h, w)))


def _good_frame(stamp: float, camera: PinholeCamera = CAMERA, seed: int = 0) -> list[Image]:
    rgb, depth, labels = _scene(camera, seed)
    return [_encode(rgb, "rgb8", stamp), _encode(depth, "32FC1", stamp), _encode(labels.astype(np.uint16), "mono16",
                                                                                 stamp)]


class _Session:
    """A tracking node, publishers of its inputs and a recorder of its odometry and diagnostics."""

    def __init__(self, ctx, executor, **parameters):
        self.executor = executor
        self.node = TrackingMappingNode(context=ctx, parameter_overrides=overrides({**FAST_SLAM, **parameters}))
        self.recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS),
                                       (DiagnosticArray, "gausem/diagnostics", EVENT_QOS)])
        self.pubs = [self.recorder.node.create_publisher(Image, t, IMAGE_QOS) for t in FRAME_TOPICS]
        self.info_pub = self.recorder.node.create_publisher(CameraInfo, "rgb/camera_info", IMAGE_QOS)
        executor.add_node(self.node)
        executor.add_node(self.recorder.node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in self.pubs + [self.info_pub]), 5.0)
        self.observations = []
        process = self.node.slam.process
        self.node.slam.process = lambda obs: (self.observations.append(obs), process(obs))[1]

    def camera_info(self, camera: PinholeCamera) -> None:
        self.info_pub.publish(ma.camera_to_camera_info(camera, ma.make_header(0.0, "cam")))
        assert spin_until(self.executor, lambda: self.node.camera == camera, 5.0)

    def send(self, messages, expect) -> None:
        for pub, msg in zip(self.pubs, messages):
            pub.publish(msg)
        assert spin_until(self.executor, expect, 20.0), dict(self.node.drops.counts)

    def dropped(self, reason: str, count: int = 1):
        return lambda: self.node.drops.counts[reason] == count

    def processed(self, count: int):
        return lambda: self.node.frames_processed == count


COLOUR = [(enc, big, pad) for enc in ("rgb8", "bgr8", "rgba8", "bgra8") for big, pad in ((False, 0), (True, 5))]
DEPTH = [("16UC1", False, 0), ("16UC1", True, 2), ("32FC1", False, 4), ("32FC1", True, 0)]
LABELS = [("mono8", False, 3), ("mono16", False, 0), ("mono16", True, 2), ("mono8", True, 0)]


def test_tracking_node_takes_every_documented_encoding_byte_order_and_row_padding():
    """Issue 24: bgr8 and bgra8 were always dropped (a negative-stride array, counted as bad_labels)."""
    with ros_session(141) as (ctx, executor):
        session = _Session(ctx, executor)
        session.camera_info(CAMERA)
        for i, ((colour, big_c, pad_c), (depth_enc, big_d, pad_d), (label_enc, big_l, pad_l)) in enumerate(
                zip(COLOUR, DEPTH + DEPTH, LABELS + LABELS)):
            rgb, depth, labels = _scene(CAMERA, i)
            stamp = 1.0 + i / 10
            order = {"rgb8": [0, 1, 2], "bgr8": [2, 1, 0], "rgba8": [0, 1, 2, 3], "bgra8": [2, 1, 0, 3]}[colour]
            rgbx = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], 2)[..., order]
            raw_depth = np.rint(depth * 1000).astype(np.uint16) if depth_enc == "16UC1" else depth
            label_dtype = np.uint8 if label_enc == "mono8" else np.uint16
            session.send([_encode(rgbx, colour, stamp, big_c, pad_c), _encode(raw_depth, depth_enc, stamp, big_d, pad_d),
                          _encode(labels.astype(label_dtype), label_enc, stamp, big_l, pad_l)], session.processed(i + 1))
            obs = session.observations[-1]
            np.testing.assert_array_equal((obs.rgb * 255).round().numpy().astype(np.uint8), rgb, err_msg=colour)
            np.testing.assert_allclose(obs.depth.numpy(), depth, rtol=1e-6, err_msg=depth_enc)
            np.testing.assert_array_equal(obs.labels.numpy(), labels, err_msg=label_enc)
        assert not session.node.drops.counts
        assert spin_until(executor, lambda: len(session.recorder.messages["gausem/odometry"]) == len(COLOUR), 5.0)


def test_image_sizes_from_1x1_to_above_max_image_pixels():
    """Issue 24: a 1x1 frame killed the node (avg_pool2d in the tracker's pyramid); a declared size the data does not
    hold is bad_image; a frame above max_image_pixels is downscaled with its intrinsics."""
    with ros_session(142) as (ctx, executor):
        session = _Session(ctx, executor, max_image_pixels=40 * 30)
        tiny = PinholeCamera(1.0, 1.0, 0.5, 0.5, 1, 1)
        session.camera_info(tiny)
        session.send(_good_frame(1.0, tiny), session.dropped("bad_size"))
        narrow = PinholeCamera(40.0, 40.0, 20.0, 7.5, 40, 15)
        session.camera_info(narrow)
        session.send(_good_frame(1.1, narrow), session.dropped("bad_size", 2))
        huge = _good_frame(1.2)
        for msg in huge:  # declares 100000x100000 pixels, holds 40x30
            msg.step, msg.height, msg.width = msg.step // msg.width * 100_000, 100_000, 100_000
        session.send(huge, session.dropped("bad_image"))

        large = PinholeCamera(400.0, 400.0, 200.0, 150.0, 400, 300)
        session.camera_info(large)
        session.send(_good_frame(1.3, large), session.processed(1))
        obs = session.observations[-1]
        rgb, depth, labels = _scene(large, 0)
        assert obs.camera == large.scaled(40, 30) == PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30)
        expected_rgb = cv2.resize(rgb, (40, 30), interpolation=cv2.INTER_AREA)
        np.testing.assert_array_equal((obs.rgb * 255).round().numpy().astype(np.uint8), expected_rgb)
        np.testing.assert_array_equal(obs.depth.numpy(), depth[5::10, 5::10])  # nearest: the block's centre pixel
        np.testing.assert_array_equal(obs.labels.numpy(), labels[5::10, 5::10])
        assert spin_until(executor, lambda: session.recorder.messages["gausem/odometry"], 5.0)
        with pytest.raises(ValueError, match="below 8 pixels.*raise min_image_size"):  # registration: 3 levels at 1/2
            TrackingMappingNode(context=ctx, parameter_overrides=overrides({**FAST_SLAM, "min_image_size": 2}))
    assert dict(session.node.drops.counts) == {"bad_size": 2, "bad_image": 1}


def test_an_exception_while_handling_an_input_is_counted_and_the_node_goes_on():
    with ros_session(143) as (ctx, executor):
        session = _Session(ctx, executor)
        session.camera_info(CAMERA)
        process = session.node.slam.process

        def fail_once(obs):
            session.node.slam.process = process
            raise RuntimeError("injected failure")
        session.node.slam.process = fail_once
        session.send(_good_frame(1.0), session.dropped("processing_error"))
        session.send(_good_frame(1.1), session.processed(1))
        assert spin_until(executor, lambda: session.recorder.messages["gausem/odometry"], 5.0)
        report = {kv.key: kv.value for kv in session.recorder.messages["gausem/diagnostics"][-1].status[0].values}
    assert report["dropped.processing_error"] == "1"
