"""The mapping worker (``worker.mode: async``): its queue on its own, then GauSemSLAM tracking while the worker maps,
opens submaps and closes a loop."""
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from gausem_core.config import from_flat, load_config
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose
from gausem_core.live import LiveCamera, frame_bytes
from gausem_core.slam.depth_filter import filter_observation
from gausem_core.slam.observation import Observation
from gausem_core.slam.submap import Submap
from gausem_core.slam.submap_store import SubmapStore
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import TrackingResult
from gausem_core.slam.worker import Job, MappingWorker, split_threads

REPO = Path(__file__).resolve().parents[1]


def wait_for(condition, seconds: float = 10) -> bool:
    """Whether ``condition()`` came true within ``seconds``."""
    for _ in range(int(seconds / 0.01)):
        if condition():
            return True
        threading.Event().wait(0.01)
    return False


def wait_until_running(worker: MappingWorker) -> None:
    assert wait_for(lambda: worker.depth == 0 and not worker.idle), "the worker never took the job"


class Gate:
    """Jobs that block until released, recording the order they ran in."""

    def __init__(self):
        self.ran, self.release = [], threading.Event()

    def job(self, frame: int, kind: str = "keyframe") -> Job:
        def run():
            self.release.wait(10)
            self.ran.append(frame)
            return frame
        return Job(frame, kind, run)


def test_a_full_queue_supersedes_the_newest_waiting_keyframe_and_counts_it():
    gate, frames = Gate(), [0]
    worker = MappingWorker(lambda: frames[0], queue_size=2)
    worker.submit(gate.job(0, "open"))
    wait_until_running(worker)  # blocked in the job
    assert worker.submit(gate.job(1)) is None and worker.submit(gate.job(2)) is None
    assert worker.pressure.is_set()  # newer keyframes wait behind the running one
    superseded = worker.submit(gate.job(3))
    assert superseded is not None and superseded.frame == 2
    assert worker.depth == 2
    frames[0] = 10
    gate.release.set()
    assert worker.drain(10)
    assert gate.ran == [0, 1, 3] and worker.take_events() == [0, 1, 3] and worker.take_events() == []
    assert worker.stats.submitted == 4 and worker.stats.superseded == 1 and worker.stats.mapped == 3
    assert worker.stats.lag_frames == [9, 8, 6]  # frames the tracker had processed past each keyframe
    assert not worker.pressure.is_set()
    worker.stop()


def test_a_map_opening_job_is_never_superseded():
    gate = Gate()
    worker = MappingWorker(lambda: 0, queue_size=1)
    worker.submit(gate.job(0))
    wait_until_running(worker)
    worker.submit(gate.job(1, "open"))
    assert worker.submit(gate.job(2)) is None  # the waiting job opens a map: the new one queues behind it
    gate.release.set()
    worker.drain(10)
    assert gate.ran == [0, 1, 2]
    worker.stop()


def test_a_job_error_reaches_the_caller_once():
    def fail():
        raise ValueError("bad keyframe")
    worker = MappingWorker(lambda: 0)
    worker.submit(Job(0, "keyframe", fail))
    with pytest.raises(RuntimeError, match="bad keyframe"):
        worker.drain(10)
    worker.drain(10)  # raised once; the worker goes on
    worker.submit(Job(1, "keyframe", lambda: "ok"))
    worker.drain(10)
    assert worker.take_events() == ["ok"]
    worker.stop()


def test_the_trackers_gaussians_wait_pending_and_survive_the_workers_optimisation():
    """A submap's Gaussians from two threads: grown ones are part of the map at once; the worker takes them in before
    it optimises and assigns its result back, and what grew meanwhile stays; an offloaded submap takes its pending
    Gaussians with it and grows no more."""
    def cloud(n, x=0.0):
        return GaussianCloud.from_points(torch.full((n, 3), x), torch.rand(n, 3), torch.rand(n, 3), torch.ones(n),
                                         torch.full((n,), 0.5))
    submap = Submap(0, torch.eye(4), cloud(3))
    assert submap.grow(lambda current: cloud(2, 1.0) if len(current) == 3 else None) == 2
    assert len(submap.cloud) == submap.num_gaussians == 5 and float(submap.cloud.means[3:, 0].min()) == 1.0
    taken = submap.take_cloud()  # the worker's optimisation starts
    assert len(taken) == 5
    assert submap.grow(lambda current: cloud(4, 2.0)) == 4  # the tracker meanwhile
    submap.cloud = cloud(5, 9.0)  # the optimised Gaussians come back
    assert len(submap.cloud) == submap.num_gaussians == 9
    assert submap.cloud.means[:, 0].tolist() == [9.0] * 5 + [2.0] * 4
    store = SubmapStore(2**20)
    submap.offload(store)
    assert len(submap.cloud) == 9 and submap.grow(lambda current: cloud(1)) == 0 and len(submap.cloud) == 9
    store.close()


