"""No input kills a node (issue 24): every documented encoding reaches the core, image size limits, exceptions on one
input are counted and the node goes on, and a seeded fuzz of every node's inputs."""
import threading
import time
from collections import Counter
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.data import SYNTHETIC_CLASSES  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_core.semantics import Segmenter  # noqa: E402
from gausem_core.slam.loop import PlaceSignature  # noqa: E402
from gausem_ros.nodes.loop_detection import LoopDetectionNode  # noqa: E402
from gausem_ros.nodes.pose_graph import PoseGraphNode  # noqa: E402
from gausem_ros.nodes.segmentation import SegmentationNode  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.qos import EVENT_QOS, IMAGE_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_for, spin_until  # noqa: E402

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


def _good_frame(stamp: float, camera: PinholeCamera = CAMERA) -> list[Image]:
    rgb, depth, labels = _scene(camera, 0)
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
        self.node.slam.process = lambda obs, skipped=0: (self.observations.append(obs),
                                                           process(obs, skipped))[1]

    def camera_info(self, camera: PinholeCamera) -> None:
        self.info_pub.publish(ma.camera_to_camera_info(camera, ma.make_header(0.0, "cam")))
        assert spin_until(self.executor, lambda: self.node.frame_input.camera == camera, 5.0)

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
    """Issue 24: bgr8 and bgra8 were always dropped (a negative-stride array, counted as bad_labels). One random scene
    seen by a camera at rest, each frame in other encodings (a new random scene every frame cannot be tracked)."""
    with ros_session(141) as (ctx, executor):
        session = _Session(ctx, executor)
        session.camera_info(CAMERA)
        for i, ((colour, big_c, pad_c), (depth_enc, big_d, pad_d), (label_enc, big_l, pad_l)) in enumerate(
                zip(COLOUR, DEPTH + DEPTH, LABELS + LABELS)):
            rgb, depth, labels = _scene(CAMERA, 0)
            stamp = 1.0 + i / 10
            order = {"rgb8": [0, 1, 2], "bgr8": [2, 1, 0], "rgba8": [0, 1, 2, 3], "bgra8": [2, 1, 0, 3]}[colour]
            rgbx = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], 2)[..., order]
            raw_depth = np.rint(depth * 1000).astype(np.uint16) if depth_enc == "16UC1" else depth.copy()
            if depth_enc == "32FC1":  # invalid readings become 0, never NaN, inf or absurd distances in the core
                raw_depth[0, :5], depth[0, :5] = [np.nan, np.inf, -np.inf, -1.0, 3e38], 0.0
            label_dtype = np.uint8 if label_enc == "mono8" else np.uint16
            session.send([_encode(rgbx, colour, stamp, big_c, pad_c),
                          _encode(raw_depth, depth_enc, stamp, big_d, pad_d),
                          _encode(labels.astype(label_dtype), label_enc, stamp, big_l, pad_l)],
                         session.processed(i + 1))
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

        def fail_once(obs, skipped=0):
            session.node.slam.process = process
            raise RuntimeError("injected failure")
        session.node.slam.process = fail_once
        session.send(_good_frame(1.0), session.dropped("processing_error"))
        session.send(_good_frame(1.1), session.processed(1))
        assert spin_until(executor, lambda: session.recorder.messages["gausem/odometry"], 5.0)
        report = {kv.key: kv.value for kv in session.recorder.messages["gausem/diagnostics"][-1].status[0].values}
    assert report["dropped.processing_error"] == "1"



