"""The SLAM system: one object that takes observations and owns the map (tracker + mapper over submaps).

Submaps (paper §III-A). Each submap has its own frame, anchored at its first keyframe (``anchor`` = world-from-
submap; the first keyframe sits at the identity and is never moved by bundle adjustment). At every keyframe the
allocation policy (``submaps.policy``) decides whether the keyframe starts a new submap. If so, the active submap gets
a boundary local BA over its last keyframes and is closed; the new submap's anchor is the old anchor composed with
the keyframe's pose in the old submap, and it is initialised from the keyframe by semantic sampling.

Frames are stored relative to a reference keyframe of their submap, so corrections of anchors or keyframe poses (loop
closure, pose graph) carry every frame along. Memory: only the active submap (Gaussians and keyframe images) lives on
the compute device. A closed submap's tensors go to a :class:`SubmapStore` (CPU memory up to
``submaps.memory_budget_mb``, disk beyond) and come back on demand; its anchor and keyframe poses stay at hand.
"""
from __future__ import annotations

import threading
import weakref
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import NamedTuple

import torch

from gausem_core.config import WORKER_MODES, SlamConfig, check_gap_mode, gap_mode_applies
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, invert_pose, project_to_se3
from gausem_core.memory import release_free_heap
from gausem_core.native import kernel_available
from gausem_core.render import prepare_backend, render
from gausem_core.semantics.descriptors import make_descriptor
from gausem_core.slam.allocation import Decision, SubmapExtent, make_allocation
from gausem_core.slam.depth_filter import filter_observation
from gausem_core.slam.events import Correction, FrameEvents, KeyframeState, SubmapChange
from gausem_core.slam.feature_start import FeatureStart
from gausem_core.slam.health import HealthMonitor, TrackingHealth, image_signals
from gausem_core.slam.loop import LoopCandidate
from gausem_core.slam.loop_closure import LoopClosure, LoopOutcome
from gausem_core.slam.loop_graphs import PoseGraphUpdate
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.refinement import global_refinement
from gausem_core.slam.observation import Observation
from gausem_core.slam.relocalisation import RelocalisationResult, Start, relocalisation_starts, track_from_starts
from gausem_core.slam.submap_store import SubmapStore
from gausem_core.slam.tracker import Tracker, TrackingResult, inspect_pose, repeat_motion
from gausem_core.slam.vignetting import Vignetting
from gausem_core.slam.worker import Job, MappingWorker, split_threads

_IMAGES = ("rgb", "depth", "semantic", "labels")
MAX_PREDICTION_S = 1.0  # the constant-velocity prediction extrapolates at most this far past the last good frame
STAMP_JITTER = 0.5  # ... and goes by the stamps only where they disagree with the frame count by more than this
# share: camera stamps jitter (TUM fr1/rpy: intervals 27-40 ms at 30 Hz), skipped frames are a clear gap


class MotionPrediction(NamedTuple):
    """What the motion model knows of the next frame (:meth:`GauSemSLAM._motion_model`)."""

    previous: torch.Tensor  # the last good frame's cam_to_world in the active submap
    predicted: torch.Tensor | None  # the constant-velocity prediction (None without two good frames in a row)
    gap: bool  # camera frames were missed since the last good one (lost, dropped or skipped; or by the stamps)
    steps: float  # the latest motions the prediction repeats: frames since the last good one, or by the stamps


def _float64(pose: torch.Tensor) -> torch.Tensor:
    """A stored pose as it is, in float64 on the CPU (events; see :mod:`~gausem_core.slam.events`)."""
    return pose.detach().cpu().double()


def _shut_down(worker: MappingWorker, store: SubmapStore) -> None:
    """Stop the mapping worker, then drop the stored submaps (:meth:`GauSemSLAM.close`)."""
    worker.stop()
    store.close()


def rigid_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b for 4x4 rigid transforms, computed in float64 with the rotation projected back onto SO(3) (SVD), in a's
    dtype: chains of anchors then stay rigid instead of accumulating rounding."""
    return project_to_se3(a.double() @ b.double()).to(a.dtype)


@dataclass
class StoredObservation:
    """A closed submap's keyframe observation: camera and timestamp at hand, the images in the store."""

    store: SubmapStore
    key: tuple
    camera: PinholeCamera
    timestamp: float

    def load(self, device: torch.device | str = "cpu") -> Observation:
        """The observation, its images read back (bit-identical) onto ``device``."""
        return Observation(**self.store.load(self.key, device), camera=self.camera, timestamp=self.timestamp)