def test_between_jobs_the_worker_does_its_idle_work_until_it_has_none_left():
    rounds = []
    worker = MappingWorker(lambda: 0, idle=lambda: rounds.append(1) or len(rounds) % 4 != 0)
    threading.Event().wait(0.05)
    assert rounds == []  # nothing to refine before the first job
    worker.submit(Job(0, "open", lambda: "opened"))
    assert wait_for(lambda: len(rounds) == 4 and worker.idle)
    threading.Event().wait(0.05)
    assert len(rounds) == 4  # it said there was nothing left: the worker waits for the next job
    worker.submit(Job(1, "keyframe", lambda: "mapped"))
    assert wait_for(lambda: len(rounds) == 8 and worker.idle)
    assert worker.take_events() == ["opened", "mapped"]
    worker.stop()


def test_a_drain_holds_the_idle_work_until_the_next_job():
    rounds = []
    worker = MappingWorker(lambda: 0, idle=lambda: rounds.append(1) or threading.Event().wait(0.001) or True)
    worker.submit(Job(0, "open", lambda: None))
    assert wait_for(lambda: len(rounds) >= 3)
    assert worker.drain(10)  # waits for the round in progress, then holds
    held = len(rounds)
    threading.Event().wait(0.05)
    assert len(rounds) == held and worker.idle
    worker.submit(Job(1, "keyframe", lambda: None))
    assert wait_for(lambda: len(rounds) > held)
    worker.stop()


def test_threads_split_the_cores_and_keep_what_is_given():
    tracker, worker = split_threads(0, 0)
    assert tracker >= 1 and worker >= 1
    assert split_threads(3, 2) == (3, 2)


def test_queue_size_is_checked():
    with pytest.raises(ValueError, match="queue_size"):
        MappingWorker(lambda: 0, queue_size=0)


class Frames:
    """A dataset of the first ``count`` frames, stamped ``interval`` seconds apart."""

    def __init__(self, data, count: int, interval: float):
        self.frames = [data[i] for i in range(count)]
        for n, frame in enumerate(self.frames):
            frame.timestamp = n * interval

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        return self.frames[i]


def test_the_live_camera_hands_out_the_newest_frame_and_counts_the_superseded():
    camera = LiveCamera(Frames(SyntheticDataset("default", resolution=(20, 15)), 12, 0.01), rate=1.0)
    camera.start()
    taken = [camera.take()]  # then a consumer busy until the camera has released every frame
    for _ in range(1000):
        if camera.ended_at is not None:
            break
        threading.Event().wait(0.01)
    while (item := camera.take()) is not None:
        taken.append(item)
    camera.stop()
    positions = [t.position for t in taken]
    assert positions == sorted(positions) and positions[0] == 0 and positions[-1] == 11
    assert camera.released == 12 and len(taken) < 12
    assert camera.superseded == 12 - len(taken) == sum(t.superseded for t in taken)
    with pytest.raises(ValueError, match="positive rate"):
        LiveCamera([], 0)


class CountingReads(Frames):
    """Frames that count how often each is read."""

    def __init__(self, *args):
        super().__init__(*args)
        self.reads = [0] * len(self.frames)

    def __getitem__(self, i):
        self.reads[i] += 1
        return self.frames[i]


@pytest.mark.parametrize("fit", [0, 3, 12])
def test_the_live_camera_reads_the_frames_that_fit_its_budget_before_the_clock_starts(fit):
    frames = CountingReads(SyntheticDataset("default", resolution=(20, 15)), 12, 0.001)
    camera = LiveCamera(frames, rate=1.0, preload_bytes=fit * frame_bytes(frames.frames[0]))
    camera.start()
    assert camera.preloaded == fit and camera.started_at is not None
    while camera.take() is not None:
        pass
    camera.stop()
    assert camera.released == 12
    assert frames.reads[:fit] == [1] * fit  # each read once, before the clock
    assert frames.reads[fit + 1:] == [1] * (11 - fit)  # the rest as they come due


