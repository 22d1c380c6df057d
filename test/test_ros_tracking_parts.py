"""The tracking node's parts (gausem_ros/nodes/tracking/), each on its own: what it publishes, counts and rejects."""
import dataclasses
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("rclpy")

import rclpy  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

import msg_adapters as ma  # noqa: E402
from gausem_core.config import SlamConfig, flatten, from_flat  # noqa: E402
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset  # noqa: E402
from gausem_core.gaussians import GaussianCloud  # noqa: E402
from gausem_core.geometry import PinholeCamera, rigid_float64  # noqa: E402
from gausem_core.slam.events import Correction, FrameEvents  # noqa: E402
from gausem_core.slam.health import TrackingHealth  # noqa: E402
from gausem_core.slam.observation import Observation  # noqa: E402
from gausem_core.slam.relocalisation import RelocalisationResult  # noqa: E402
from gausem_core.slam.submap import Submap  # noqa: E402
from gausem_core.slam.submap_store import SubmapStore  # noqa: E402
from gausem_core.slam.system import GauSemSLAM  # noqa: E402
from gausem_ros.nodes.common import LAST_FRAME_KEY, AccountingLock, DropReport, FrameRejected  # noqa: E402
from gausem_ros.nodes.tracking.checkpoints import SessionCheckpoints  # noqa: E402
from gausem_ros.nodes.tracking.diagnostics import FrameAccounting, core_status, unpublished  # noqa: E402
from gausem_ros.nodes.tracking.frame_input import FrameInput  # noqa: E402
from gausem_ros.nodes.tracking.loop_link import LoopNodesLink  # noqa: E402
from gausem_ros.nodes.tracking.map_outputs import MapPublisher  # noqa: E402
from gausem_ros.nodes.tracking.parameters import NODE_DEFAULTS, check_parameters  # noqa: E402
from gausem_ros.nodes.tracking.records import RecordPublisher  # noqa: E402
from gausem_ros.nodes.tracking.services import MapServices  # noqa: E402
from gausem_ros.nodes.tracking.trajectory import DEGRADED_VARIANCE, TrajectoryPublisher  # noqa: E402
from gausem_ros.qos import EVENT_QOS, IMAGE_QOS, LATCHED_QOS  # noqa: E402
from ros_harness import FAST_SLAM, Recorder, ros_session, spin_for, spin_until  # noqa: E402


@pytest.fixture(autouse=True)
def _localhost(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def params(**values) -> SimpleNamespace:
    """The node's parameters: the defaults with ``values``."""
    return SimpleNamespace(**{**NODE_DEFAULTS, **values})


@pytest.fixture(scope="module")
def mapped():
    """A core (sync) after 5 synthetic frames at 80x60, keyframes 0, 2 and 4: (slam, its frame results)."""
    cfg = from_flat({**flatten(SlamConfig()), **FAST_SLAM, "mapping.every": 2, "worker.mode": "sync"})
    data = SyntheticDataset("default", resolution=(80, 60))
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(SYNTHETIC_CLASSES.palette))
    results = [slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                                    f.timestamp)) for f in (data[i] for i in range(5))]
    yield slam, results
    slam.close()


