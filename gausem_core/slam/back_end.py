"""The back end: the map and everything that changes it (keyframes, Gaussian mapping, submap allocation and storage,
vignetting calibration, loop closure, refinement), and in ``worker.mode: async`` the mapping worker that runs it.

It owns the submaps and the records of the processed frames, which hang off their keyframes (``slam.submap``). The
front end reads both to track (under :attr:`BackEnd.lock`) and hands every frame's record and its keyframes to
:meth:`BackEnd.add_keyframe`. At every keyframe the allocation policy (``submaps.policy``) decides whether it starts a
new submap. If so, the active submap gets a boundary local BA over its last keyframes and is closed (offloaded to the
store, CPU memory up to ``submaps.memory_budget_mb``, disk beyond); the new submap's anchor is the old anchor composed
with the keyframe's pose in the old submap, and it is initialised from the keyframe by semantic sampling.
"""
from __future__ import annotations

import time
import weakref
from collections import Counter, deque
from collections.abc import Sequence
from functools import partial

import torch

from gausem_core.config import SlamConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, rigid_product
from gausem_core.memory import release_free_heap
from gausem_core.semantics.descriptors import make_descriptor
from gausem_core.slam.allocation import Decision, SubmapExtent, make_allocation
from gausem_core.slam.events import Correction, FrameEvents, KeyframeState, SubmapChange
from gausem_core.slam.loop import LoopCandidate
from gausem_core.slam.loop_closure import LoopClosure, LoopOutcome
from gausem_core.slam.loop_graphs import PoseGraphUpdate
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.observation import Observation
from gausem_core.slam.pose_graph import chain_links, components
from gausem_core.slam.refinement import global_refinement
from gausem_core.slam.submap import FrameRecord, Submap
from gausem_core.slam.submap_store import SubmapStore
from gausem_core.slam.vignetting import Vignetting
from gausem_core.slam.worker import Job, MappingWorker, split_threads


TIMES_KEPT = 10_000  # the latest keyframes' mapping times kept (and the front end's tracking times)


def _float64(pose: torch.Tensor) -> torch.Tensor:
    """A stored pose as it is, in float64 on the CPU (events; see :mod:`~gausem_core.slam.events`)."""
    return pose.detach().cpu().double()


def _shut_down(worker: MappingWorker | None, store: SubmapStore) -> None:
    """Stop the mapping worker, then drop the stored submaps (:meth:`BackEnd.close`)."""
    if worker is not None:
        worker.stop()
    store.close()