class Submap:
    """Gaussians and keyframes in a local frame anchored at the first keyframe; ``anchor`` is world-from-submap.

    While active, ``cloud`` and the keyframes' ``obs`` are tensors on the compute device. After :meth:`offload`
    (inactive) they live in a :class:`SubmapStore`: ``cloud`` reads a CPU copy back (assigning it writes the store)
    and each keyframe's ``obs`` is a :class:`StoredObservation`. Anchor and keyframe poses always stay in memory.
    """

    def __init__(self, submap_id: int, anchor: torch.Tensor, cloud: GaussianCloud,
                 keyframes: list[Keyframe] | None = None, extent: SubmapExtent | None = None, trackable: bool = True):
        self.submap_id = submap_id
        self.trackable = threading.Event()  # its Gaussians are fit to track against (a new one's: once published)
        if trackable:
            self.trackable.set()
        self.anchor = anchor
        self.keyframes = list(keyframes or [])
        self.extent = extent  # what allocation needs while the submap is active
        self._cloud: GaussianCloud | None = cloud
        self._store: SubmapStore | None = None
        self.num_gaussians = len(cloud)

    @property
    def is_active(self) -> bool:
        """Whether the tensors are resident (not offloaded to a store)."""
        return self._store is None

    @property
    def cloud(self) -> GaussianCloud:
        """The Gaussians in the submap frame (for an inactive submap: a copy read from the store)."""
        return self.load_cloud()

    @cloud.setter
    def cloud(self, cloud: GaussianCloud) -> None:
        if self._store is None:
            self._cloud = cloud
        else:
            self._store.store(self._cloud_key, cloud.tensors())
        self.num_gaussians = len(cloud)

    def load_cloud(self, device: torch.device | str | None = None) -> GaussianCloud:
        """The Gaussians on ``device`` (default: where they are; the CPU for an inactive submap). An inactive
        submap's come back as a bit-identical copy; an active submap's are its own tensors (moved if asked)."""
        if self._store is None:
            return self._cloud if device is None else self._cloud.to(device)
        return GaussianCloud(**self._store.load(self._cloud_key, device or "cpu"))

    def observation(self, keyframe: Keyframe, device: torch.device | str = "cpu") -> Observation:
        """One of the keyframes' observation: an active submap's own, an inactive one's read back onto ``device``."""
        obs = keyframe.obs
        return obs.load(device) if isinstance(obs, StoredObservation) else obs

    def world_pose(self, keyframe: Keyframe) -> torch.Tensor:
        """World-from-camera of one of this submap's keyframes."""
        return self.anchor @ keyframe.cam_to_world

    def offload(self, store: SubmapStore) -> None:
        """Move the Gaussians and the keyframe images into ``store``; the submap becomes inactive."""
        if self._store is not None:
            raise ValueError(f"submap {self.submap_id} is already offloaded")
        store.store(self._cloud_key, self._cloud.tensors())
        for kf in self.keyframes:
            key = ("keyframe", self.submap_id, kf.frame_id)
            store.store(key, {name: getattr(kf.obs, name) for name in _IMAGES})
            kf.obs = StoredObservation(store, key, kf.obs.camera, kf.obs.timestamp)
        self._cloud, self._store = None, store

    @property
    def _cloud_key(self) -> tuple:
        return ("cloud", self.submap_id)


@dataclass
class FrameRecord:
    """A processed frame, stored relative to its reference keyframe so map corrections carry it along."""

    frame_id: int
    timestamp: float
    submap: Submap
    reference: Keyframe
    relative: torch.Tensor  # reference-keyframe-from-camera
    lost: bool = False  # tracking was judged lost: the pose is kept for the record, nothing else uses it
    skipped: int = 0  # camera frames missed just before this one (skipped by the caller, or dropped)

    @property
    def cam_to_world(self) -> torch.Tensor:
        return self.submap.anchor @ self.reference.cam_to_world @ self.relative


@dataclass
class FrameResult:
    frame_id: int
    cam_to_world: torch.Tensor
    is_keyframe: bool
    tracking_loss: float
    tracking_iterations: int
    mapping_loss: float | None
    num_gaussians: int  # in the active submap
    submap_id: int  # the submap the frame belongs to
    allocation: Decision | None  # the allocation decision (keyframes after the first)
    relocalisation: RelocalisationResult | None = None  # when the frame was relocalised (the system was lost)
    health: TrackingHealth | None = None  # ok / degraded / lost and its signals (``slam.health``)
    events: FrameEvents = field(default_factory=FrameEvents)  # keyframe, submaps closed/opened, loop outcome
    mapped: tuple[FrameEvents, ...] = ()  # ``worker.mode: async``: the events of the keyframes the mapping worker
    # finished since the previous frame (a keyframe's own ``events`` come so, later; sync: always empty)
    map_age: int = 0  # frames between the newest keyframe in the map the frame was tracked against and the frame