def test_records_go_out_one_message_per_kind_and_none_for_no_events(mapped):
    slam, results = mapped
    with ros_session(201) as (ctx, executor):
        node = rclpy.create_node("parts", context=ctx)
        records = RecordPublisher(node)
        recorder = Recorder(ctx, [(PointCloud2, topic, EVENT_QOS)
                                  for topic in ("gausem/keyframes", "gausem/submaps", "gausem/loop_constraints")])
        for n in (node, recorder.node):
            executor.add_node(n)
        assert spin_until(executor, records.constraint_listened, 5.0)
        header = ma.make_header(1.0, "map")
        first = results[0].events
        assert first.keyframe is not None and first.submaps
        records.publish_events(first, header)
        records.publish_events(FrameEvents(), header)  # nothing happened: nothing goes out
        records.publish_loop(None, header)
        records.publish_keyframes(slam.keyframe_states(), header)  # all of them, as they are now
        assert spin_until(executor, lambda: len(recorder.messages["gausem/keyframes"]) == 2, 5.0)
        spin_for(executor, 0.2)
        submaps = [ma.pointcloud2_to_records(m, ma.SubmapEvent) for m in recorder.messages["gausem/submaps"]]
        assert [[(e.submap_id, e.kind) for e in m] for m in submaps] == [[(0, ma.SubmapEventKind.CREATED)]]
        one, every = (ma.pointcloud2_to_records(m, ma.KeyframeRecord) for m in recorder.messages["gausem/keyframes"])
        assert [r.keyframe_id for r in one] == [0] and [r.keyframe_id for r in every] == [0, 2, 4]
        state = slam.keyframe_states()[1]
        assert np.array_equal(every[1].pose, state.pose.numpy()) and every[1].stamp == state.timestamp
        assert not recorder.messages["gausem/loop_constraints"]


def test_trajectory_publishes_odometry_and_a_growing_path_rebuilt_after_a_correction(mapped):
    slam, results = mapped
    with ros_session(202) as (ctx, executor):
        node = rclpy.create_node("parts", context=ctx)
        trajectory = TrajectoryPublisher(node, params(), None)
        trajectory.reset(slam)
        recorder = Recorder(ctx, [(Odometry, "gausem/odometry", EVENT_QOS), (Path, "gausem/path", LATCHED_QOS)])
        for n in (node, recorder.node):
            executor.add_node(n)
        stamps = [t for t, _ in slam.trajectory()]
        for result, stamp in zip(results[:3], stamps):
            pose = rigid_float64(result.cam_to_world).numpy()
            trajectory.publish_odometry(pose, stamp, "cam", degraded=result.frame_id == 1)
            trajectory.publish_motion(result, pose, stamp)
        assert spin_until(executor, lambda: len(recorder.messages["gausem/odometry"]) == 3, 5.0)
        odometry = recorder.messages["gausem/odometry"]
        assert [(m.header.frame_id, m.child_frame_id) for m in odometry] == [("map", "cam")] * 3
        assert not np.any(odometry[0].pose.covariance)
        assert np.array_equal(np.reshape(odometry[1].pose.covariance, (6, 6)), DEGRADED_VARIANCE * np.eye(6))
        # a new map's first path is built from the core's trajectory (here already five frames), then each frame
        # appends its pose
        assert spin_until(executor, lambda: len(recorder.messages["gausem/path"][-1].poses) == 7, 5.0)
        trajectory.note_events(SimpleNamespace(loop=SimpleNamespace(correction=Correction(1, 0))))
        trajectory.publish_path()  # rebuilt from the whole trajectory, as corrected
        assert spin_until(executor, lambda: len(recorder.messages["gausem/path"][-1].poses) == 5, 5.0)
        path = recorder.messages["gausem/path"][-1]
        assert [ma.header_seconds(p.header) for p in path.poses] == pytest.approx(stamps)


class SlowMap:
    """A core of one active submap whose Gaussians take until ``release`` is set to read."""

    def __init__(self):
        self.reading, self.release = threading.Event(), threading.Event()
        self.lock = threading.RLock()
        self.submaps = [SimpleNamespace(submap_id=0, version=0, is_active=True, anchor=torch.eye(4),
                                        load_cloud=self.load_cloud)]

    def load_cloud(self, device=None):
        del device
        self.reading.set()
        assert self.release.wait(10.0)
        return GaussianCloud.empty()


def random_cloud(count: int, seed: int) -> GaussianCloud:
    """``count`` Gaussians in the unit cube, random colours, opacities, radii and classes of the synthetic table."""
    g = torch.Generator().manual_seed(seed)
    palette = SYNTHETIC_CLASSES.palette.float()
    return GaussianCloud.from_points(torch.rand(count, 3, generator=g), torch.rand(count, 3, generator=g),
                                     palette[torch.randint(len(palette), (count,), generator=g)],
                                     torch.rand(count, generator=g) * 0.01 + 0.005, torch.rand(count, generator=g))