def test_the_input_accounting_adds_up_whenever_another_thread_can_read_it():
    """Issue 63: a soak's diagnostics message now and then did not add up (frames in = processed + dropped +
    pending), read between two steps of a frame's way, or sent by a drop amid a change of several counts (an rgb
    image left unmatched by a match not yet queued). A reader thread looks before and after every step of every way
    (superseded, unmatched, lost in transport, rejected, an exception, processed): it finds the counts being changed
    (the accounting's lock held) or adding up; so does every message sent."""
    with ros_session(144) as (ctx, _):
        node = TrackingMappingNode(context=ctx, parameter_overrides=overrides(FAST_SLAM))
        node.frame_input.camera_info(ma.camera_to_camera_info(CAMERA, ma.make_header(0.0, "cam")))
        seen, sent = Counter(), []
        node.drops._pub = SimpleNamespace(publish=sent.append)

        def adds_up(values: dict) -> str:
            dropped = sum(int(n) for key, n in values.items() if key.startswith("dropped."))
            return "adds up" if int(values["frames_in"]) == int(values["frames_processed"]) + dropped + int(
                values["frames_pending"]) else "torn"

        def read():
            if not node.accounting.lock.acquire(blocking=False):
                seen["held"] += 1
                return
            try:
                seen[adds_up(node.drops.values())] += 1
            finally:
                node.accounting.lock.release()

        def look():
            reader = threading.Thread(target=read)
            reader.start()
            reader.join()

        def watched(step):
            def run(*args, **kwargs):
                look()
                result = step(*args, **kwargs)
                look()
                return result
            return run
        sync, queue = node._inputs.synchronizer, node._queue
        sync.callback, sync.on_drop = watched(sync.callback), watched(sync.on_drop)
        queue._process, queue._on_superseded = watched(queue._process), watched(queue._on_superseded)
        for owner, name in ((queue, "put"), (queue, "skip"), (queue, "settle"), (node.drops, "drop"),
                            (node.accounting, "published"), (node.accounting, "dropped"), (node.slam, "process")):
            setattr(owner, name, watched(getattr(owner, name)))
        sequences = [0, 0, 0]  # each input's publication sequence number

        def send(stamp: float, frame: list[Image], inputs=(0, 1, 2), gap: int = 0) -> None:
            for i in inputs:
                sequences[i] += 1 + gap * (i == 0)
                sync.add(i, stamp, frame[i], sequences[i])
        send(1.0, _good_frame(1.0))
        send(1.1, _good_frame(1.1))  # supersedes 1.0
        queue._run()  # processed
        send(1.2, _good_frame(1.2), inputs=(0,))  # rgb alone: unmatched once 1.3 matches
        send(1.3, _good_frame(1.3), gap=1)  # an rgb message before it lost in transport
        queue._run()  # processed
        blank = _good_frame(1.4)
        blank[1] = _encode(np.zeros((CAMERA.height, CAMERA.width), np.float32), "32FC1", 1.4)
        send(1.4, blank)
        queue._run()  # rejected: invalid_depth
        _fail_once(node.slam, "process")
        send(1.5, _good_frame(1.5))
        queue._run()  # processing_error
        summary = node.summary()
        node.destroy_node()
    assert summary["frames_in"] == 7 and summary["frames_processed"] == 2 and summary["frames_pending"] == 0
    assert summary["dropped"] == {"invalid_depth": 1, "lost_in_transport": 1, "processing_error": 1, "superseded": 1,
                                  "unmatched": 1}
    assert seen["torn"] == 0 and seen["adds up"] >= 10 and seen["held"] >= 10, seen
    messages = Counter(adds_up({kv.key: kv.value for kv in msg.status[0].values}) for msg in sent)
    assert messages == {"adds up": 7}  # one at each drop and each processed frame


def _fail_once(owner, name: str):
    """Make ``owner.name`` raise RuntimeError on its next call only."""
    original = getattr(owner, name)

    def fail(*args, **kwargs):
        setattr(owner, name, original)
        raise RuntimeError(f"injected failure in {name}")
    setattr(owner, name, fail)


def _signature(keyframe_id: int, stamp: float) -> PointCloud2:
    """A place signature (a global descriptor) as the tracker publishes it."""
    place = PlaceSignature(keyframe_id, 0, torch.ones(384), torch.ones(2))
    return ma.records_to_pointcloud2([ma.place_signature_to_record(place, stamp)], ma.make_header(stamp, "map"))


DESCRIPTOR_DETECTION = {"loop.place_recognition": "descriptor"}


def test_loop_detection_pose_graph_and_segmentation_count_an_exception_and_go_on():
    with ros_session(147) as (ctx, executor):
        loop = LoopDetectionNode(context=ctx, parameter_overrides=overrides(DESCRIPTOR_DETECTION))
        graph = PoseGraphNode(context=ctx, namespace="pg")  # only submap events reach it
        seg = SegmentationNode(_BrightnessSegmenter(), context=ctx)
        recorder = Recorder(ctx, [(Image, "semantic/color", IMAGE_QOS)])
        pubs = {topic: recorder.node.create_publisher(msg_type, topic, qos) for topic, msg_type, qos in (
            ("gausem/place_signatures", PointCloud2, EVENT_QOS), ("pg/gausem/submaps", PointCloud2, EVENT_QOS),
            ("rgb/image", Image, IMAGE_QOS))}
        for node in (loop, graph, seg, recorder.node):
            executor.add_node(node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs.values()), 5.0)
        _fail_once(loop.detector, "add_keyframe")
        _fail_once(graph, "_records")
        _fail_once(seg.segmenter, "segment")
        for i, stamp in enumerate((1.0, 2.0)):
            header = ma.make_header(stamp, "cam")
            pubs["gausem/place_signatures"].publish(_signature(i, stamp))
            pubs["pg/gausem/submaps"].publish(ma.records_to_pointcloud2([ma.SubmapEvent(
                i, i, np.eye(4), ma.SubmapEventKind.CREATED)], header))
            pubs["rgb/image"].publish(ma.rgb_to_image(np.zeros((30, 40, 3), np.uint8), header))
            assert spin_until(executor, lambda: all(n.drops.counts["processing_error"] == 1 for n in (loop, graph, seg))
                              and loop.keyframes_checked == i and len(graph.graphs.anchors) == i
                              and seg.frames_segmented == i, 5.0), [dict(n.drops.counts) for n in (loop, graph, seg)]
        assert spin_until(executor, lambda: len(recorder.messages["semantic/color"]) == 1, 5.0)
    assert all(dict(n.drops.counts) == {"processing_error": 1} for n in (loop, graph, seg))