CHEAP = {"backend": "torch", "device": "cpu", "mapping.every": 2, "mapping.iterations": 5,
         "mapping.init_iterations": 20, "mapping.init_samples_fraction": 0.5, "submaps.policy": "motion",
         "submaps.motion_translation": 0.15, "submaps.boundary_iterations": 5, "loop.enabled": False,
         "refinement.enabled": False, "worker.mode": "async", "worker.publish_every": 5,
         "tracking.feature_start.mode": "never"}


def test_async_tracks_every_frame_while_the_worker_opens_submaps():
    """The real tracker on the synthetic walk's first 20 frames (80x60, params/synthetic.yaml made cheaper): the map's
    first Gaussians are published after ``publish_every`` steps and tracked against at once; new submaps are opened
    on the worker; every keyframe's events come back once, in order (with later frames or after finish); the
    trajectory is within a few centimetres of the truth, as the same run in sync."""
    data = SyntheticDataset("default", resolution=(80, 60))
    frames = [data[i] for i in range(20)]
    first = torch.tensor(frames[0].gt_pose)
    truth = [(invert_pose(first) @ torch.tensor(f.gt_pose)).float() for f in frames]
    errors = {}
    for mode in ("sync", "async"):
        cfg = load_config(REPO / "params" / "synthetic.yaml", {
            "device": "cpu", "worker.mode": mode, "worker.publish_every": 10, "mapping.init_iterations": 60,
            "mapping.iterations": 10, "submaps.policy": "motion", "submaps.motion_translation": 0.1,
            "loop.enabled": False, "refinement.enabled": False})
        slam = GauSemSLAM(cfg, "cpu", len(SYNTHETIC_CLASSES))
        results = [slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera,
                                                        SYNTHETIC_CLASSES.palette, f.timestamp)) for f in frames]
        assert slam.asynchronous == (mode == "async")
        slam.finish()
        events = [e for r in results for e in (r.events, *r.mapped) if e.keyframe is not None] + \
            list(slam.take_mapped())
        keyframes = [r.frame_id for r in results if r.is_keyframe]
        assert [e.keyframe.frame_id for e in events] == keyframes  # each keyframe's events once, in order
        assert all(r.health.status != "lost" for r in results)
        assert len(slam.submaps) >= 3 and sum(c.opened for e in events for c in e.submaps) == len(slam.submaps)
        estimate = [pose for _, pose in slam.trajectory()]
        errors[mode] = max(float((e[:3, 3] - t[:3, 3]).norm()) for e, t in zip(estimate, truth))
        assert len(slam.front_end.tracking_seconds) == len(frames) - 1  # every frame after the first, timed
        assert len(slam.back_end.mapping_seconds) == len(keyframes)  # every keyframe's mapping, where it ran
        assert min(slam.front_end.tracking_seconds) > 0 and min(slam.back_end.mapping_seconds) > 0
        if mode == "async":
            stats = slam.back_end.worker.stats
            assert stats.mapped == len(keyframes) and stats.superseded == 0
        slam.close()
    assert errors["async"] < 0.05 and errors["sync"] < 0.05, errors  # metres, worst frame


class InitOdometry:
    """Drifting odometry relative to the start the system gives (the last frame's pose in the frame of the submap
    it tracks against), so that it works whatever submap the worker has published."""

    def __init__(self, truth, bias):
        self.truth, self.bias, self.n = truth, bias, 0

    def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None) -> TrackingResult:
        self.n += 1
        step = invert_pose(self.truth[self.n - 1]) @ self.truth[self.n] @ self.bias
        from test_loop_e2e import rigid

        return TrackingResult(rigid(init_cam_to_world @ step), 0.0, 0)


