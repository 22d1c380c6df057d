"""GauSem's ROS 2 nodes through real rclpy pub/sub in one process (each test on its own ROS domain)."""
import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.data import NYU40_CLASSES, SYNTHETIC_CLASSES, open_dataset  # noqa: E402
from gausem_core.geometry import PinholeCamera  # noqa: E402
from gausem_core.semantics import Ade20kSegmenter, Segmenter  # noqa: E402
from gausem_ros.nodes.loop_detection import LoopDetectionNode  # noqa: E402
from gausem_ros.nodes.pose_graph import PoseGraphNode  # noqa: E402
from gausem_ros.nodes.segmentation import SegmentationNode  # noqa: E402
from gausem_ros.nodes.tracking_mapping import TrackingMappingNode  # noqa: E402
from gausem_ros.player import Player, open_source  # noqa: E402
from gausem_ros.qos import EVENT_QOS, IMAGE_QOS, LATCHED_QOS  # noqa: E402
from gausem_ros.run_all import build_nodes  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, overrides, ros_session, spin_for, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _translation(x: float) -> np.ndarray:
    m = np.eye(4)
    m[0, 3] = x
    return m


def _diagnostics(recorder) -> dict:
    """Latest key -> value of the tracking node's gausem/diagnostics."""
    values = {}
    for msg in recorder.messages["gausem/diagnostics"]:
        values.update({kv.key: kv.value for kv in msg.status[0].values})
    return values


def test_adapters_round_trip_through_rclpy_pub_sub():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    depth_m = np.round(rng.uniform(0.5, 4.0, (6, 8)), 3).astype(np.float32)
    camera = PinholeCamera(50.0, 52.0, 4.0, 3.0, 8, 6)
    pose = _translation(0.7) @ np.diag([1.0, -1.0, -1.0, 1.0])
    header = ma.make_header(12.25, "cam")
    sent = {"rgb": ma.rgb_to_image(rgb, header, "bgr8"), "depth": ma.depth_to_image(depth_m, header, "16UC1"),
            "info": ma.camera_to_camera_info(camera, header),
            "odom": ma.matrix_to_odometry(pose, ma.make_header(12.25, "map"), "cam"),
            "kf": ma.records_to_pointcloud2([ma.KeyframeRecord(3, 12.25, 1, pose, np.eye(4))], header)}
    types = {"rgb": Image, "depth": Image, "info": CameraInfo, "odom": Odometry, "kf": PointCloud2}
    with ros_session(101) as (ctx, executor):
        recorder = Recorder(ctx, [(types[k], f"t/{k}", EVENT_QOS) for k in sent])
        pub_node = recorder.node
        pubs = {k: pub_node.create_publisher(types[k], f"t/{k}", EVENT_QOS) for k in sent}
        executor.add_node(pub_node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs.values()), 5.0)
        for key, msg in sent.items():
            pubs[key].publish(msg)
        assert spin_until(executor, lambda: all(recorder.messages[f"t/{k}"] for k in sent), 5.0)
        got = {k: recorder.messages[f"t/{k}"][0] for k in sent}
    np.testing.assert_array_equal(ma.image_to_rgb(got["rgb"]), rgb)
    np.testing.assert_allclose(ma.image_to_depth(got["depth"]), depth_m, atol=5e-4)
    assert ma.camera_info_to_camera(got["info"]) == camera
    np.testing.assert_allclose(ma.odometry_to_matrix(got["odom"]), pose, atol=1e-12)
    assert got["odom"].child_frame_id == "cam" and ma.header_seconds(got["odom"].header) == 12.25
    assert ma.pointcloud2_to_records(got["kf"], ma.KeyframeRecord) == ma.pointcloud2_to_records(sent["kf"],
                                                                                               ma.KeyframeRecord)