def test_loop_detection_drops_a_keyframe_older_than_the_newest_as_out_of_order():
    """Found by the fuzz test: the detector raised on it. Dropped, counted, and answered (with no candidates)."""
    with ros_session(148) as (ctx, executor):
        loop = LoopDetectionNode(context=ctx, parameter_overrides=overrides(DESCRIPTOR_DETECTION))
        recorder = Recorder(ctx, [(PointCloud2, "gausem/loop_candidates", EVENT_QOS)])
        pub = recorder.node.create_publisher(PointCloud2, "gausem/place_signatures", EVENT_QOS)
        executor.add_node(loop)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: pub.get_subscription_count(), 5.0)
        for keyframe_id, stamp in ((5, 1.0), (3, 2.0)):
            pub.publish(_signature(keyframe_id, stamp))
        answers = recorder.messages["gausem/loop_candidates"]
        assert spin_until(executor, lambda: len(answers) == 2, 5.0)
    assert dict(loop.drops.counts) == {"keyframe_out_of_order": 1} and loop.keyframes_checked == 1
    assert [ma.header_seconds(m.header) for m in answers] == [1.0, 2.0] and not any(m.width for m in answers)

# --- fuzz -----------------------------------------------------------------------------------------------------------
FUZZ_SECONDS = 3.0  # per node
SIDES = (0, 1, 2, 3, 7, 15, 16, 17, 33)
UNKNOWN_ENCODINGS = ("", "yuv422", "32FC3", "bgr16", "8UC3", "mono8 ")
RECORD_TYPES = {"gausem/keyframes": ma.KeyframeRecord, "gausem/place_signatures": ma.PlaceSignatureRecord,
                "gausem/submaps": ma.SubmapEvent,
                "gausem/loop_candidates": ma.LoopCandidateRecord, "gausem/loop_constraints": ma.LoopConstraintRecord,
                "gausem/pose_graph": ma.PoseGraphNode}
FUZZED_INPUTS = {  # node -> the topics fuzzed while it is the target
    "tracking_mapping": ("rgb/camera_info", *FRAME_TOPICS, "gausem/loop_candidates", "gausem/pose_graph"),
    "loop_detection": ("gausem/place_signatures",),
    "pose_graph": ("gausem/keyframes", "gausem/submaps", "gausem/loop_constraints"),
    "segmentation": ("seg/rgb/image",),
}


class _BrightnessSegmenter(Segmenter):
    """A stand-in that needs no weights (the node's DINOv2 segmenter does): class 1 where red exceeds 127."""

    num_classes = len(SYNTHETIC_CLASSES)

    def segment(self, rgb, labels=None):
        return (rgb[..., 0] > 127).astype(np.int64)