def test_the_map_message_reads_a_spilled_submap_only_when_its_gaussians_changed(tmp_path):
    """Issue 63: the map publisher read every submap each period, those spilled to disk included, and joined them all
    into one cloud. Now an inactive submap's points are kept in its frame: a loop closure's new anchor moves them
    without a read, new Gaussians (a new version) are read once; with map_voxel_size, one point per voxel."""
    store = SubmapStore(0, tmp_path)  # every inactive submap's tensors spilled to disk at once
    clouds = [random_cloud(400, seed) for seed in range(3)]
    anchors = [torch.eye(4) for _ in clouds]
    for k, anchor in enumerate(anchors):
        anchor[:3, 3] = torch.tensor([2.0 * k, 0.0, 0.0])
    submaps = [Submap(k, anchor, cloud) for k, (anchor, cloud) in enumerate(zip(anchors, clouds))]
    for submap in submaps[:2]:
        submap.offload(store)
    reads = []
    read = store.read
    store.read = lambda key, device="cpu": (reads.append(key), read(key, device))[1]
    slam = SimpleNamespace(lock=threading.RLock(), submaps=submaps)
    with ros_session(207) as (ctx, _):
        node = rclpy.create_node("parts", context=ctx)
        for voxel in (0.0, 0.25):
            outputs = MapPublisher(node, params(map_voxel_size=voxel, grid_publish_period=0.0),
                                   from_flat(flatten(SlamConfig())).grid, SYNTHETIC_CLASSES.palette, None, None,
                                   lambda: 1.0)
            outputs.reset(slam)
            reads.clear()
            points = outputs.map_points()
            assert reads == [("cloud", 0), ("cloud", 1)] and all(store.on_disk(key) for key in reads)
            expected = [ma.cloud_to_points(c, SYNTHETIC_CLASSES.palette, voxel) for c in clouds]
            assert len(points) == sum(map(len, expected))
            assert len(points) == 1200 if not voxel else len(points) <= 3 * 4 ** 3
            assert np.allclose(points["x"][:len(expected[0])], expected[0]["x"])
            submaps[1].anchor = submaps[1].anchor.clone()
            submaps[1].anchor[2, 3] = 1.0  # a loop closure moves submap 1
            moved = outputs.map_points()
            assert len(reads) == 2 and np.allclose(moved["z"] - points["z"], np.repeat([0.0, 1.0, 0.0],
                                                                                        list(map(len, expected))))
            submaps[0].cloud = clouds[2]  # new Gaussians of submap 0 (refined after a loop): read once
            assert len(outputs.map_points()) == len(points) - len(expected[0]) + len(expected[2])
            assert reads == [("cloud", 0), ("cloud", 1), ("cloud", 0)]
            submaps[0].cloud = clouds[0]
            submaps[1].anchor = anchors[1]
    store.close()


def test_the_map_is_built_off_the_frame_path_and_only_after_it_changed():
    """While the map timer builds the map, callbacks of the node's default group (where frames are processed) go on;
    an unchanged map is not published again; without grid_publish_period there is no grid."""
    slam = SlowMap()
    with ros_session(203) as (ctx, executor):
        node = rclpy.create_node("parts", context=ctx)
        outputs = MapPublisher(node, params(map_publish_period=0.05, grid_publish_period=0.0),
                               from_flat(flatten(SlamConfig())).grid, SYNTHETIC_CLASSES.palette, None, None,
                               lambda: 1.0)
        outputs.reset(slam)
        frames = []
        node.create_timer(0.01, lambda: frames.append(time.monotonic()))  # the default group, as the frame queue
        recorder = Recorder(ctx, [(PointCloud2, "gausem/map", LATCHED_QOS)])
        for n in (node, recorder.node):
            executor.add_node(n)
        outputs.map_changed()
        outputs.grid_changed()
        assert not outputs.grid_dirty  # no grid to rebuild
        assert spin_until(executor, slam.reading.is_set, 5.0)
        during = len(frames)
        spin_for(executor, 0.3)
        assert len(frames) >= during + 5  # the frame path went on while the map was being read
        slam.release.set()
        assert spin_until(executor, lambda: recorder.messages["gausem/map"], 5.0)
        spin_for(executor, 0.3)  # six periods, the map unchanged
        assert len(recorder.messages["gausem/map"]) == 1
        assert recorder.messages["gausem/map"][0].header.frame_id == "map"