class GauSemSLAM:
    """Tracking, mapping and submap allocation over a stream of observations.

    ``num_classes``: length of the class histograms (the class table's size); they grow to the largest class id seen,
    so 1 is fine when the table is unknown. ``detect_loops``: False when loops are detected elsewhere (the ROS
    loop_detection node) from the place signatures in the frames' events and handed in through :meth:`register_loop`
    (the loop database still stores them, unchecked: a saved session holds them either way).
    Call :meth:`close` (or use ``with``) to delete spilled submaps at once; otherwise that happens when the object is
    collected.

    :meth:`save` writes the whole state to a folder and :meth:`load` restores it (see ``slam.persistence``). A loaded
    system is :attr:`lost`: the first frame given to :meth:`process` is relocalised against the map
    (:meth:`relocalise`) instead of tracked from the last pose; when relocalisation fails the frame is dropped (not
    recorded, the map untouched, ``FrameResult.relocalisation.accepted`` False) and the next frame tries again.

    Every frame's tracking is judged (``FrameResult.health``, see ``slam.health``). A frame judged lost is recorded (its
    pose, for the trajectory) but not mapped, even at a keyframe, and the system becomes :attr:`lost`: the next frames
    are relocalised, the constant-velocity prediction from the last good frames first among the starts, until a
    placement passes the health monitor (:meth:`relocalise`). That frame is degraded (reason ``relocalised``: it was
    not tracked from the frame before) and tracking goes on from it, the motion model skipping the lost frames.

    ``worker.mode`` (``slam.worker``): ``sync`` maps each keyframe (allocation, submaps, loop closure) inside the
    :meth:`process` call that tracked it; ``async`` hands it to a mapping thread and returns after tracking. The tracker
    then tracks against the Gaussians the worker last published (a new map's, placed from the first frame's depth at
    once, optimised in the worker), and a keyframe's events reach the caller with a later frame
    (``FrameResult.mapped``, or :meth:`take_mapped` after :meth:`finish`). Map corrections (keyframe poses, anchors)
    happen under :attr:`lock`, which the tracker holds while it reads the poses behind its motion model.
    """

    def __init__(self, cfg: SlamConfig, device: torch.device | str = "cpu", num_classes: int = 1,
                 detect_loops: bool = True, tracker: Tracker | None = None):
        if cfg.submaps.boundary_window < 1 or cfg.submaps.boundary_iterations < 0:
            raise ValueError("submaps.boundary_window must be >= 1 and submaps.boundary_iterations >= 0, got "
                             f"{cfg.submaps.boundary_window} and {cfg.submaps.boundary_iterations}")
        check_gap_mode("mapping.coverage_keyframes", cfg.mapping.coverage_keyframes)
        if cfg.worker.mode not in WORKER_MODES:
            raise ValueError(f"worker.mode must be one of {WORKER_MODES}, got {cfg.worker.mode!r}")
        self.cfg = cfg
        self.device = torch.device(device)
        prepare_backend(cfg.backend, self.device)  # builds or loads the compiled kernels now, not in the first frame
        if self.device.type == "cpu":
            kernel_available()  # Gauss-Newton tracking uses them whatever renders (loading: a quarter second)
        torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # the first optimiser imports torch._dynamo (seconds)
        self.num_classes = num_classes
        # the tracking step; another object with Tracker.track's signature may stand in (e.g. a benchmark's oracle)
        self.tracker = tracker if tracker is not None else Tracker(cfg.tracking, cfg.backend)
        self.feature_start = FeatureStart(cfg.tracking.feature_start)
        self.health = HealthMonitor(cfg.health)
        self.vignetting = Vignetting(cfg.vignetting)
        self.mapper = Mapper(cfg.mapping, cfg.backend, cfg.seed)
        self.allocation = make_allocation(cfg.submaps)
        self.allocation_rules: Counter = Counter()  # (rule, whether it opened a submap) of every allocation decision
        self.store = SubmapStore(int(cfg.submaps.memory_budget_mb * 2**20), cfg.submaps.cache_dir or None)
        self._close = weakref.finalize(self, self.store.close)
        self.submaps: list[Submap] = []
        self.frames: list[FrameRecord] = []
        self.lost = False  # the next frame is relocalised (set by load; a caller may set it after a tracking failure)
        self.segment_start = 0  # first frame id of the current tracking segment (the motion model stays inside it;
        # load starts a new one when it relocalises)
        self.dropped = 0  # frames dropped (not relocalised while lost) since the last recorded frame
        self.skipped = 0  # frames the caller skipped (``process``'s ``skipped``) since the last recorded frame
        self.detect_loops = detect_loops
        self.descriptor = make_descriptor(cfg.semantics.descriptor, cfg.semantics.dinov2_weights,
                                          device=self.device) if cfg.loop.enabled or cfg.refinement.enabled else None
        self.loop_closure = LoopClosure(cfg.loop, self.mapper, self.descriptor, cfg.backend,
                                        self.device) if cfg.loop.enabled else None
        self.lock = self.mapper.lock  # held while the map's poses change and while the tracker reads them
        self.worker = self._start_worker(cfg) if cfg.worker.mode == "async" else None
        self._mapped: list[FrameEvents] = []  # async: finished keyframes' events not yet handed out

    def _start_worker(self, cfg: SlamConfig) -> MappingWorker:
        """The mapping thread of ``worker.mode: async``; the calling (tracking) thread keeps its share of the
        cores."""
        tracker_threads, worker_threads = split_threads(cfg.worker.tracker_threads, cfg.worker.threads)
        torch.set_num_threads(tracker_threads)
        self.mapper.min_iteration_fraction = cfg.worker.min_iteration_fraction
        worker = MappingWorker(lambda: len(self.frames), cfg.worker.queue_size, worker_threads, self.mapper.pressure)
        self._close.detach()
        self._close = weakref.finalize(self, _shut_down, worker, self.store)
        return worker

    @property
    def asynchronous(self) -> bool:
        """Whether keyframes are mapped on the mapping thread (``worker.mode: async``)."""
        return self.worker is not None

    def take_mapped(self) -> tuple[FrameEvents, ...]:
        """``worker.mode: async``: the events of the keyframes mapped since the last call (or frame), in order."""
        if self.worker is not None:
            self._mapped.extend(self.worker.take_events())
        events, self._mapped = tuple(self._mapped), []
        return events

    def drain(self) -> None:
        """Wait until the mapping worker has mapped every keyframe given to it (nothing to wait for in sync mode);
        their events stay for :meth:`take_mapped`."""
        if self.worker is not None:
            self.worker.drain()
            self._mapped.extend(self.worker.take_events())

    @property
    def active(self) -> Submap:
        return self.submaps[-1]

    def process(self, obs: Observation, skipped: int = 0) -> FrameResult:
        """Track the frame against the active submap (while :attr:`lost`: relocalise it, or drop it when that
        fails); at a keyframe, start a new submap when the allocation policy says so, else map the keyframe into the
        active one (``worker.mode: async``: on the mapping thread, after this call returns). ``skipped``: the camera's
        frames since the previous call that the caller did not pass on (a live node that fell behind, dropped inputs);
        the motion model counts them, as its stamps alone miss a node that is steadily slower than its camera."""
        if skipped < 0:
            raise ValueError(f"skipped must be >= 0, got {skipped}")
        if self.worker is not None:
            self.worker.raise_error()
        obs = filter_observation(self.vignetting.correct(obs), self.cfg.depth_filter)
        frame_id = len(self.frames)
        self.mapper.hurry.clear()
        self.skipped += skipped
        if not self.submaps:
            self.skipped = 0
            return self._first_frame(obs, frame_id)
        self._tracked_submap()  # async: waits for the map's first Gaussians (not under the lock the worker needs)
        with self.lock:  # the map the frame is tracked against, and the poses behind the motion model, in one piece
            submap = self._tracked_submap()
            cloud = submap.cloud
            motion = self._motion_model(obs.timestamp)
        map_age = frame_id - submap.keyframes[-1].frame_id
        tracked, relocalised = self._place(obs, motion, submap, cloud)
        if tracked is None:  # lost and not relocalised: the frame is dropped
            self.dropped += 1
            judged = relocalised.health or TrackingHealth("lost")
            return FrameResult(frame_id, relocalised.cam_to_world, False, relocalised.tracking_loss,
                               relocalised.iterations, None, submap.num_gaussians, submap.submap_id, None,
                               relocalised, replace(judged, status="lost",
                                                    reasons=(*judged.reasons, "relocalisation_failed")),
                               mapped=self.take_mapped(), map_age=map_age)
        health = self._assess(obs, tracked, relocalised, motion, cloud)
        missed, self.dropped, self.skipped = self.dropped + self.skipped, 0, 0
        pose = tracked.cam_to_world.detach()
        lost = health.status == "lost"
        if not lost:
            self.feature_start.remember(obs)
        keyframe = not lost and self._is_keyframe(frame_id, health, motion.gap or relocalised is not None)
        if not keyframe or self.worker is not None:
            reference = submap.keyframes[-1]
            record = FrameRecord(frame_id, obs.timestamp, submap, reference,
                                 invert_pose(reference.cam_to_world) @ pose, lost, missed)
            with self.lock:
                self.frames.append(record)
            self.lost = lost
            if keyframe:  # async: mapped on the worker, which re-anchors the record at the keyframe
                self.worker.submit(Job(frame_id, "keyframe", partial(self._keyframe_job, obs, record)))
            return replace(self._result(tracked, keyframe, None, None, relocalised, health),
                           mapped=self.take_mapped(), map_age=map_age)
        events, loss, decision = self._map(obs, frame_id, pose, missed)
        return replace(self._result(tracked, True, loss, decision, relocalised, health, events), map_age=map_age)

    def _first_frame(self, obs: Observation, frame_id: int) -> FrameResult:
        """The map's first frame, which defines the world frame: a submap from its depth (semantic sampling), then
        optimised (async: on the worker, the unoptimised Gaussians trackable at once)."""
        submap = self._place_submap(obs, frame_id, torch.eye(4, device=self.device))
        self.feature_start.remember(obs)
        if self.worker is not None:
            self.worker.submit(Job(frame_id, "open", lambda: self._first_job(submap, obs)[0]))
            return self._result(None, True, None, None)
        events, loss = self._first_job(submap, obs)
        return self._result(None, True, loss, None, events=events)

    def _tracked_submap(self) -> Submap:
        """The submap frames are tracked against: the newest one whose Gaussians are trackable (async: a new submap
        once its first optimisation published them; the map's first one is waited for)."""
        submap = next((s for s in reversed(self.submaps) if s.trackable.is_set()), None)
        if submap is None:
            submap = self.submaps[0]
            while not submap.trackable.wait(0.1):
                self.worker.raise_error()
        return submap

    def _first_job(self, submap: Submap, obs: Observation) -> tuple[FrameEvents, float | None]:
        """The mapping half of :meth:`_first_frame` (async: on the worker): optimisation, vignetting calibration,
        the keyframe's events; and the last mapping loss."""
        loss = self._optimise_first(submap)
        self._calibrate(obs, submap.keyframes[0].cam_to_world)
        return self._keyframe_events([]), loss

    def _keyframe_job(self, obs: Observation, record: FrameRecord) -> FrameEvents:
        """The worker's mapping of a keyframe the tracker recorded as ``record``: at its current pose (corrections
        since carried it along) in the active submap."""
        with self.lock:  # (projected onto SE(3): re-expressed poses must not drift off it, chained keyframe on keyframe)
            pose = rigid_product(invert_pose(self.active.anchor), record.cam_to_world)
        events, _, _ = self._map(obs, record.frame_id, pose, record.skipped, record)
        return events

    def _map(self, obs: Observation, frame_id: int, pose: torch.Tensor, missed: int,
             record: FrameRecord | None = None) -> tuple[FrameEvents, float | None, Decision]:
        """A keyframe at ``pose`` in the active submap: vignetting calibration, the allocation decision, then a new
        submap (the active one closed) or the keyframe mapped into the active one, then loop closure. ``record``: the
        frame's record to re-anchor at the keyframe (async), else a new one is appended. Returns the keyframe's events,
        the last mapping loss and the allocation decision."""
        obs = self._calibrate(obs, pose)
        decision = self.allocation.should_start_new(self.active.extent, obs, pose)
        self.allocation_rules[decision.rule, decision.new] += 1
        closed = []
        if decision.new:
            old = self.active
            closed.append(self._submap_change(old, opened=False))
            self._boundary_adjust(old)
            submap = self._place_submap(obs, frame_id, rigid_product(old.anchor, pose), missed, record)
            loss = self._optimise_first(submap)
            old.offload(self.store)  # after: the tracker tracks against it until the new one is trackable
        else:
            loss = self._map_keyframe(obs, frame_id, pose, missed, record)
        events = self._keyframe_events(closed)
        release_free_heap()  # mapping and loop closure freed many image-sized buffers
        return events, loss, decision

    def _is_keyframe(self, frame_id: int, health: TrackingHealth, gap: bool) -> bool:
        """Every ``mapping.every``-th frame is mapped, and (``mapping.coverage_keyframes``; ``gap``: camera frames
        were missed before it) a frame whose view the map covers less than ``mapping.min_coverage`` of: a camera
        outrunning its map (frames a live node skipped, or fast motion)."""
        cfg = self.cfg.mapping
        return frame_id % cfg.every == 0 or (gap_mode_applies(cfg.coverage_keyframes, gap)
                                             and health.coverage < cfg.min_coverage)

    def _place(self, obs: Observation, motion: MotionPrediction, submap: Submap,
               cloud: GaussianCloud) -> tuple[TrackingResult | None, RelocalisationResult | None]:
        """The frame's pose in ``submap`` (the active one, its Gaussians ``cloud`` as published): tracked, or
        relocalised while :attr:`lost` (None when that fails)."""
        if not self.lost:
            return self._track(obs, motion, cloud), None
        relocalised = self.relocalise(obs)
        if not relocalised.accepted:
            return None, relocalised
        self.lost = False
        with self.lock:
            local = invert_pose(submap.anchor) @ relocalised.cam_to_world
        return TrackingResult(local, relocalised.tracking_loss, relocalised.iterations), relocalised

    def _track(self, obs: Observation, motion: MotionPrediction, cloud: GaussianCloud) -> TrackingResult:
        """Track from the motion model's prediction; where the motion since the last good frame is unknown (frames were
        missed, or there is no motion model yet: a segment's second frame) the gap measures apply
        (``gauss_newton.search``, ``feature_start``)."""
        unknown = motion.gap or motion.predicted is None
        search = gap_mode_applies(self.cfg.tracking.gauss_newton.search, unknown)
        featured = self.feature_start.predict(obs, motion.previous) if self.feature_start.wanted(unknown) else None
        alternatives = [] if featured is None else [featured]
        if motion.predicted is None:
            return self.tracker.track(cloud, obs, motion.previous, alternatives, search=search)
        return self.tracker.track(cloud, obs, motion.predicted, [motion.previous, *alternatives], search=search)

    def _motion_model(self, timestamp: float) -> MotionPrediction:
        """For a frame stamped ``timestamp``: the last good (not lost) frame's pose in the active submap, the
        constant-velocity prediction, whether camera frames were missed since the last good one (lost, dropped or
        skipped ones, or by the stamps), and how many times the prediction repeats the latest motion. That motion is
        the one between the latest two consecutively recorded good frames of the tracking segment; it is repeated once
        per the camera frames it spans in the camera frames since the last good one (lost, dropped and skipped frames
        count), or, where the stamps say clearly more or less time passed (:data:`STAMP_JITTER`: a gap that nobody
        counted), over the time since the last good frame in units of that pair's interval (at most
        :data:`MAX_PREDICTION_S` ahead). No prediction without such a pair or with ``tracking.constant_velocity``
        off."""
        good = self._last_good()
        frames_after = sum(1 + f.skipped for f in self.frames[good + 1:]) + 1 + self.dropped + self.skipped
        previous = self._local_pose(good)
        pair = self._latest_good_pair(good) if self.cfg.tracking.constant_velocity else None
        if pair is None:
            return MotionPrediction(previous, None, frames_after > 1, frames_after)
        relative = invert_pose(self._local_pose(pair - 1)) @ self._local_pose(pair)
        interval = self.frames[pair].timestamp - self.frames[pair - 1].timestamp
        by_count = frames_after / (1 + self.frames[pair].skipped)
        elapsed = min(timestamp - self.frames[good].timestamp, MAX_PREDICTION_S)
        by_time = elapsed / interval if interval > 0 and elapsed > 0 else by_count
        steps = by_count if abs(by_time / by_count - 1) <= STAMP_JITTER else by_time
        return MotionPrediction(previous, repeat_motion(previous, relative, steps),
                                max(frames_after, steps) > 1 + STAMP_JITTER, steps)

    def _last_good(self) -> int:
        """Index of the last recorded frame not judged lost (the first frame never is)."""
        return next(i for i in range(len(self.frames) - 1, -1, -1) if not self.frames[i].lost)

    def _latest_good_pair(self, last: int) -> int | None:
        """The largest index i <= ``last`` with frames i-1 and i good and in the tracking segment (None if none)."""
        for i in range(last, 0, -1):
            if self.frames[i - 1].frame_id < self.segment_start:
                return None
            if not (self.frames[i].lost or self.frames[i - 1].lost):
                return i
        return None

    def _assess(self, obs: Observation, tracked: TrackingResult, relocalised: RelocalisationResult | None,
                motion: MotionPrediction, cloud: GaussianCloud) -> TrackingHealth:
        """The health of a frame tracked to ``tracked`` against ``cloud`` (before it is recorded), its pose jump
        judged against ``motion``. A relocalised frame was judged by relocalisation (against the submap that placed
        it): after a restart ok, and a new motion history starts; after a tracking loss as the health monitor judged
        it, degraded at least (``relocalised``)."""
        if relocalised is not None:
            return self._relocalised_health(obs, relocalised)
        view, hessian = inspect_pose(cloud, obs, tracked.cam_to_world, self.cfg.tracking, self.cfg.backend)
        image = image_signals(view, obs, hessian, self.cfg.health)
        return self.health.assess(tracked.loss, image, tracked.cam_to_world, motion.previous,
                                  motion.previous if motion.predicted is None else motion.predicted, motion.steps)

    def _relocalised_health(self, obs: Observation, relocalised: RelocalisationResult) -> TrackingHealth:
        """The health of an accepted relocalisation (see :meth:`_assess`); the monitor learns its residual."""
        if relocalised.health is None:
            self.health.reset()
            return TrackingHealth("ok", inlier_fraction=relocalised.inlier_fraction,
                                  valid_depth=float(obs.valid_depth.float().mean()))
        self.health.learn(relocalised.tracking_loss, None)
        return replace(relocalised.health, status="degraded", reasons=(*relocalised.health.reasons, "relocalised"))

    def interrupt(self) -> None:
        """Ask the frame in progress (in another thread) to finish early, e.g. on Ctrl-C: optimisations stop at their
        next iteration, so the map stays consistent, only less refined. The next frame clears it."""
        self.mapper.hurry.set()

    def relocalise(self, obs: Observation) -> RelocalisationResult:
        """Place a frame against the map without trusting the motion model (``slam.relocalisation``): tracked from
        the constant-velocity prediction when the tracking segment has one (after a tracking loss), the last good pose
        and the ``relocalisation.candidates`` keyframes nearest by global descriptor (or the active submap's
        keyframes), the best start kept. After a tracking loss it accepts from ``health.recovery_inlier_fraction``
        (the map lacks what the lost frames would have added) and only a placement that passes the health monitor
        (:meth:`_judge_recovery`). With ``tracking.feature_start`` on, the feature start from the last good frame
        comes first. Changes nothing; :meth:`process` uses it while :attr:`lost`."""
        if not self.frames:
            raise ValueError("relocalise: the map is empty (no frame processed or loaded)")
        cfg = self.cfg.relocalisation
        recovering = self.frames[-1].lost
        if recovering:
            cfg = replace(cfg, min_inlier_fraction=min(cfg.min_inlier_fraction,
                                                       self.cfg.health.recovery_inlier_fraction))
        last = self.frames[self._last_good()]
        ranked = (self.loop_closure.nearest_keyframes(obs, cfg.candidates)
                  if self.loop_closure is not None else [])
        local = invert_pose(last.submap.anchor) @ last.cam_to_world
        starts = relocalisation_starts(self.submaps, (last.submap, local), ranked, cfg.candidates)
        with self.lock:
            predicted = self._motion_model(obs.timestamp).predicted
        if predicted is not None:
            starts.insert(0, Start(self._tracked_submap(), predicted, "constant velocity"))
        featured = self.feature_start.predict(obs, local) if self.feature_start.wanted(gap=True) else None
        if featured is not None:
            starts.insert(0, Start(last.submap, featured, "features"))
        placed = track_from_starts(obs, starts, self.tracker, cfg, self.device)
        return self._judge_recovery(obs, placed) if recovering and placed.accepted else placed

    def _judge_recovery(self, obs: Observation, placed: RelocalisationResult) -> RelocalisationResult:
        """A placement after a tracking loss, judged by the health monitor as a tracked frame would be (against the
        submap that placed it; no pose jump: the prediction across the loss is only a guess), accepted unless that
        finds it lost or its residual's z-score against the frames before the loss exceeds
        ``health.recovery_residual_z``."""
        submap = self.submaps[placed.submap_id]
        local = invert_pose(submap.anchor) @ placed.cam_to_world
        view, hessian = inspect_pose(submap.load_cloud(self.device), obs, local, self.cfg.tracking, self.cfg.backend)
        health = self.health.judge(placed.tracking_loss, image_signals(view, obs, hessian, self.cfg.health), local,
                                   None)
        fits = health.status != "lost" and health.residual_z <= self.cfg.health.recovery_residual_z
        return replace(placed, accepted=fits, health=health)

    def save(self, folder) -> None:
        """Write the whole state into ``folder`` (see :func:`gausem_core.slam.persistence.save_session`)."""
        from gausem_core.slam.persistence import save_session
        self.drain()
        save_session(self, folder)

    @staticmethod
    def load(folder, device: torch.device | str = "cpu", cfg: SlamConfig | None = None,
             relocalise: bool = True) -> "GauSemSLAM":
        """A saved system on ``device``, :attr:`lost` with ``relocalise`` (see
        :func:`gausem_core.slam.persistence.load_session`)."""
        from gausem_core.slam.persistence import load_session
        return load_session(folder, cfg, device, relocalise)

    def _map_keyframe(self, obs: Observation, frame_id: int, pose: torch.Tensor, skipped: int,
                      record: FrameRecord | None = None) -> float | None:
        """Add a keyframe to the active submap: densify, then BA over the recent keyframes. ``skipped``: the camera
        frames missed just before it (its record's); ``record``: see :meth:`_map`."""
        submap = self.active
        kf = Keyframe(frame_id, obs, pose)
        with self.lock:
            submap.keyframes.append(kf)
            self._anchor_record(FrameRecord(frame_id, obs.timestamp, submap, kf, torch.eye(4, device=pose.device),
                                            skipped=skipped), record)
        submap.extent.add(obs, pose)
        submap.cloud = self.mapper.densify(submap.cloud, obs, pose)
        window = submap.keyframes[-self.cfg.mapping.window:]
        submap.cloud, losses = self.mapper.optimise(submap.cloud, window, self.cfg.mapping.iterations)
        return losses[-1] if losses else None

    def _anchor_record(self, anchored: FrameRecord, record: FrameRecord | None) -> None:
        """Append ``anchored`` (a keyframe's record at its keyframe), or make the tracker's ``record`` of that frame
        so (async), the frames tracked after it re-expressed relative to it (their poses unchanged: later corrections
        carry them with their nearest keyframe); under :attr:`lock`."""
        if record is None:
            self.frames.append(anchored)
            return
        for later in reversed(self.frames):  # the frames tracked since follow the keyframe from now on
            if later is record:
                break
            if later.reference.frame_id < record.frame_id:
                base = anchored.submap.anchor @ anchored.reference.cam_to_world
                later.submap, later.reference, later.relative = (anchored.submap, anchored.reference,
                                                                 rigid_product(invert_pose(base), later.cam_to_world))
        record.submap, record.reference, record.relative = anchored.submap, anchored.reference, anchored.relative

    def _calibrate(self, obs: Observation, pose: torch.Tensor) -> Observation:
        """Refine the vignetting estimate with the keyframe ``obs`` at ``pose`` in the active submap, paired with the
        submap's last keyframe (see ``slam.vignetting``); when the estimate moves, the submap's keyframes are
        re-corrected to it before mapping goes on. Returns ``obs`` as corrected now."""
        before = self.vignetting.a
        self.vignetting.update(obs, pose, self.active.submap_id)
        if self.vignetting.a == before:
            return obs
        for kf in self.active.keyframes:
            kf.obs = self.vignetting.correct(kf.obs, before)
        return self.vignetting.correct(obs, before)

    def _place_submap(self, obs: Observation, frame_id: int, anchor: torch.Tensor, skipped: int = 0,
                      record: FrameRecord | None = None) -> Submap:
        """A new active submap anchored (world-from-submap) at ``anchor``: its first keyframe is ``obs``, fixed at the
        identity, and its Gaussians come from semantic sampling of its depth, usable for tracking at once (before
        :meth:`_optimise_first`). ``skipped``, ``record``: see :meth:`_map`."""
        eye = torch.eye(4, device=self.device)
        kf = Keyframe(frame_id, obs, eye, fixed=True)
        opacity = self.cfg.worker.first_opacity if self.worker is not None else None
        submap = Submap(len(self.submaps), anchor, self.mapper.initialise(obs, eye, opacity), [kf],
                        SubmapExtent.start(obs, eye, self.num_classes), trackable=self.worker is None)
        with self.lock:
            self.submaps.append(submap)
            self._anchor_record(FrameRecord(frame_id, obs.timestamp, submap, kf, eye.clone(), skipped=skipped), record)
        return submap

    def _optimise_first(self, submap: Submap) -> float | None:
        """The initial optimisation of a new submap's Gaussians over its first keyframe; the last loss. Async: the
        Gaussians are published every ``worker.publish_every`` steps, the first publication making them trackable."""
        def publish(cloud: GaussianCloud) -> None:
            submap.cloud = cloud
            submap.trackable.set()

        every = self.cfg.worker.publish_every if self.worker is not None else 0
        cloud, losses = self.mapper.optimise(submap.cloud, submap.keyframes[:1], self.cfg.mapping.init_iterations,
                                             publish=publish, publish_every=every)
        publish(cloud)
        return losses[-1] if losses else None

    def _boundary_adjust(self, submap: Submap) -> None:
        """Boundary local BA over a submap's last keyframes, before it is closed (offloaded)."""
        window = submap.keyframes[-self.cfg.submaps.boundary_window:]
        submap.cloud, _ = self.mapper.optimise(submap.cloud, window, self.cfg.submaps.boundary_iterations)

    def _result(self, tracked: TrackingResult | None, is_keyframe: bool, mapping_loss: float | None,
                allocation: Decision | None, relocalised: RelocalisationResult | None = None,
                health: TrackingHealth | None = None, events: FrameEvents | None = None) -> FrameResult:
        """The last frame's result (``tracked`` is None for the first frame, which defines the world frame: ok)."""
        record = self.frames[-1]
        loss, iterations = (tracked.loss, tracked.iterations) if tracked else (0.0, 0)
        return FrameResult(record.frame_id, record.cam_to_world, is_keyframe, loss, iterations, mapping_loss,
                           self.active.num_gaussians, self.active.submap_id, allocation, relocalised,
                           health or TrackingHealth("ok"), events or FrameEvents())

    def _local_pose(self, index: int) -> torch.Tensor:
        """A recent frame's pose in the frame of the submap tracked against (the active one in sync mode)."""
        return invert_pose(self._tracked_submap().anchor) @ self.frames[index].cam_to_world

    def _keyframe_events(self, closed: list[SubmapChange]) -> FrameEvents:
        """The events of a frame that made the newest keyframe (``closed``: the submap it closed, if any), after loop
        closure (Algorithm 1) for it: the outcome of a loop detected here (``detect_loops``), else the keyframe's
        place signature for the detector elsewhere (a loop keyframe's)."""
        submap = self.active
        keyframe = submap.keyframes[-1]
        loop = place = None
        if self.loop_closure is not None and self.detect_loops:
            loop = self.loop_closure.on_keyframe(self.submaps, submap, keyframe)
        elif self.loop_closure is not None:
            place = self.loop_closure.describe(self.submaps, submap, keyframe)
            if place is not None:  # stored unchecked, so that the session holds it as a detecting one would
                self.loop_closure.detect(place, check=False)
        opened = [self._submap_change(submap, opened=True)] if len(submap.keyframes) == 1 else []
        return FrameEvents(self._keyframe_state(submap, keyframe), tuple(closed + opened), loop, place)

    @staticmethod
    def _submap_change(submap: Submap, opened: bool) -> SubmapChange:
        return SubmapChange(submap.submap_id, submap.keyframes[0].frame_id, _float64(submap.anchor), opened)

    @staticmethod
    def _keyframe_state(submap: Submap, kf: Keyframe) -> KeyframeState:
        return KeyframeState(kf.frame_id, submap.submap_id, kf.obs.timestamp, _float64(kf.cam_to_world),
                             _float64(submap.anchor))

    def keyframe_states(self, submap_id: int | None = None) -> list[KeyframeState]:
        """The keyframes (of one submap, or all) with their current poses, in order."""
        return [self._keyframe_state(s, kf) for s in self.submaps if submap_id is None or s.submap_id == submap_id
                for kf in s.keyframes]

    def submap_states(self) -> list[SubmapChange]:
        """Every submap as opened (e.g. to announce a loaded map), with its current anchor."""
        return [self._submap_change(s, opened=True) for s in self.submaps]

    def register_loop(self, candidates: Sequence[LoopCandidate]) -> LoopOutcome | None:
        """Close a loop detected elsewhere: among one query keyframe's ranked candidates (from the detector's
        :meth:`~gausem_core.slam.loop.LoopDetector.add_keyframe` for its place signature, ``FrameEvents.place``) the
        one the loop closure confirms is registered (keyframe alignment or SGR); the outcome's constraint is set when
        accepted; None when none is confirmed. The map is not corrected: that is the pose graph's answer
        (:meth:`apply_pose_graph`). Raises ValueError when loop closure is disabled or the candidates name unknown
        keyframes or several query keyframes."""
        if self.loop_closure is None:
            raise ValueError("loop closure is disabled (loop.enabled: false)")
        self.drain()  # async: registration reads, and a re-map writes, the submaps the worker maps
        candidate = self.loop_closure.confirm(self.submaps, candidates)
        return None if candidate is None else self.loop_closure.register(self.submaps, candidate)

    def apply_pose_graph(self, update: PoseGraphUpdate) -> Correction:
        """Move the map to a pose graph's answer: anchors (world-from-submap), then keyframe poses (submap frame),
        each submap whose keyframes moved re-mapped with them held. Unknown ids are ignored."""
        self.drain()
        if self.loop_closure is None:
            if update.keyframes:
                raise ValueError("loop closure is disabled (loop.enabled: false): keyframes cannot be re-mapped")
            return Correction(LoopClosure.move_anchors(self.submaps, update.anchors), 0)
        return self.loop_closure.apply(self.submaps, update)

    def finish(self) -> LoopOutcome | None:
        """Call after the last frame: with ``loop.check_at_end`` (and loops detected here), the loop keyframes whose
        check never came are checked (:meth:`LoopClosure.check_unchecked`), then the two-stage global refinement when
        ``refinement.enabled`` (with or without loop closure: they are separate ablations, paper Tab. VIII). Returns
        the loop closed at the end, if any. Async: the worker maps the keyframes still queued first (their events
        then wait for :meth:`take_mapped`)."""
        self.drain()
        loop = None
        if self.loop_closure is not None and self.detect_loops and self.cfg.loop.check_at_end:
            loop = self.loop_closure.check_unchecked(self.submaps)
        if self.cfg.refinement.enabled and self.submaps:
            global_refinement(self.submaps, self.mapper, self.cfg.refinement, self.cfg.loop.registration,
                              self.descriptor, self.cfg.backend, self.device)
        return loop

    def trajectory(self) -> list[tuple[float, torch.Tensor]]:
        """(timestamp, cam_to_world) of every processed frame, with all corrections applied."""
        return [(f.timestamp, f.cam_to_world) for f in self.frames]

    def global_cloud(self) -> GaussianCloud:
        """All submaps' Gaussians in the world frame, on the compute device (inactive ones read from the store)."""
        if not self.submaps:
            return GaussianCloud.empty(device=self.device)
        return GaussianCloud.cat([s.load_cloud(self.device).transformed(s.anchor) for s in self.submaps])

    def close(self) -> None:
        """Drop the stored submaps and delete their spill folder (idempotent); the map is unusable afterwards."""
        self._close()

    def __enter__(self) -> "GauSemSLAM":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