def test_tracking_node_in_lockstep_with_the_player(tmp_path):
    frames = 4
    with ros_session(102) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "map_publish_period": 0.2, "output_dir": str(tmp_path / "out"),
             "loop_closure": "nodes", "map_voxel_size": 0.0}))  # applies gausem/pose_graph answers; every Gaussian
        player = Player(open_source("synthetic", size=(80, 60), max_frames=frames), rate=0.0, lockstep=True,
                        timeout=30.0, context=ctx)
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (Path, "gausem/path", LATCHED_QOS),
                                  (PointCloud2, "gausem/map", LATCHED_QOS),
                                  (Image, "semantic/labels", IMAGE_QOS), (PointCloud2, "gausem/keyframes", EVENT_QOS),
                                  (PointCloud2, "gausem/submaps", EVENT_QOS)])
        for node in (tracking, player, recorder.node):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 50.0)
        assert spin_until(executor, lambda: recorder.messages["gausem/map"]
                          and len(recorder.messages["gausem/odometry"]) == frames
                          and len(recorder.messages["gausem/path"][-1].poses) == frames, 5.0)
        odometry = recorder.messages["gausem/odometry"]
        assert len(odometry) == player.odometry_received == tracking.frames_processed == frames
        assert player.timeouts == 0 and not tracking.drops.counts
        dataset = open_dataset("synthetic", size=(80, 60), max_frames=frames)
        assert [ma.header_seconds(o.header) for o in odometry] == pytest.approx([dataset[i].timestamp
                                                                           for i in range(frames)], abs=1e-9)
        assert {(o.header.frame_id, o.child_frame_id) for o in odometry} == {("map", "camera")}
        np.testing.assert_allclose(ma.odometry_to_matrix(odometry[0]), np.eye(4), atol=1e-6)  # first frame = world
        path = recorder.messages["gausem/path"][-1]
        assert path.header.frame_id == "map" and len(path.poses) == frames
        np.testing.assert_allclose(ma.path_to_poses(path)[-1][1], ma.odometry_to_matrix(odometry[-1]), atol=1e-6)
        cloud, labels = ma.pointcloud2_to_cloud(recorder.messages["gausem/map"][-1])
        assert recorder.messages["gausem/map"][-1].header.frame_id == "map"
        assert len(cloud) == len(tracking.slam.global_cloud()) > 0
        assert labels.min() >= 0 and labels.max() < len(SYNTHETIC_CLASSES)
        label_msgs = recorder.messages["semantic/labels"]
        assert len(label_msgs) >= frames - 1  # the recorder may subscribe after the first frame went out
        assert {m.encoding for m in label_msgs} == {"mono16"}
        keyframe = ma.pointcloud2_to_records(recorder.messages["gausem/keyframes"][0], ma.KeyframeRecord)[0]
        assert (keyframe.keyframe_id, keyframe.submap_id) == (0, 0)
        created = ma.pointcloud2_to_records(recorder.messages["gausem/submaps"][0], ma.SubmapEvent)[0]
        assert created.kind == ma.SubmapEventKind.CREATED

        # a corrected anchor moves the whole trajectory; the path is re-published
        before = [p for _, p in ma.path_to_poses(path)]
        update_pub = recorder.node.create_publisher(PointCloud2, "gausem/pose_graph", EVENT_QOS)
        shift = _translation(0.5)
        update = ma.PoseGraphUpdate([ma.PoseGraphNode(ma.PoseGraphNodeKind.ANCHOR, 0, shift)])
        update_pub.publish(ma.pose_graph_update_to_pointcloud2(update, ma.make_header(1.0, "map")))
        assert spin_until(executor, lambda: len(recorder.messages["gausem/path"]) > frames, 5.0)
        after = [p for _, p in ma.path_to_poses(recorder.messages["gausem/path"][-1])]
        np.testing.assert_allclose(after, [shift @ p for p in before], atol=1e-6)

        client = recorder.node.create_client(Trigger, "gausem/save_map")
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, future.done, 10.0) and future.result().success
        load = recorder.node.create_client(Trigger, "gausem/load_map").call_async(Trigger.Request())
        assert spin_until(executor, load.done, 30.0) and load.result().success
        summary = tracking.summary()  # the input accounting goes on across a loaded map
        assert summary["frames_processed"] == frames and summary["frames_in"] == (
            frames + sum(summary["dropped"].values()) + summary["frames_pending"])
        reset = recorder.node.create_client(Trigger, "gausem/reset").call_async(Trigger.Request())
        assert spin_until(executor, reset.done, 10.0) and reset.result().success
        assert tracking.frames_processed == 0 and not tracking.slam.frames
        assert spin_until(executor, lambda: not recorder.messages["gausem/path"][-1].poses, 5.0)
    trajectory = (tmp_path / "out" / "trajectory.txt").read_text().splitlines()
    assert len(trajectory) == frames + 1 and (tmp_path / "out" / "map.ply").stat().st_size > 0


def test_the_node_maps_on_its_worker_by_default_and_publishes_the_keyframes_it_finishes():
    """tracking_mapping's default is worker.mode async: odometry for every frame, each keyframe's record published
    once the worker has mapped it (with a later frame, or at finish), the worker's state in the diagnostics, the
    path appended frame by frame."""
    frames = 8
    with ros_session(109) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(
            {**FAST_SLAM, "mapping.every": 2, "map_publish_period": 1000.0}))  # the map: only as finish sends it
        player = Player(open_source("synthetic", size=(80, 60), max_frames=frames), rate=0.0, lockstep=True,
                        timeout=30.0, context=ctx)
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (Path, "gausem/path", LATCHED_QOS),
                                  (PointCloud2, "gausem/keyframes", EVENT_QOS), (PointCloud2, "gausem/map", LATCHED_QOS)])
        for node in (tracking, player, recorder.node):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 50.0)
        assert tracking.slam.asynchronous and tracking.cfg.worker.mode == "async"
        status = tracking._status()
        assert status["worker.mode"] == "async" and {"worker.queue_depth", "worker.lag_frames",
                                                     "worker.map_age_frames"} <= set(status)
        tracking.finish()
        keyframes = [k.frame_id for s in tracking.slam.submaps for k in s.keyframes]
        stats = tracking.slam.worker.stats
        assert len(keyframes) >= 2 and stats.mapped == len(keyframes) == stats.submitted - stats.superseded
        tracked = tracking.frames_processed  # every frame not judged lost
        assert tracked >= frames - 2

        def published() -> set[int]:  # keyframes announced one by one (finish re-publishes them all at once)
            records = [ma.pointcloud2_to_records(m, ma.KeyframeRecord) for m in recorder.messages["gausem/keyframes"]]
            return {r[0].keyframe_id for r in records if len(r) == 1}
        assert spin_until(executor, lambda: len(recorder.messages["gausem/odometry"]) == tracked
                          and published() == set(keyframes)
                          and max(len(p.poses) for p in recorder.messages["gausem/path"]) >= tracked, 30.0)
        lengths = [len(p.poses) for p in recorder.messages["gausem/path"]]  # a latched topic of depth 1 may skip some
        assert lengths[0] >= 1 and lengths[:-1] == sorted(lengths[:-1])  # grows frame by frame until finish
        # the refined map, published by finish itself (the map timer's period is far longer than this test)
        assert spin_until(executor, lambda: len(recorder.messages["gausem/map"]) == 1, 10.0)