def test_the_loop_link_awaits_loop_detection_and_counts_bad_answers(mapped):
    """A place signature goes out flagged as the map's first, then not; the next frame waits (settled false) while
    loop_detection listens, until its candidates for that keyframe arrive; malformed answers are rejected and wake
    the waiting frame; an empty pose-graph answer is applied without moving the map."""
    slam, _ = mapped
    place = slam.loop_closure.stored_places()[0]
    with ros_session(204) as (ctx, executor):
        node = rclpy.create_node("parts", context=ctx)
        drops = DropReport(node)
        wakes, moved = [], []
        link = LoopNodesLink(node, params(), RecordPublisher(node), drops, lambda: wakes.append(1), lambda: 1.0,
                             lambda: moved.append(1))
        link.reset(slam)
        recorder = Recorder(ctx, [(PointCloud2, "gausem/place_signatures", EVENT_QOS)])
        answers = {topic: recorder.node.create_publisher(PointCloud2, topic, EVENT_QOS)
                   for topic in ("gausem/loop_candidates", "gausem/pose_graph")}
        for n in (node, recorder.node):
            executor.add_node(n)
        assert spin_until(executor, lambda: all(p.get_subscription_count() for p in answers.values()), 5.0)
        stamp = 2.5
        link.publish_place(place, stamp)
        link.publish_place(place, stamp)
        assert not link.settled()
        assert spin_until(executor, lambda: len(recorder.messages["gausem/place_signatures"]) == 2, 5.0)
        sent = [ma.pointcloud2_to_records(m, ma.PlaceSignatureRecord)[0]
                for m in recorder.messages["gausem/place_signatures"]]
        assert [(r.keyframe_id, r.new_map, r.loaded) for r in sent] == [(place.keyframe_id, True, False),
                                                                         (place.keyframe_id, False, False)]
        header = ma.make_header(stamp, "map")
        answers["gausem/loop_candidates"].publish(ma.records_to_pointcloud2([], header, ma.LoopCandidateRecord))
        assert spin_until(executor, link.settled, 5.0) and wakes
        answers["gausem/pose_graph"].publish(ma.records_to_pointcloud2([], header, ma.KeyframeRecord))  # not one
        assert spin_until(executor, lambda: drops.rejected["bad_pose_graph"] == 1, 5.0)
        answers["gausem/pose_graph"].publish(ma.pose_graph_update_to_pointcloud2(ma.PoseGraphUpdate(()), header))
        assert spin_until(executor, lambda: len(link.pose_graph_updates) == 1, 5.0)
        assert not moved and len(wakes) >= 3


class CountingSlam:
    """What checkpoints read of a core: its keyframes, frames and ``save``."""

    def __init__(self, fail: bool = False):
        self.submaps, self.frames, self.saved, self.fail = [SimpleNamespace(keyframes=[])], [], [], fail

    def step(self, keyframe: bool) -> None:
        self.frames.append(len(self.frames))
        if keyframe:
            self.submaps[0].keyframes.append(len(self.frames))

    def save(self, folder) -> None:
        self.saved.append(len(self.frames))
        if self.fail:
            raise OSError("disk full")


def test_checkpoints_every_few_keyframes_and_survive_a_failed_write(tmp_path):
    with ros_session(205) as (ctx, _):
        node = rclpy.create_node("parts", context=ctx)
        checkpoints = SessionCheckpoints(node.get_logger(), params(map_path=str(tmp_path), checkpoint_keyframes=2,
                                                                   checkpoint_period=0.0))
        slam = CountingSlam()
        checkpoints.reset(slam)
        for keyframe in (True, False, True, True, False):
            slam.step(keyframe)
            checkpoints.after_frame()
        assert slam.saved == [3]  # the second new keyframe
        assert checkpoints.status() == {"checkpoint.written": 1, "checkpoint.frames": 3,
                                        "checkpoint.seconds_last": checkpoints.stats.seconds_last}
        failing = CountingSlam(fail=True)
        checkpoints.reset(failing)
        for _ in range(3):
            failing.step(True)
            checkpoints.after_frame()  # logged; tried again two keyframes later, not at every frame
        assert failing.saved == [2] and checkpoints.stats.written == 1