class BackEnd:
    """The map (:attr:`submaps`, :attr:`frames`) and its mapping. ``worker.mode: sync`` maps a keyframe inside
    :meth:`add_keyframe`; ``async`` queues it for the mapping thread, whose keyframes' events come back through
    :meth:`take_mapped`. Poses of keyframes and anchors, and frame records, change under :attr:`lock`."""

    def __init__(self, cfg: SlamConfig, device: torch.device, num_classes: int, detect_loops: bool):
        self.cfg = cfg
        self.device = device
        self.num_classes = num_classes
        self.detect_loops = detect_loops
        self.mapper = Mapper(cfg.mapping, cfg.backend, cfg.seed)
        self.lock = self.mapper.lock  # the map's lock: what it guards and who takes it, see ``Mapper.__init__``
        self.allocation = make_allocation(cfg.submaps)
        self.allocation_rules: Counter = Counter()  # (rule, whether it opened a submap) of every allocation decision
        self.vignetting = Vignetting(cfg.vignetting)
        self.store = SubmapStore(int(cfg.submaps.memory_budget_mb * 2**20), cfg.submaps.cache_dir or None)
        self.submaps: list[Submap] = []
        self.frames: list[FrameRecord] = []  # every processed frame, in order
        self.descriptor = make_descriptor(cfg.semantics.descriptor, cfg.semantics.dinov2_weights,
                                          device=device) if cfg.loop.enabled or cfg.refinement.enabled else None
        self.loop_closure = LoopClosure(cfg.loop, self.mapper, self.descriptor, cfg.backend,
                                        device) if cfg.loop.enabled else None
        self._mapped: list[FrameEvents] = []  # async: finished keyframes' events not yet handed out
        self.mapping_seconds: deque[float] = deque(maxlen=TIMES_KEPT)  # wall time of the latest keyframes' mapping
        self.growth_seconds: deque[float] = deque(maxlen=TIMES_KEPT)  # async: the tracker's growth of keyframes
        self.window_iterations: dict[int, int] = {}  # optimisation steps over each newest keyframe's window
        self._idle_spent = (-1, 0)  # (newest keyframe, idle steps given to its window)
        self.window_ages: deque[int] = deque(maxlen=TIMES_KEPT)  # tracker frames past the newest keyframe, per
        # optimisation (a job's or an idle round's)
        self.worker = self._start_worker() if cfg.worker.mode == "async" else None
        self._close = weakref.finalize(self, _shut_down, self.worker, self.store)

    def _start_worker(self) -> MappingWorker:
        """The mapping thread of ``worker.mode: async``; the calling (tracking) thread keeps its share of the
        cores."""
        cfg = self.cfg.worker
        tracker_threads, worker_threads = split_threads(cfg.tracker_threads, cfg.threads)
        torch.set_num_threads(tracker_threads)
        self.mapper.min_iteration_fraction = cfg.min_iteration_fraction
        idle = self._refine_window if cfg.idle_iterations > 0 and cfg.max_idle_iterations > 0 else None
        return MappingWorker(lambda: len(self.frames), cfg.queue_size, worker_threads, self.mapper.pressure, idle)

    def _refine_window(self) -> bool:
        """Anytime mapping (the worker's idle work): ``worker.idle_iterations`` more steps over the active submap's
        newest keyframes' window; False once the newest keyframe's window has had ``worker.max_idle_iterations``."""
        submap, cfg = self.active, self.cfg.worker
        newest = submap.keyframes[-1].frame_id
        spent = self._idle_spent[1] if self._idle_spent[0] == newest else 0
        budget = min(cfg.idle_iterations, cfg.max_idle_iterations - spent)
        if budget <= 0:
            return False
        cloud, losses = self._optimise_window(submap, budget)
        submap.cloud = cloud
        self._idle_spent = (newest, spent + budget)
        return bool(losses)

    def _optimise_window(self, submap: Submap, iterations: int) -> tuple[GaussianCloud, list[float]]:
        """``iterations`` steps over ``submap``'s newest keyframes (``mapping.window``), the pending Gaussians taken
        in; counted for the newest keyframe, with the window's age."""
        newest = submap.keyframes[-1].frame_id
        self.window_ages.append(len(self.frames) - 1 - newest)
        cloud, losses = self.mapper.optimise(submap.take_cloud(), submap.keyframes[-self.cfg.mapping.window:],
                                             iterations)
        self.window_iterations[newest] = self.window_iterations.get(newest, 0) + len(losses)
        return cloud, losses

    @property
    def active(self) -> Submap:
        """The submap keyframes are mapped into (the newest)."""
        return self.submaps[-1]

    def tracked_submap(self) -> Submap:
        """The submap frames are tracked against: the newest (its Gaussians from its first keyframe's depth are a map
        before any optimisation)."""
        return self.submaps[-1]

    def segments(self) -> list[set[int]]:
        """Submap ids by tracking segment (a new one starts where the tracker lost the map for good), segments that
        inter-submap loops joined merged; ordered by their first submap."""
        keys = [s.submap_id for s in self.submaps]
        breaks = [s.submap_id for s in self.submaps if s.starts_segment]
        loops = [] if self.loop_closure is None else [(c.submap_a, c.submap_b) for c in self.loop_closure.constraints
                                                      if not c.intra]
        return components(keys, chain_links(keys, breaks) + loops)

    def segment_submaps(self) -> list[Submap]:
        """The submaps of the active one's segment (merged ones included), in order: those a frame tracked in it can
        be placed against."""
        group = next(g for g in self.segments() if self.active.submap_id in g)
        return [s for s in self.submaps if s.submap_id in group]

    def raise_error(self) -> None:
        """Raise the mapping worker's error, if a job failed (nothing in sync mode)."""
        if self.worker is not None:
            self.worker.raise_error()

    def take_mapped(self) -> tuple[FrameEvents, ...]:
        """``worker.mode: async``: the events of the keyframes mapped since the last call, in order."""
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

    def start(self, obs: Observation, frame_id: int, segment: tuple[torch.Tensor, int] | None = None
              ) -> tuple[FrameEvents | None, float | None]:
        """The map's first frame, which defines the world frame: a submap from its depth (semantic sampling), then
        optimised. With ``segment`` (the guess of its pose, the camera frames missed before it): the first frame of a
        new, disconnected tracking segment (the tracker lost the map for good), its submap anchored at the guess and
        the active one closed. Returns its events and last mapping loss (async: (None, None); the optimisation runs on
        the worker, the unoptimised Gaussians tracked against meanwhile)."""
        anchor, missed = segment if segment is not None else (torch.eye(4, device=self.device), 0)
        closing = self.active if self.submaps else None
        self.drain()  # async: keyframes queued before the loss map into the submap they were tracked in
        submap = self._place_submap(obs, frame_id, anchor, starts_segment=closing is not None)
        self.frames[-1].skipped = missed
        if self.worker is not None:
            self.worker.submit(Job(frame_id, "open", lambda: self._timed(self._first_job, submap, obs, closing)[0]))
            return None, None
        return self._timed(self._first_job, submap, obs, closing)

    def add_keyframe(self, obs: Observation, record: FrameRecord,
                     pose: torch.Tensor) -> tuple[FrameEvents, float | None, Decision] | None:
        """Map the frame the front end recorded as ``record`` (the last one), tracked to ``pose`` in its submap, as a
        keyframe (see :meth:`_map`): now in sync mode, returning its events, the last mapping loss and the allocation
        decision. Async: its new Gaussians (where the map lacks its view) join the map now, on the tracker's clock,
        and it is queued for the worker (None), mapped at its pose as corrected by then."""
        if self.worker is None:
            return self._timed(self._map, obs, pose, record)
        start = time.perf_counter()
        opacity = self.cfg.worker.first_opacity
        record.submap.grow(lambda cloud: self.mapper.strategy.new_gaussians(cloud, obs, pose, opacity))
        self.growth_seconds.append(time.perf_counter() - start)
        self.worker.submit(Job(record.frame_id, "keyframe", partial(self._timed, self._keyframe_job, obs, record)))
        return None

    def _timed(self, run, *args):
        """``run(*args)``, its wall time kept in :attr:`mapping_seconds` (a keyframe's mapping: optimisation, a new
        submap's opening, loop closure; in sync mode or on the worker)."""
        start = time.perf_counter()
        result = run(*args)
        self.mapping_seconds.append(time.perf_counter() - start)
        return result

    def _first_job(self, submap: Submap, obs: Observation,
                   closing: Submap | None = None) -> tuple[FrameEvents, float | None]:
        """The mapping half of :meth:`start` (async: on the worker): optimisation, vignetting calibration, the
        submap it follows closed (``closing``: a new tracking segment's), the keyframe's events; and the last mapping
        loss."""
        loss = self._optimise_first(submap)
        self._calibrate(obs, submap.keyframes[0].cam_to_world)
        closed = []
        if closing is not None:
            closed.append(self._submap_change(closing, opened=False))
            self._boundary_adjust(closing)
            closing.offload(self.store)
        return self._keyframe_events(closed), loss

    def _keyframe_job(self, obs: Observation, record: FrameRecord) -> FrameEvents:
        """The worker's mapping of a keyframe the front end recorded as ``record``: at its current pose (corrections
        since carried it along) in the active submap."""
        with self.lock:  # (projected onto SE(3): re-expressed poses must not drift off it, chained keyframe on keyframe)
            pose = rigid_product(invert_pose(self.active.anchor), record.cam_to_world)
        return self._map(obs, pose, record)[0]

    def _map(self, obs: Observation, pose: torch.Tensor,
             record: FrameRecord) -> tuple[FrameEvents, float | None, Decision]:
        """A keyframe at ``pose`` in the active submap: vignetting calibration, the allocation decision, then a new
        submap (the active one closed) or the keyframe mapped into the active one, then loop closure. ``record`` (the
        frame's) is re-anchored at the keyframe. Returns the keyframe's events, the last mapping loss and the
        allocation decision."""
        obs = self._calibrate(obs, pose)
        decision = self.allocation.should_start_new(self.active.extent, obs, pose)
        self.allocation_rules[decision.rule, decision.new] += 1
        closed = []
        if decision.new:
            old = self.active
            closed.append(self._submap_change(old, opened=False))
            self._boundary_adjust(old)
            submap = self._place_submap(obs, record.frame_id, rigid_product(old.anchor, pose), record)
            loss = self._optimise_first(submap)
            old.offload(self.store)  # after: its pending Gaussians go with it
        else:
            loss = self._map_keyframe(obs, pose, record)
        events = self._keyframe_events(closed)
        release_free_heap()  # mapping and loop closure freed many image-sized buffers
        return events, loss, decision

    def _map_keyframe(self, obs: Observation, pose: torch.Tensor, record: FrameRecord) -> float | None:
        """Add a keyframe to the active submap: densify (async: done by :meth:`add_keyframe`), BA over the recent
        keyframes, then detail where the map still misses the keyframe's colour."""
        submap = self.active
        kf = Keyframe(record.frame_id, obs, pose)
        with self.lock:
            submap.keyframes.append(kf)
            self._anchor_record(record, submap, kf)
        submap.extent.add(obs, pose)
        if self.worker is None:
            submap.cloud = self.mapper.strategy.grow(submap.cloud, obs, pose)
        cloud, losses = self._optimise_window(submap, self.cfg.mapping.iterations)
        submap.cloud = self.mapper.strategy.add_detail(cloud, kf.obs, kf.cam_to_world)
        return losses[-1] if losses else None

    def _anchor_record(self, record: FrameRecord | None, submap: Submap, keyframe: Keyframe) -> None:
        """Make ``record`` (the keyframe's frame) relative to its keyframe, the frames recorded after it (async)
        re-expressed relative to it too (their poses unchanged: later corrections carry them with their nearest
        keyframe); a frame not tracked (``record`` None: the map's first, a new segment's) is recorded so. Under
        :attr:`lock`."""
        eye = torch.eye(4, device=self.device)
        if record is None:
            self.frames.append(FrameRecord(keyframe.frame_id, keyframe.obs.timestamp, submap, keyframe, eye))
            return
        base = submap.anchor @ keyframe.cam_to_world
        for later in reversed(self.frames):
            if later is record:
                break
            if later.reference.frame_id < record.frame_id:
                later.submap, later.reference, later.relative = submap, keyframe, rigid_product(invert_pose(base),
                                                                                               later.cam_to_world)
        record.submap, record.reference, record.relative = submap, keyframe, eye

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

    def _place_submap(self, obs: Observation, frame_id: int, anchor: torch.Tensor, record: FrameRecord | None = None,
                      starts_segment: bool = False) -> Submap:
        """A new active submap anchored (world-from-submap) at ``anchor``: its first keyframe is ``obs``, fixed at the
        identity, and its Gaussians come from semantic sampling of its depth, tracked against at once (async: before
        :meth:`_optimise_first`). ``record``: the frame's record (None for a frame not tracked: the map's first, or a
        new tracking segment's, ``starts_segment``)."""
        eye = torch.eye(4, device=self.device)
        kf = Keyframe(frame_id, obs, eye, fixed=True)
        opacity = self.cfg.worker.first_opacity if self.worker is not None else None
        submap = Submap(len(self.submaps), anchor, self.mapper.strategy.initial(obs, eye, opacity), [kf],
                        SubmapExtent.start(obs, eye, self.num_classes), starts_segment)
        with self.lock:
            self.submaps.append(submap)
            self._anchor_record(record, submap, kf)
        return submap

    def _optimise_first(self, submap: Submap) -> float | None:
        """The initial optimisation of a new submap's Gaussians over its first keyframe; the last loss. Async: the
        Gaussians are published every ``worker.publish_every`` steps."""
        def publish(cloud: GaussianCloud) -> None:
            submap.cloud = cloud

        every = self.cfg.worker.publish_every if self.worker is not None else 0
        cloud, losses = self.mapper.optimise(submap.take_cloud(), submap.keyframes[:1],
                                             self.cfg.mapping.init_iterations, publish=publish, publish_every=every)
        first = submap.keyframes[0]
        publish(self.mapper.strategy.add_detail(cloud, first.obs, first.cam_to_world))
        return losses[-1] if losses else None

    def _boundary_adjust(self, submap: Submap) -> None:
        """Boundary local BA over a submap's last keyframes, then the Gaussians hidden from all its keyframes pruned,
        before it is closed (offloaded)."""
        window = submap.keyframes[-self.cfg.submaps.boundary_window:]
        cloud, _ = self.mapper.optimise(submap.take_cloud(), window, self.cfg.submaps.boundary_iterations)
        views = [(invert_pose(kf.cam_to_world), kf.obs.camera) for kf in submap.keyframes]
        submap.cloud = self.mapper.strategy.prune_hidden(cloud, views)

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
        """See :meth:`GauSemSLAM.register_loop <gausem_core.slam.system.GauSemSLAM.register_loop>`."""
        if self.loop_closure is None:
            raise ValueError("loop closure is disabled (loop.enabled: false)")
        self.drain()  # async: registration reads, and a re-map writes, the submaps the worker maps
        candidate = self.loop_closure.confirm(self.submaps, candidates)
        return None if candidate is None else self.loop_closure.register(self.submaps, candidate)

    def apply_pose_graph(self, update: PoseGraphUpdate) -> Correction:
        """See :meth:`GauSemSLAM.apply_pose_graph <gausem_core.slam.system.GauSemSLAM.apply_pose_graph>`."""
        self.drain()
        if self.loop_closure is None:
            if update.keyframes:
                raise ValueError("loop closure is disabled (loop.enabled: false): keyframes cannot be re-mapped")
            return Correction(LoopClosure.move_anchors(self.submaps, update.anchors), 0)
        return self.loop_closure.apply(self.submaps, update)

    def finish(self) -> LoopOutcome | None:
        """See :meth:`GauSemSLAM.finish <gausem_core.slam.system.GauSemSLAM.finish>`."""
        self.drain()
        loop = None
        if self.loop_closure is not None and self.detect_loops and self.cfg.loop.check_at_end:
            loop = self.loop_closure.check_unchecked(self.submaps)
        if self.cfg.refinement.enabled and self.submaps:
            global_refinement(self.submaps, self.mapper, self.cfg.refinement, self.cfg.loop.registration,
                              self.descriptor, self.cfg.backend, self.device)
        return loop

    def global_cloud(self) -> GaussianCloud:
        """All submaps' Gaussians in the world frame, on the compute device (inactive ones read from the store, where
        they stay). Joined field by field, each field's parts freed as it is joined: the map is held about once."""
        if not self.submaps:
            return GaussianCloud.empty(device=self.device)
        parts = [s.load_cloud(self.device).transformed(s.anchor).tensors() for s in list(self.submaps)]
        return GaussianCloud(**{name: torch.cat([part.pop(name) for part in parts]) for name in list(parts[0])})

    def state_dict(self) -> dict:
        """What the map holds besides its submaps (each exports itself, :meth:`Submap.state_dict`): the frame records,
        the vignetting estimate, the mapper's random state and the loop closure's state (None without one), as plain
        values and tensors; :meth:`load_state_dict` restores it."""
        return {"frames": [f.state_dict() for f in self.frames], "vignetting": self.vignetting.state_dict(),
                "mapper_generator": self.mapper.state_dict()["generator"],
                "loop_closure": None if self.loop_closure is None else self.loop_closure.state_dict()}

    def load_state_dict(self, state: dict, submaps: Sequence[Submap]) -> None:
        """Restore :meth:`state_dict` onto this back end, whose map is empty, with the ``submaps`` it was saved with
        (:meth:`Submap.from_state`, in order); other keys of ``state`` are ignored, and older sessions may lack
        ``vignetting``."""
        if self.submaps or self.frames:
            raise ValueError("BackEnd.load_state_dict: the map is not empty")
        self.submaps.extend(submaps)
        by_id = {s.submap_id: s for s in self.submaps}
        self.frames.extend(FrameRecord.from_state(f, by_id, self.device) for f in state["frames"])
        if "vignetting" in state:
            self.vignetting.load_state_dict(state["vignetting"])
        self.mapper.load_state_dict({"generator": state["mapper_generator"]})
        if self.loop_closure is not None and state["loop_closure"] is not None:
            self.loop_closure.load_state_dict(state["loop_closure"])

    def close(self) -> None:
        """Stop the worker, drop the stored submaps and delete their spill folder (idempotent)."""
        self._close()