def _frame_messages(stamp: float, size=(40, 30), rgb_encoding="rgb8", depth=None, label=0):
    """rgb, depth (32FC1 exactly as given: NaN and inf go on the wire) and labels of one frame."""
    header = ma.make_header(stamp, "cam")
    w, h = size
    rgb = np.random.default_rng(int(stamp * 10)).integers(0, 256, (h, w, 3), dtype=np.uint8)
    image = ma.rgb_to_image(rgb, header)
    if rgb_encoding != "rgb8":
        image.encoding = rgb_encoding
    depth = np.full((h, w), 2.0, np.float32) if depth is None else depth.astype(np.float32)
    labels = np.full((h, w), label, np.int64)
    return image, ma.numpy_to_image(depth, "32FC1", header), ma.labels_to_image(labels, header)


def test_bad_input_is_dropped_and_reported_and_the_node_keeps_running():
    """Issue 6 §5: wrong encodings, rgb/depth size mismatches, NaN/inf/zero depth, missing or invalid camera_info,
    labels outside the class table, duplicate and out-of-order stamps, a diverged pose estimate."""
    camera = PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30)
    with ros_session(103) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(FAST_SLAM))
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS),
                                  (DiagnosticArray, "gausem/diagnostics", EVENT_QOS)])
        node = recorder.node
        pubs = [node.create_publisher(Image, topic, IMAGE_QOS) for topic in
                ("rgb/image", "depth/image", "semantic/labels")]
        info_pub = node.create_publisher(CameraInfo, "rgb/camera_info", IMAGE_QOS)
        executor.add_node(tracking)
        executor.add_node(node)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in pubs + [info_pub]), 5.0)

        def send(messages, expect):
            for pub, msg in zip(pubs, messages):
                pub.publish(msg)
            assert spin_until(executor, expect, 20.0), dict(tracking.drops.counts)

        def dropped(reason, count=1):
            return lambda: tracking.drops.counts[reason] == count

        send(_frame_messages(1.0), dropped("no_camera_info"))
        info_pub.publish(ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam")))
        spin_for(executor, 0.3)
        uncalibrated = ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam"))
        uncalibrated.k = np.zeros(9)
        info_pub.publish(uncalibrated)  # dropped: the valid camera_info before it stays in use
        assert spin_until(executor, lambda: tracking.drops.rejected["bad_camera_info"] == 1, 5.0)
        assert tracking.frame_input.lens_distortion == () and tracking.frame_input.camera == camera
        distorted = ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam"))
        distorted.d = [0.1, 0.0, 0.0, 0.0, 0.0]  # frames are undistorted into a longer-focal pinhole
        info_pub.publish(distorted)
        assert spin_until(executor, lambda: tracking.frame_input.lens_distortion == (0.1, 0.0, 0.0, 0.0, 0.0), 5.0)
        assert tracking.frame_input.camera.fx > camera.fx and tracking._status()["camera.undistorted"] is True
        obs = tracking._observation(*_frame_messages(1.05))  # what the core would get: the undistorted frame
        assert obs.camera == tracking.frame_input.camera and bool((obs.depth > 0).all())
        distorted.d = [0.1, 0.2]  # a model it cannot undo: rejected, the one before stays
        info_pub.publish(distorted)
        assert spin_until(executor, lambda: tracking.drops.rejected["bad_camera_info"] == 2, 5.0)
        assert tracking.frame_input.lens_distortion == (0.1, 0.0, 0.0, 0.0, 0.0)
        info_pub.publish(ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam")))
        assert spin_until(executor, lambda: tracking.frame_input.camera == camera, 5.0)
        send(_frame_messages(1.1, rgb_encoding="mono16"), dropped("bad_encoding"))
        send(_frame_messages(1.2, size=(20, 30)), dropped("size_mismatch"))  # all three differ from camera_info
        send(_frame_messages(1.21, depth=np.full((30, 20), 2.0)), dropped("size_mismatch", 2))  # rgb vs depth
        for i, value in enumerate((np.nan, np.inf, -np.inf, 0.0)):
            send(_frame_messages(1.3 + i / 100, depth=np.full((30, 40), value)), dropped("invalid_depth", i + 1))
        send(_frame_messages(1.35, label=len(SYNTHETIC_CLASSES)), dropped("bad_labels"))
        send(_frame_messages(1.4), lambda: tracking.frames_processed == 1)
        send(_frame_messages(1.4), dropped("stale_stamp"))  # a repeated stamp
        send(_frame_messages(1.5), lambda: tracking.frames_processed == 2)
        send(_frame_messages(1.45), dropped("stale_stamp", 2))  # out of order: older than the last processed frame

        process = tracking.slam.process  # a core whose estimate diverges on the next frame
        tracking.slam.process = lambda obs, skipped=0: dataclasses.replace(process(obs, skipped),
                                                                           cam_to_world=torch.full((4, 4), np.nan))
        send(_frame_messages(1.6), dropped("tracking_diverged"))
        tracking.slam.process = process
        send(_frame_messages(1.7), lambda: tracking.frames_processed == 3)
        assert spin_until(executor, lambda: len(recorder.messages["gausem/odometry"]) == 3, 5.0)
        assert spin_until(executor, lambda: _diagnostics(recorder).get("frames_processed") == "3", 5.0)
        report = _diagnostics(recorder)
    expected = {"no_camera_info": 1, "bad_encoding": 1, "size_mismatch": 2, "invalid_depth": 4, "bad_labels": 1,
                "stale_stamp": 2, "tracking_diverged": 1}
    assert {k: int(v) for k, v in report.items() if k.startswith("dropped.")} == {
        f"dropped.{k}": v for k, v in expected.items()}
    assert report["rejected.bad_camera_info"] == "2"
    assert report["sync.depth.backwards"] == report["sync.labels.backwards"] == "2"
    assert int(report["frames_in"]) == 15 == 3 + sum(expected.values()) and report["frames_pending"] == "0"
    assert [ma.header_seconds(o.header) for o in recorder.messages["gausem/odometry"]] == [1.4, 1.5, 1.7]


class _BrightnessSegmenter(Segmenter):
    """Class 1 where the red channel exceeds 127, else 0 (over the synthetic table's 12 classes)."""

    num_classes = len(SYNTHETIC_CLASSES)

    def segment(self, rgb, labels=None):
        return (rgb[..., 0] > 127).astype(np.int64)


def _segmented(ctx, executor, seg: SegmentationNode, image: Image) -> tuple[Image, Image]:
    """The labels and colour messages ``seg`` publishes for ``image``."""
    recorder = Recorder(ctx, [(Image, "semantic/labels", IMAGE_QOS), (Image, "semantic/color", IMAGE_QOS)])
    pub = recorder.node.create_publisher(Image, "rgb/image", IMAGE_QOS)
    executor.add_node(seg)
    executor.add_node(recorder.node)
    assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 5.0)
    pub.publish(image)
    assert spin_until(executor, lambda: recorder.messages["semantic/color"], 20.0)
    return recorder.messages["semantic/labels"][0], recorder.messages["semantic/color"][0]


def test_segmentation_node_publishes_labels_and_colours_and_refuses_the_labels_kind():
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[:, 3:, 0] = 200
    with ros_session(104) as (ctx, executor):
        with pytest.raises(ValueError, match="cannot segment an image by itself"):
            SegmentationNode(context=ctx)
        labels_msg, color_msg = _segmented(ctx, executor, SegmentationNode(_BrightnessSegmenter(), context=ctx),
                                           ma.rgb_to_image(rgb, ma.make_header(3.0, "cam"), "bgr8"))
    expected = np.zeros((4, 6), np.int64)  # sent as bgr8, read back as RGB: red is 200 in the right half
    expected[:, 3:] = 1
    np.testing.assert_array_equal(ma.image_to_labels(labels_msg), expected)
    assert labels_msg.encoding == "mono16" and ma.header_seconds(labels_msg.header) == 3.0
    np.testing.assert_array_equal(ma.image_to_rgb(color_msg), SYNTHETIC_CLASSES.colorize(expected))


def test_segmentation_node_runs_the_ade20k_model_into_the_nyu40_table(ade20k_model):
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[24:] = (150, 120, 90)  # a brown floor under a pale wall
    rgb[:24] = (225, 225, 220)
    model = {"semantics.segmenter": "ade20k", "semantics.ade20k_model": str(ade20k_model)}
    with ros_session(124) as (ctx, executor):
        with pytest.raises(ValueError, match="classes:=nyu40"):
            SegmentationNode(context=ctx, parameter_overrides=overrides(model))
        seg = SegmentationNode(context=ctx, parameter_overrides=overrides({**model, "classes": "nyu40"}))
        labels_msg, _ = _segmented(ctx, executor, seg, ma.rgb_to_image(rgb, ma.make_header(2.0, "cam"), "rgb8"))
    labels = ma.image_to_labels(labels_msg)
    np.testing.assert_array_equal(labels, Ade20kSegmenter(ade20k_model).segment(rgb))  # the core's labels, as sent
    assert labels.shape == (48, 64) and labels.max() < len(NYU40_CLASSES)


def _answers(domain: int, parameters: dict, places: list) -> tuple[list, LoopDetectionNode]:
    """Run a loop-detection node on place signatures (core PlaceSignatures, stamped 1, 2, ...); its answers (one
    list of candidate records per signature) and the node."""
    with ros_session(domain) as (ctx, executor):
        loop = LoopDetectionNode(context=ctx, parameter_overrides=overrides({"loop.exclude_recent": 1, **parameters}))
        recorder = Recorder(ctx, [(PointCloud2, "gausem/loop_candidates", EVENT_QOS)])
        pub = recorder.node.create_publisher(PointCloud2, "gausem/place_signatures", EVENT_QOS)
        executor.add_node(loop)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: pub.get_subscription_count(), 5.0)
        answers = recorder.messages["gausem/loop_candidates"]
        for i, place in enumerate(places):
            stamp = 1.0 + i
            pub.publish(ma.records_to_pointcloud2([ma.place_signature_to_record(place, stamp)],
                                                  ma.make_header(stamp, "map")))
            assert spin_until(executor, lambda: len(answers) == i + 1, 5.0)  # every signature is answered
            assert ma.header_seconds(answers[i].header) == stamp
    return [ma.pointcloud2_to_records(m, ma.LoopCandidateRecord) for m in answers], loop