def synchroniser() -> SimpleNamespace:
    """What the accounting reads of the synchroniser: 7 rgb images received, 1 lost, 2 unmatched ones waiting."""
    return SimpleNamespace(names=["rgb", "depth"], received=[7, 7], lost=[1, 0], pending=lambda index: 2,
                           dropped={("depth", "unmatched"): 2, ("rgb", "unmatched"): 1})


def test_the_frame_accounting_adds_up_and_says_why_a_frame_publishes_nothing(mapped):
    slam, results = mapped
    with ros_session(206) as (ctx, _):
        node = rclpy.create_node("parts", context=ctx)
        lock = AccountingLock()
        drops = DropReport(node, lock=lock)
        queue = SimpleNamespace(pending=1, in_progress=1, settle=lambda: setattr(queue, "in_progress", 0))
        accounting = FrameAccounting(synchroniser(), queue, drops, lock)
        for arrived in (time.monotonic() - 0.1, time.monotonic() - 0.2):
            queue.in_progress = 1
            accounting.published(arrived)
        accounting.handled_ns = 42
        drops.drop("superseded", "test")
        status = accounting.status({"tracking.status": "ok"})
        assert status["frames_in"] == 8 and status["frames_processed"] == 2 and status["frames_pending"] == 3
        assert status[LAST_FRAME_KEY] == 42 and status["tracking.status"] == "ok"
        assert 100 <= status["latency_ms.median"] <= status["latency_ms.p95"]
        assert status["sync.depth.unmatched"] == 2 and "sync.rgb.unmatched" not in status
        summary = accounting.summary()
        assert summary["dropped"] == {"superseded": 1} and summary["frames_in"] == 8
        accounting.clear()
        assert accounting.summary()["frames_processed"] == 0 and "latency_ms.median" not in accounting.summary()

    pose = rigid_float64(results[1].cam_to_world).numpy()
    assert unpublished(results[1], pose, 1.0) is None
    lost = dataclasses.replace(results[1], health=TrackingHealth("lost", reasons=("jump",)))
    assert unpublished(lost, pose, 1.0)[0] == "tracking_lost"
    assert unpublished(results[1], np.full((4, 4), np.nan), 1.0)[0] == "tracking_diverged"
    failed = RelocalisationResult(False, results[1].cam_to_world, 0.1, 1.0, 5, "last pose", 0, 3)
    assert unpublished(dataclasses.replace(results[1], relocalisation=failed), pose, 1.0)[0] == "relocalisation_failed"

    status = core_status(slam, TrackingHealth("degraded", inlier_fraction=0.5), 3, True)
    assert status["tracking.status"] == "degraded" and status["tracking.inlier_fraction"] == 0.5
    assert status["camera.vignetting_corner_gain"] == pytest.approx(np.exp(slam.vignetting.a))
    assert status["camera.undistorted"] is True and status["worker.map_age_frames"] == 3
    assert status["worker.mode"] == "sync" and "worker.queue_depth" not in status  # no worker in sync mode