def odometry_loop_run(mode: str, pace: bool) -> tuple[GauSemSLAM, list, list]:
    """test_loop_e2e's drifting walk around the loop and back, tracked by the test's odometry in ``mode`` with a queue
    deep enough to keep every keyframe (with ``pace``, a pause every 4 frames: the worker maps while frames go on
    arriving). Returns the finished system, each frame's result and the ground truth."""
    from test_loop_e2e import BIAS, CONFIG, RATE, revisit_frames

    _, frames = revisit_frames()
    first = torch.tensor(frames[0].gt_pose)
    truth = [(invert_pose(first) @ torch.tensor(f.gt_pose)).float() for f in frames]
    cfg = from_flat({**CONFIG, "worker.mode": mode, "worker.queue_size": 1000, "tracking.constant_velocity": False,
                     "tracking.feature_start.mode": "never", "worker.publish_every": 5,
                     # the odometry is given: a map still being optimised must not have it judged lost
                     "health.lost_inlier_fraction": 0.0, "health.lost_jump": 1e9, "health.lost_valid_depth": 0.0,
                     "health.lost_coverage": 0.0})
    slam = GauSemSLAM(cfg, "cpu", len(SYNTHETIC_CLASSES))
    slam.front_end.tracker = InitOdometry(truth, BIAS)
    results = []
    for n, f in enumerate(frames):
        results.append(slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera,
                                                            SYNTHETIC_CLASSES.palette, n / RATE)))
        if pace and n % 4 == 3:
            threading.Event().wait(0.5)
    return slam, results, truth


@pytest.mark.slow
def test_async_closes_a_loop_while_frames_keep_coming():
    """The worker opens submaps and closes the revisit while the tracker has gone on; the correction reaches the
    later frames and the loop's events arrive with a frame, not only at the end. The pose graph spreads a loop found
    at the walk's end over its submaps, which removes about half the drift in lock-step: async does as well, within
    the spread that the worker's timing gives its maps (anytime mapping)."""
    from test_loop_e2e import ate_rmse, integrate_odometry

    slam, results, truth = odometry_loop_run("async", pace=True)
    during = [e for r in results for e in r.mapped]
    slam.finish()
    assert slam.loop_closure.loops, "no loop closed"
    assert any(e.loop is not None and e.loop.correction for e in during) or slam.back_end.worker.stats.lag_frames[-1] > 0
    assert max(slam.back_end.worker.stats.lag_frames) >= 1  # the tracker went on while keyframes were mapped
    assert len(slam.submaps) >= 2
    live = ate_rmse([pose for _, pose in slam.trajectory()], truth)
    slam.close()
    lock_step, _, _ = odometry_loop_run("sync", pace=False)
    lock_step.finish()
    closed = ate_rmse([pose for _, pose in lock_step.trajectory()], truth)
    lock_step.close()
    assert closed <= 0.6 * ate_rmse(integrate_odometry(truth), truth)
    assert live <= 1.25 * closed


def test_async_a_keyframes_gaussians_join_the_map_before_the_next_frame_while_the_worker_is_busy():
    """The worker held in the map's first optimisation: the tracker does not wait for it, and each keyframe it hands
    over adds its Gaussians to the map it tracks the next frame against; once released, the worker takes them into
    its optimisations."""
    data = SyntheticDataset("default", resolution=(40, 30))
    slam = GauSemSLAM(from_flat({**CHEAP, "worker.queue_size": 100}), "cpu", len(SYNTHETIC_CLASSES))
    release, optimise = threading.Event(), slam.back_end.mapper.optimise
    slam.back_end.mapper.optimise = lambda *args, **kwargs: release.wait(60) and optimise(*args, **kwargs)
    observations = [Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                            f.timestamp) for f in (data[i] for i in range(12))]
    counts = []
    for obs in observations:
        result = slam.process(obs)
        counts.append((result.is_keyframe, slam.active.num_gaussians))
    worker = slam.back_end.worker
    assert worker.stats.mapped == 0 and not worker.idle  # still held: every frame was tracked without it
    grown = [after > before for (_, before), (keyframe, after) in zip(counts, counts[1:]) if keyframe]
    assert sum(k for k, _ in counts[1:]) >= 3 and len(slam.back_end.growth_seconds) == sum(k for k, _ in counts[1:])
    assert counts[-1][1] > counts[0][1] and any(grown)
    release.set()
    slam.finish()
    assert worker.stats.mapped == sum(k for k, _ in counts) and worker.stats.superseded == 0
    assert all(len(s.load_cloud()) == s.num_gaussians for s in slam.submaps)
    slam.close()