def _orb_places() -> list:
    """Bag-of-words signatures of synthetic views: three places, then the first one again (a revisit)."""
    from gausem_core.config import BowConfig
    from gausem_core.slam.loop import PlaceSignature
    from gausem_core.slam.features import extract_features
    from loop_scene import frame
    places = []
    for n, index in enumerate((0, 90, 180, 3)):
        obs = frame(index)[0]
        features = extract_features(obs.rgb, obs.depth, obs.camera, BowConfig())
        places.append(PlaceSignature(5 * n, n // 2, features, torch.tensor([1.0, float(n % 3), 0.5])))
    return places


@pytest.mark.parametrize("place_recognition", ["descriptor", "bow"])
def test_loop_detection_answers_with_the_core_detectors_candidates(place_recognition):
    """The node is the core's LoopDetector, configured as the tracker's loop closure configures it: the same
    signatures give the same ranked candidates (with the bag of words: its database, up to bow.candidates)."""
    from gausem_core.config import from_flat
    from gausem_core.slam.loop import LoopDetector, PlaceSignature
    parameters = {"loop.check_every": 1, "loop.place_recognition": place_recognition, "loop.bow.candidates": 2}
    if place_recognition == "bow":
        places = _orb_places()
    else:
        g = torch.Generator().manual_seed(2)
        a, b = (torch.nn.functional.normalize(torch.randn(384, generator=g), dim=0) for _ in range(2))
        places = [PlaceSignature(5 * n, 0, d, torch.tensor([1.0, 2.0])) for n, d in enumerate((a, b, b, a))]
    answers, loop = _answers(105 if place_recognition == "bow" else 119, parameters, places)
    cfg = from_flat({**parameters, "loop.exclude_recent": 1}).loop
    detector = LoopDetector.from_config(cfg, cfg.place_recognition_for("fallback"))
    expected = [[ma.loop_candidate_to_record(c) for c in detector.add_keyframe(p)] for p in places]
    assert answers == expected and answers[-1]  # the revisit of keyframe 0 is found
    assert answers[-1][0].match_keyframe_id == 0 and loop.keyframes_checked == 4


def test_loop_detection_takes_the_keyframes_the_tracker_names_nearby():
    """Three different places, no descriptor check: the third signature names the first as near in the tracker's
    pose estimate (``loop.proximity_radius``), so it is a candidate."""
    from gausem_core.slam.loop import PlaceSignature
    g = torch.Generator().manual_seed(3)
    places = [PlaceSignature(5 * n, 0, torch.randn(384, generator=g), torch.ones(2), nearby)
              for n, nearby in enumerate([(), (), (0,)])]
    answers, _ = _answers(118, {"loop.check_every": 100, "loop.place_recognition": "descriptor"}, places)
    assert [[(c.query_keyframe_id, c.match_keyframe_id) for c in a] for a in answers] == [[], [], [(10, 0)]]


def test_pose_graph_node_closes_an_intra_submap_loop():
    with ros_session(106) as (ctx, executor):
        graph = PoseGraphNode(context=ctx)
        recorder = Recorder(ctx, [(PointCloud2, "gausem/pose_graph", EVENT_QOS)])
        kf_pub = recorder.node.create_publisher(PointCloud2, "gausem/keyframes", EVENT_QOS)
        loop_pub = recorder.node.create_publisher(PointCloud2, "gausem/loop_constraints", EVENT_QOS)
        executor.add_node(graph)
        executor.add_node(recorder.node)
        assert spin_until(executor, lambda: kf_pub.get_subscription_count() and loop_pub.get_subscription_count(),
                          5.0)
        records = [ma.KeyframeRecord(5 * i, 0.1 * i, 0, _translation(0.1 * i), np.eye(4))
                   for i in range(4)]  # odometry says keyframe 15 is 0.3 m from keyframe 0 ...
        kf_pub.publish(ma.records_to_pointcloud2(records, ma.make_header(0.3, "map")))
        assert spin_until(executor, lambda: len(graph.keyframes) == 4, 5.0)
        header = ma.make_header(0.3, "map")
        information = ma.sigmas_to_information((0.005, 0.01))  # as certain as one odometry step
        unknown = ma.LoopConstraintRecord(0, 99, 0, 0, _translation(0.2), 1.0, information, True)
        loop = ma.LoopConstraintRecord(0, 15, 0, 0, _translation(0.2), 1.0, information, True)  # ... the loop 0.2 m
        loop_pub.publish(ma.records_to_pointcloud2([unknown, loop], header))
        assert spin_until(executor, lambda: recorder.messages["gausem/pose_graph"], 10.0)
        update = ma.pointcloud2_to_pose_graph_update(recorder.messages["gausem/pose_graph"][0])
    assert graph.drops.counts["unknown_nodes"] == 1
    poses = {n.node_id: n.pose for n in update.nodes}
    assert sorted(poses) == [0, 5, 10, 15] and {n.kind for n in update.nodes} == {ma.PoseGraphNodeKind.KEYFRAME}
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)  # the submap's first keyframe is fixed
    x = [poses[k][0, 3] for k in (5, 10, 15)]
    assert 0.2 < x[2] < 0.3 and x[0] < x[1] < x[2]  # pulled towards the loop, odometry order kept


def test_pose_graph_node_takes_anchors_from_the_latest_keyframe_record():
    """The tracker re-publishes its keyframes with their current anchors before each loop constraint (as the core's
    correction reads them): the latest record wins; a submap event only names a submap no record named yet."""
    with ros_session(120) as (ctx, executor):
        graph = PoseGraphNode(context=ctx)
        node = Recorder(ctx, []).node
        kf_pub = node.create_publisher(PointCloud2, "gausem/keyframes", EVENT_QOS)
        submap_pub = node.create_publisher(PointCloud2, "gausem/submaps", EVENT_QOS)
        executor.add_node(graph)
        executor.add_node(node)
        assert spin_until(executor, lambda: kf_pub.get_subscription_count() and submap_pub.get_subscription_count(),
                          5.0)
        header = ma.make_header(1.0, "map")
        for anchor_x in (0.5, 0.7):  # the anchor of submap 1 before and after a correction
            kf_pub.publish(ma.records_to_pointcloud2([ma.KeyframeRecord(5, 1.0, 1, np.eye(4), _translation(anchor_x))],
                                                     header))
            assert spin_until(executor, lambda: 1 in graph.graphs.anchors
                              and graph.graphs.anchors[1][0, 3] == anchor_x, 5.0)
        events = [ma.SubmapEvent(s, 5, _translation(9.0), ma.SubmapEventKind.CLOSED) for s in (1, 2)]
        submap_pub.publish(ma.records_to_pointcloud2(events, header))
        assert spin_until(executor, lambda: 2 in graph.graphs.anchors, 5.0)
    assert graph.graphs.anchors[1][0, 3] == 0.7 and graph.graphs.anchors[2][0, 3] == 9.0


def test_run_all_builds_the_node_set_the_parameters_ask_for():
    with ros_session(107) as (ctx, executor):
        del executor
        nodes = build_nodes(context=ctx, parameter_overrides=overrides({"device": "cpu", "loop_closure": "nodes"}))
        names = [n.get_name() for n in nodes]
        without_loops = build_nodes(context=ctx, parameter_overrides=overrides({"device": "cpu",
                                                                                "loop.enabled": False}))
        names_without = [n.get_name() for n in without_loops]
        in_core = build_nodes(context=ctx, parameter_overrides=overrides({"device": "cpu"}))  # the default
        names_in_core = [n.get_name() for n in in_core]
        for node in nodes + without_loops + in_core:
            node.destroy_node()
    assert names == ["tracking_mapping", "loop_detection", "pose_graph"]
    assert names_without == names_in_core == ["tracking_mapping"]


def test_a_node_given_a_renamed_parameter_fails_naming_the_new_name():
    with ros_session(162) as (ctx, _):
        graph = PoseGraphNode(context=ctx, parameter_overrides=overrides({"refinement.iterations_per_keyframe": 3}))
        iterations, undeclared = graph.cfg.refinement.iterations_per_keyframe, not graph.has_parameter(
            "loop.refine_iterations_per_keyframe")
        graph.destroy_node()
        with pytest.raises(ValueError, match="'loop.refine_iterations_per_keyframe' is now "
                                             "'refinement.iterations_per_keyframe'"):
            PoseGraphNode(context=ctx, parameter_overrides=overrides({"loop.refine_iterations_per_keyframe": 3}))
    assert iterations == 3 and undeclared


def test_tracker_keeps_tracking_while_loop_detection_and_pose_graph_restart():
    """Frames 0-3 with every node up, 4-5 with loop_detection and pose_graph down, 6-9 after fresh instances start."""
    slam = {**FAST_SLAM, "mapping.every": 2, "worker.mode": "sync",  # keyframes 0, 2, 4, 6, 8, each mapped in its frame
            "submaps.policy": "motion", "submaps.motion_translation": 100.0}  # all in one submap: the loop is intra
    # a loop per check
    loops = {"loop.keyframe_every": 2, "loop.check_every": 1, "loop.exclude_recent": 0,
             "loop.place_recognition": "descriptor", "loop.max_fallback_descriptor_distance": 2.0,
             "loop.registration.min_fitness": 2.0, "loop_closure": "nodes"}  # none accepted: the constraint below stands in for registration
    frames = list(open_source("synthetic", size=(80, 60), max_frames=10))
    with ros_session(108) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides({**slam, **loops}))
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS)])
        constraint_pub = recorder.node.create_publisher(PointCloud2, "gausem/loop_constraints", EVENT_QOS)
        executor.add_node(tracking)
        executor.add_node(recorder.node)

        def start_helpers():
            helpers = (LoopDetectionNode(context=ctx, parameter_overrides=overrides({**slam, **loops})),
                       PoseGraphNode(context=ctx))
            for node in helpers:
                executor.add_node(node)
            assert spin_until(executor, lambda: constraint_pub.get_subscription_count() == 1, 5.0)
            return helpers

        def play(first: int, last: int) -> None:
            player = Player(frames[first:last], rate=0.0, lockstep=True, timeout=60.0, context=ctx)
            executor.add_node(player)
            assert spin_until(executor, lambda: player.done, 90.0)
            assert player.timeouts == 0 and tracking.frames_processed == last
            assert executor.retire_node(player)

        loop_detection, pose_graph = start_helpers()
        play(0, 4)
        assert spin_until(executor, lambda: tracking.loop_link.candidates, 5.0)  # keyframe 2 -> 0
        for node in (loop_detection, pose_graph):  # both "crash"
            assert executor.retire_node(node)
        candidates_before = len(tracking.loop_link.candidates)
        play(4, 6)  # keyframe 4 reaches nobody; tracking goes on
        assert spin_until(executor, lambda: len(recorder.messages["gausem/odometry"]) == 6, 5.0)
        assert len(tracking.loop_link.candidates) == candidates_before

        loop_detection, pose_graph = start_helpers()
        play(6, 10)
        assert spin_until(executor, lambda: len(tracking.loop_link.candidates) > candidates_before, 5.0)
        assert spin_until(executor, lambda: sorted(pose_graph.keyframes) == [6, 8], 5.0)
        before = {k.frame_id: k.cam_to_world.clone() for s in tracking.slam.submaps for k in s.keyframes}
        (_, pose_6), (_, pose_8) = pose_graph.keyframes[6], pose_graph.keyframes[8]  # as the records carried them
        relative = np.linalg.inv(pose_6) @ pose_8 @ _translation(0.05)
        constraint = ma.LoopConstraintRecord(6, 8, 0, 0, relative, 1.0, ma.sigmas_to_information((0.005, 0.01)),
                                             True)  # stands in for registration
        constraint_pub.publish(ma.records_to_pointcloud2([constraint], ma.make_header(1.0, "map")))
        assert spin_until(executor, lambda: tracking.loop_link.pose_graph_updates, 10.0)
        after = {k.frame_id: k.cam_to_world for s in tracking.slam.submaps for k in s.keyframes}
    assert [c.query_keyframe_id for c in tracking.loop_link.candidates] == [2, 8]  # 4 and 6 found no earlier keyframe
    assert tracking.loop_link.candidates[-1].match_keyframe_id == 6
    update = {n.node_id: n.pose for n in tracking.loop_link.pose_graph_updates[0].nodes}
    assert sorted(update) == [6, 8] and pose_graph.updates_published == 1
    np.testing.assert_allclose(after[8].double().numpy(), update[8], atol=1e-6)  # the tracker applied the correction
    assert not np.allclose(after[8].numpy(), before[8].numpy(), atol=1e-4)
    np.testing.assert_allclose(after[0].numpy(), before[0].numpy())  # keyframes the new pose graph never saw stay
    assert tracking.frames_processed == 10 and not tracking.drops.counts
    assert [r.accepted for r in tracking.slam.loop_closure.records] == [False, False]  # both candidates registered