class _Fuzzer:
    """Random messages of the right types: any size (0x0, 1x1, huge declared sizes with short data), encodings
    known and unknown, random steps, byte orders and data, NaN/inf depth, CameraInfo with zero/NaN/negative K, records
    with random or corrupted fields and data."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)

    def chance(self, p: float) -> bool:
        return self.rng.random() < p

    def image(self, stamp: float, family: tuple[str, ...]) -> Image:
        rng = self.rng
        if self.chance(0.3):  # well-formed, of the camera's size: random content gets past the checks
            encoding = str(rng.choice(family))
            dtype, channels = ma.images.ENCODINGS[encoding]
            size = CAMERA.width * CAMERA.height * channels * dtype.itemsize
            data = self.pixels(dtype, size) if family != ma.images.COLOR_ENCODINGS else rng.bytes(size)
            return Image(header=ma.make_header(stamp, "cam"), height=CAMERA.height, width=CAMERA.width,
                         encoding=encoding, step=size // CAMERA.height, data=data)
        encoding = str(rng.choice(family if self.chance(0.8) else (*ma.images.ENCODINGS, *UNKNOWN_ENCODINGS)))
        dtype, channels = ma.images.ENCODINGS.get(encoding, (np.dtype(np.uint8), int(rng.integers(1, 5))))
        w, h = (CAMERA.width, CAMERA.height) if self.chance(0.7) else rng.choice(SIDES, 2)
        if self.chance(0.05):
            w, h = rng.integers(2**16, 2**32, 2)  # a huge declared size; the data stays short
        row = int(w) * channels * dtype.itemsize
        step = row + int(rng.choice([0, 0, 0, 1, 3, -1])) if self.chance(0.95) else int(rng.integers(0, 2**32))
        step = max(step, 0)
        size = int(h) * step if int(h) * step <= 200_000 else int(rng.integers(0, 4096))
        if self.chance(0.1):
            size = max(size + int(rng.integers(-8, 9)), 0)
        data = self.pixels(dtype, size) if family != ma.images.COLOR_ENCODINGS else rng.bytes(size)
        return Image(header=ma.make_header(stamp, "cam"), height=int(h), width=int(w), encoding=encoding,
                     is_bigendian=int(self.chance(0.3)), step=step, data=data)

    def pixels(self, dtype: np.dtype, size: int) -> bytes:
        """``size`` bytes: depth-like floats mixed with NaN, inf, zero and negative ones, small integers (class ids
        of the table), or random bytes."""
        if self.chance(0.3):
            return self.rng.bytes(size)
        if dtype == np.float32:
            values = self.rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0, 1.5, 2.0, 3.0], size // 4 + 1)
        else:
            values = self.rng.integers(0, len(SYNTHETIC_CLASSES), size // dtype.itemsize + 1)
        return values.astype(dtype.newbyteorder("<")).tobytes()[:size]

    def camera_info(self, stamp: float) -> CameraInfo:
        rng = self.rng
        w, h = (CAMERA.width, CAMERA.height) if self.chance(0.5) else rng.choice(SIDES, 2)
        k = ma.camera_to_camera_info(CAMERA, ma.make_header(stamp, "cam")).k.copy()
        k[rng.integers(0, 9, int(rng.integers(0, 3)))] = rng.choice([0.0, np.nan, np.inf, -np.inf, -40.0, 1e30])
        if self.chance(0.1):
            k[:] = 0.0
        return CameraInfo(header=ma.make_header(stamp, "cam"), width=int(w), height=int(h), k=k)

    def pose(self) -> np.ndarray:
        q, _ = np.linalg.qr(self.rng.normal(size=(3, 3)))
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = q * np.sign(np.linalg.det(q)), self.rng.normal(scale=0.3, size=3)
        return pose

    def record(self, record_type, stamp: float, descriptor_length: int):
        rng, ids = self.rng, lambda: int(rng.integers(0, 4))
        if record_type is ma.KeyframeRecord:
            return ma.KeyframeRecord(int(rng.integers(0, 1000)), stamp, ids(), self.pose(), self.pose())
        if record_type is ma.PlaceSignatureRecord:  # a global descriptor and ORB rows flagged either way, any values
            rows = descriptor_length  # one length per message
            return ma.PlaceSignatureRecord(
                int(rng.integers(0, 1000)), stamp, ids(), self.chance(0.5),
                rng.normal(size=descriptor_length).astype(np.float32),
                rng.normal(scale=50, size=(rows, 2)).astype(np.float32),
                rng.integers(0, 256, (rows, 32), dtype=np.uint8), rng.normal(size=(rows, 3)).astype(np.float32),
                ids(), rng.normal(size=descriptor_length), rng.integers(-2, 1000, descriptor_length))
        if record_type is ma.SubmapEvent:
            return ma.SubmapEvent(ids(), ids(), self.pose(), ma.SubmapEventKind(ids() % 2))
        if record_type is ma.LoopCandidateRecord:
            return ma.LoopCandidateRecord(ids(), ids(), ids(), ids(), float(rng.random()), float(rng.random()),
                                          self.chance(0.5))
        if record_type is ma.LoopConstraintRecord:
            a = rng.normal(size=(6, 6))
            return ma.LoopConstraintRecord(ids(), ids(), ids(), ids(), self.pose(), float(rng.random()),
                                           a @ a.T + np.eye(6), self.chance(0.5))
        return ma.PoseGraphNode(ma.PoseGraphNodeKind(ids() % 2), ids(), self.pose())

    def cloud(self, record_type, stamp: float) -> PointCloud2:
        """Records of ``record_type``, then maybe corrupted: data, declared size or fields."""
        rng = self.rng
        length = int(rng.integers(0, 4))
        msg = ma.records_to_pointcloud2([self.record(record_type, stamp, length)
                                         for _ in range(int(rng.integers(0, 3)))],
                                        ma.make_header(stamp, "map"), record_type)
        corruption = rng.choice(["none", "none", "data", "short", "size", "fields"])
        if corruption == "data":
            msg.data = rng.bytes(len(msg.data))
        elif corruption == "short":
            msg.data = bytes(msg.data)[:int(rng.integers(0, len(msg.data) + 1))]
        elif corruption == "size":
            msg.width, msg.point_step, msg.row_step = (int(v) for v in rng.integers(0, 2**32, 3))
        elif corruption == "fields":
            field = msg.fields[int(rng.integers(0, len(msg.fields)))]
            field.datatype, field.count, field.offset = (int(v) for v in (rng.integers(0, 12), rng.integers(0, 2**31),
                                                                          rng.integers(0, 2**31)))
        return msg

    def message(self, topic: str, stamp: float):
        if topic in RECORD_TYPES:
            return self.cloud(RECORD_TYPES[topic], stamp)
        if topic == "rgb/camera_info":
            return self.camera_info(stamp)
        family = {"depth/image": ma.images.DEPTH_ENCODINGS,
                  "semantic/labels": ma.images.LABEL_ENCODINGS}.get(topic, ma.images.COLOR_ENCODINGS)
        return self.image(stamp, family)


def _fuzz(executor, publishers: dict, fuzzer: _Fuzzer, topics, stamp: float, seconds: float) -> float:
    """Publish random messages on ``topics`` (one stamp per round) for ``seconds``, spinning between rounds; any
    exception a node raises propagates from the executor and fails the test. The last stamp used."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        stamp += 0.01
        for topic in topics:
            if fuzzer.chance(0.8):
                publishers[topic].publish(fuzzer.message(topic, stamp))
        for _ in range(5):
            executor.spin_once(timeout_sec=0.001)
        assert executor.context.ok()
    return stamp