def test_async_between_keyframes_the_worker_goes_on_optimising_the_newest_window_up_to_its_budget():
    """Anytime mapping: with time between keyframes, the newest keyframe's window gets its mapping steps and then
    ``worker.idle_iterations`` more at a time, up to ``worker.max_idle_iterations``; a drain holds it."""
    data = SyntheticDataset("default", resolution=(40, 30))
    slam = GauSemSLAM(from_flat({**CHEAP, "submaps.motion_translation": 100.0, "worker.idle_iterations": 4,
                                 "worker.max_idle_iterations": 12}), "cpu", len(SYNTHETIC_CLASSES))
    back = slam.back_end
    for f in (data[i] for i in range(5)):  # keyframes 0, 2 and 4 (mapping.every 2), one submap
        slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                             f.timestamp))
    assert wait_for(lambda: back.window_iterations.get(4) == 5 + 12, 60), back.window_iterations  # 5: its mapping
    slam.drain()
    assert back.window_iterations[4] == 5 + 12 and back.worker.idle and len(slam.submaps) == 1
    assert len(back.window_ages) >= 3
    slam.close()


@pytest.mark.parametrize("mode", ["async", "sync"])
def test_a_live_tracker_takes_the_raw_depth_and_the_map_each_keyframes_filtered(mode):
    """``depth_filter.frames: async``: in async mode the filter runs on keyframes alone, after tracking and before
    mapping (the map's first frame too); in sync every frame is filtered before tracking."""
    data = SyntheticDataset("default", resolution=(40, 30))
    slam = GauSemSLAM(from_flat({**CHEAP, "worker.mode": mode}), "cpu", len(SYNTHETIC_CLASSES))
    seen = {"tracked": [], "mapped": []}

    def recording(kind, method):
        def record(obs, *args):
            seen[kind].append(obs.depth)
            return method(obs, *args)
        return record

    slam.front_end.place = recording("tracked", slam.front_end.place)
    slam.back_end.start = recording("mapped", slam.back_end.start)
    slam.back_end.add_keyframe = recording("mapped", slam.back_end.add_keyframe)
    generator, raw = torch.Generator().manual_seed(0), []
    for f in (data[i] for i in range(5)):  # keyframes 0, 2 and 4 (mapping.every 2)
        obs = Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette, f.timestamp)
        obs = replace(obs, depth=obs.depth * (1 + 0.01 * torch.randn(obs.depth.shape, generator=generator)))
        raw.append(obs)
        slam.process(obs)
    slam.close()
    filtered = [filter_observation(obs, slam.cfg.depth_filter).depth for obs in raw]
    assert all(not torch.equal(f, obs.depth) for f, obs in zip(filtered, raw))  # the filter changes the noisy depth
    expected = filtered if mode == "sync" else [obs.depth for obs in raw]
    assert all(torch.equal(a, b) for a, b in zip(seen["tracked"], expected[1:], strict=True))
    assert all(torch.equal(a, b) for a, b in zip(seen["mapped"], filtered[::2], strict=True))


def test_sync_and_async_reject_an_unknown_mode():
    with pytest.raises(ValueError, match="worker.mode"):
        GauSemSLAM(from_flat({**CHEAP, "worker.mode": "threads"}), "cpu", 1)


def test_a_saved_async_session_holds_every_keyframe(tmp_path):
    """save waits for the worker: the saved session has every keyframe the tracker handed over."""
    data = SyntheticDataset("default", resolution=(40, 30), stride=3)
    slam = GauSemSLAM(from_flat(CHEAP), "cpu", len(SYNTHETIC_CLASSES))
    results = [slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                                    f.timestamp)) for f in (data[i] for i in range(7))]
    slam.save(tmp_path / "session")
    loaded = GauSemSLAM.load(tmp_path / "session", "cpu", from_flat({**CHEAP, "worker.mode": "sync"}))
    assert [kf.frame_id for s in loaded.submaps for kf in s.keyframes] == [r.frame_id for r in results
                                                                            if r.is_keyframe]
    np.testing.assert_allclose(np.stack([p.numpy() for _, p in loaded.trajectory()]),
                               np.stack([p.numpy() for _, p in slam.trajectory()]), atol=1e-6)
    slam.close()
    loaded.close()