def test_a_loop_candidate_is_registered_optimised_by_pose_graph_and_applied_with_re_mapping():
    """loop_closure: nodes. A candidate (standing in for loop_detection) for keyframes 2 -> 0 of one submap: the
    tracker registers it, re-publishes the submap's keyframes and publishes the constraint; pose_graph answers; the
    tracker moves the keyframes and re-maps the submap."""
    slam = {"mapping.every": 2, "mapping.iterations": 10, "mapping.init_iterations": 30, "device": "cpu",
            "worker.mode": "sync",  # each keyframe's loop answered within its frame, as gausem-ros --lockstep runs
            "backend": "torch", "loop.keyframe_every": 1000, "submaps.min_keyframes": 100,  # one submap
            "loop_closure": "nodes"}
    frames = list(open_source("synthetic", size=(80, 60), max_frames=5))
    with ros_session(110) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(slam))
        graph = PoseGraphNode(context=ctx, parameter_overrides=overrides(slam))
        recorder = Recorder(ctx, [(PointCloud2, "gausem/loop_constraints", EVENT_QOS),
                                  (PointCloud2, "gausem/pose_graph", EVENT_QOS)])
        candidate_pub = recorder.node.create_publisher(PointCloud2, "gausem/loop_candidates", EVENT_QOS)
        player = Player(frames, rate=0.0, lockstep=True, timeout=60.0, context=ctx)
        for node in (tracking, graph, recorder.node, player):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 120.0) and tracking.frames_processed == 5
        assert spin_until(executor, lambda: sorted(graph.keyframes) == [0, 2, 4], 5.0)
        cloud_before = tracking.slam.active.cloud.means.detach().clone()
        poses_before = {k.frame_id: k.cam_to_world.double().clone() for k in tracking.slam.active.keyframes}
        candidate = ma.LoopCandidateRecord(2, 0, 0, 0, 0.1, 0.0, True)
        candidate_pub.publish(ma.records_to_pointcloud2([candidate], ma.make_header(2.0, "map")))
        assert spin_until(executor, lambda: tracking.loop_link.pose_graph_updates, 60.0)
        keyframes = {k.frame_id: k.cam_to_world.double().numpy() for k in tracking.slam.active.keyframes}
        cloud_after = tracking.slam.active.cloud.means.detach()
    record = tracking.slam.loop_closure.records[-1]
    assert (record.query_frame, record.match_frame, record.intra, record.accepted) == (2, 0, True, True)
    constraint = ma.pointcloud2_to_records(recorder.messages["gausem/loop_constraints"][0],
                                           ma.LoopConstraintRecord)[0]
    assert (constraint.keyframe_a, constraint.keyframe_b, constraint.intra_submap) == (0, 2, True)
    truth = np.linalg.inv(frames[0].gt_pose) @ frames[2].gt_pose
    assert np.linalg.norm(constraint.relative_pose[:3, 3] - truth[:3, 3]) < 0.01  # registration measured the motion
    update = {n.node_id: n.pose for n in tracking.loop_link.pose_graph_updates[0].nodes}
    assert sorted(update) == [0, 2, 4]
    for frame_id, pose in update.items():
        np.testing.assert_allclose(keyframes[frame_id], pose, atol=1e-5)  # applied
    # re-mapped when the correction moved a keyframe beyond the loop edges' sigma floors, else left as it was
    reg = tracking.cfg.loop.registration
    changes = [np.linalg.inv(poses_before[k].numpy()) @ keyframes[k] for k in keyframes]
    beyond = any(np.linalg.norm(c[:3, 3]) > reg.sigma_translation
                 or np.arccos(np.clip((np.trace(c[:3, :3]) - 1) / 2, -1, 1)) > reg.sigma_rotation for c in changes)
    remapped = cloud_after.shape != cloud_before.shape or not torch.equal(cloud_after, cloud_before)
    assert remapped == beyond
    assert not tracking.drops.counts and not graph.drops.counts