@pytest.mark.slow
def test_fuzzed_inputs_never_kill_a_node_and_tracking_goes_on():
    with ros_session(144) as (ctx, executor):
        session = _Session(ctx, executor, loop_closure="nodes")  # subscribes to loop candidates and pose graphs
        nodes = {"tracking_mapping": session.node,
                 "loop_detection": LoopDetectionNode(context=ctx, parameter_overrides=overrides(
                     {"loop.exclude_recent": 1})),
                 "pose_graph": PoseGraphNode(context=ctx),
                 "segmentation": SegmentationNode(_BrightnessSegmenter(), context=ctx, namespace="seg")}
        for node in list(nodes.values())[1:]:
            executor.add_node(node)
        types = {**{t: PointCloud2 for t in RECORD_TYPES}, "rgb/camera_info": CameraInfo}
        publishers = {topic: session.recorder.node.create_publisher(types.get(topic, Image), topic, EVENT_QOS)
                      for topic in {t for topics in FUZZED_INPUTS.values() for t in topics}}
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in publishers.values()), 5.0)
        fuzzer, stamp = _Fuzzer(24), 1.0
        for name, topics in FUZZED_INPUTS.items():
            stamp = _fuzz(executor, publishers, fuzzer, topics, stamp, FUZZ_SECONDS)
            assert spin_until(executor, lambda: nodes[name].drops.counts, 5.0), f"{name} dropped nothing"

        spin_for(executor, 1.0)  # the fuzz's last frames are handled before the good ones
        # a fuzzed frame that passed every check started the map in its camera, which the good frames' is not
        # (they would be dropped as camera_changed): a new map
        reset = session.recorder.node.create_client(Trigger, "gausem/reset").call_async(Trigger.Request())
        assert spin_until(executor, reset.done, 10.0) and reset.result().success
        session.camera_info(CAMERA)
        processed = session.node.frames_processed  # fuzzed frames that got past every check
        odometry = session.recorder.messages["gausem/odometry"]
        for _ in range(3):  # one at a time, so none is superseded
            stamp = round(stamp) + 1.0  # exact on the wire (ns)
            session.send(_good_frame(stamp),  # one scene, the camera at rest
                         lambda: odometry and ma.header_seconds(odometry[-1].header) == stamp)
        assert session.node.frames_processed == processed + 3
        drops = {name: dict(node.drops.counts) for name, node in nodes.items()}
    print(f"fuzzed frames processed: {processed}; drops: {drops}")  # what the fuzz hit (pytest -s)