def test_frame_input_rejects_what_the_core_cannot_take_and_resizes_a_scaled_camera():
    camera = PinholeCamera(40.0, 40.0, 20.0, 15.0, 40, 30)
    with ros_session(207) as (ctx, _):
        node = rclpy.create_node("parts", context=ctx)
        drops = DropReport(node)
        frames = FrameInput(node, params(max_image_pixels=60 * 45), SYNTHETIC_CLASSES.palette, torch.device("cpu"),
                            drops, IMAGE_QOS, None)

        def messages(stamp, cam=camera, label=0):
            header = ma.make_header(stamp, "cam")
            shape = (cam.height, cam.width)
            return (ma.rgb_to_image(np.zeros((*shape, 3), np.uint8), header),
                    ma.numpy_to_image(np.full(shape, 2.0, np.float32), "32FC1", header),
                    ma.labels_to_image(np.full(shape, label, np.int64), header))

        def rejected(reason, *args):
            with pytest.raises(FrameRejected) as err:
                frames.observation(*args)
            return err.value.reason == reason

        assert rejected("no_camera_info", messages(1.0), -np.inf, None)
        bad = ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam"))
        bad.d = [0.1, 0.2]
        frames.camera_info(bad)
        assert drops.rejected["bad_camera_info"] == 1 and frames.camera is None
        frames.camera_info(ma.camera_to_camera_info(camera, ma.make_header(1.0, "cam")))
        assert frames.camera == camera and frames.lens_distortion == ()
        assert rejected("stale_stamp", messages(1.0), 1.0, None)
        assert rejected("bad_labels", messages(1.0, label=len(SYNTHETIC_CLASSES.palette)), 0.0, None)
        assert frames.observation(messages(1.0), 0.0, None).camera == camera
        big = camera.scaled(80, 60)  # above max_image_pixels: downscaled, then into the map's camera
        frames.camera_info(ma.camera_to_camera_info(big, ma.make_header(1.0, "cam")))
        assert frames.observation(messages(1.0, big), 0.0, camera).camera == camera
        assert tuple(frames.observation(messages(1.0, big), 0.0, None).depth.shape) == (45, 60)
        other = PinholeCamera(60.0, 60.0, 20.0, 15.0, 40, 30)
        frames.camera_info(ma.camera_to_camera_info(other, ma.make_header(1.0, "cam")))
        assert rejected("camera_changed", messages(1.0, other), 0.0, camera)


@pytest.mark.parametrize("values, names", [({"loop_closure": "both"}, "loop_closure"),
                                           ({"min_image_size": 4}, "min_image_size"),
                                           ({"max_image_pixels": 100}, "max_image_pixels"),
                                           ({"grid_frame": "odom"}, "grid_frame"),
                                           ({"sync_wait": -1.0}, "sync_wait"),
                                           ({"grid_publish_period": -1.0}, "grid_publish_period")])
def test_parameters_that_cannot_work_are_refused_naming_them(values, names):
    cfg = from_flat(flatten(SlamConfig()))
    check_parameters(cfg, params())
    with pytest.raises(ValueError, match=f"tracking_mapping: {names}"):
        check_parameters(cfg, params(**values))


def test_the_services_answer_with_what_their_action_did_or_why_it_failed(tmp_path):
    """Each trigger runs the node's action and answers success with what it did, or failure naming the folder and
    the error (a map that cannot be written or read stays as it is)."""
    with ros_session(208) as (ctx, executor):
        node = rclpy.create_node("parts", context=ctx)
        node.declare_parameter("map_path", str(tmp_path / "no_session"))
        done = []

        def save_map(folder):
            raise OSError("read-only file system")
        node.params, node.save_map = params(output_dir=str(tmp_path)), save_map
        node.slam = SimpleNamespace(submaps=[0])
        node.finish, node.reset = (lambda: done.append("finish")), (lambda: done.append("reset"))
        node.device, node.cfg = "cpu", None
        MapServices(node)
        client_node = rclpy.create_node("client", context=ctx)
        for n in (node, client_node):
            executor.add_node(n)

        def call(name: str):
            future = client_node.create_client(Trigger, name).call_async(Trigger.Request())
            assert spin_until(executor, future.done, 10.0)
            return future.result().success, future.result().message

        assert call("gausem/save_map") == (False, f"could not write to {tmp_path}: read-only file system")
        success, message = call("gausem/load_map")
        assert not success and message.startswith(f"could not load {tmp_path / 'no_session'}: ")
        assert call("gausem/finish") == (True, "global refinement done over 1 submaps")
        assert call("gausem/reset") == (True, "map and trajectory cleared") and done == ["finish", "reset"]