def test_in_core_mode_the_tracker_closes_loops_itself_and_publishes_them():
    """loop_closure: core (the default): no loop_detection / pose_graph; the core's accepted loop (keyframe 2 -> 0)
    is published."""
    slam = {"mapping.every": 2, "mapping.iterations": 10, "mapping.init_iterations": 30, "device": "cpu",
            "worker.mode": "sync",  # each keyframe's loop answered within its frame, as gausem-ros --lockstep runs
            "backend": "torch", "submaps.min_keyframes": 100, "loop.keyframe_every": 2, "loop.check_every": 1,
            "loop.exclude_recent": 0, "loop.max_fallback_descriptor_distance": 2.0,
            "loop.place_recognition": "descriptor"}  # 80x60 frames hold too few ORB features for the bag of words
    with ros_session(111) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(slam))
        recorder = Recorder(ctx, [(PointCloud2, "gausem/loop_constraints", EVENT_QOS)])
        player = Player(open_source("synthetic", size=(80, 60), max_frames=3), rate=0.0, lockstep=True,
                        timeout=60.0, context=ctx)
        for node in (tracking, recorder.node, player):
            executor.add_node(node)
        assert spin_until(executor, lambda: player.done, 120.0)
        assert spin_until(executor, lambda: recorder.messages["gausem/loop_constraints"], 5.0)
        subscribed = {name for name, _ in tracking.get_subscriber_names_and_types_by_node("tracking_mapping", "/")}
    assert not {"/gausem/loop_candidates", "/gausem/pose_graph"} & subscribed
    assert [(r.query_frame, r.match_frame, r.accepted) for r in tracking.slam.loop_closure.records] == [(2, 0, True)]
    constraint = ma.pointcloud2_to_records(recorder.messages["gausem/loop_constraints"][0], ma.LoopConstraintRecord)
    core = tracking.slam.loop_closure.constraints[0]
    assert [(c.keyframe_a, c.keyframe_b, c.intra_submap) for c in constraint] == [(0, 2, True)]
    np.testing.assert_allclose(constraint[0].relative_pose, core.relative.numpy(), atol=1e-12)


def test_lockstep_goes_on_past_a_frame_the_tracker_drops():
    frames = list(open_source("synthetic", size=(80, 60), max_frames=4))
    bad = frames[1]
    bad.messages = [(key, ma.depth_to_image(np.zeros((60, 80), np.float32), msg.header) if key == "depth" else msg)
                    for key, msg in bad.messages]
    with ros_session(109) as (ctx, executor):
        tracking = TrackingMappingNode(context=ctx, parameter_overrides=overrides(FAST_SLAM))
        player = Player(frames, rate=0.0, lockstep=True, timeout=60.0, context=ctx)
        executor.add_node(tracking)
        executor.add_node(player)
        assert spin_until(executor, lambda: player.done, 30.0)  # the drop, reported on gausem/diagnostics, answers
    assert player.timeouts == 0 and player.odometry_received == tracking.frames_processed == 3
    assert tracking.drops.counts == {"invalid_depth": 1}
