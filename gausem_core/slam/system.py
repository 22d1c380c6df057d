"""The SLAM system: one object that takes observations and owns the map, composed of a front end (motion model,
tracking, health, relocalisation, the keyframe decision: ``slam.front_end``) and a back end (the map of submaps and
everything that changes it: ``slam.back_end``), each owning its state.

``worker.mode: sync`` maps each keyframe inside the :meth:`GauSemSLAM.process` call that tracked it (deterministic);
``async`` hands it to the back end's mapping thread and returns after tracking (``slam.worker``).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import torch

from gausem_core.config import WORKER_MODES, SlamConfig, check_gap_mode
from gausem_core.gaussians import GaussianCloud
from gausem_core.native import kernel_available
from gausem_core.render import prepare_backend
from gausem_core.slam.allocation import Decision
from gausem_core.slam.back_end import BackEnd
from gausem_core.slam.events import Correction, FrameEvents, KeyframeState, SubmapChange
from gausem_core.slam.front_end import FrontEnd
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.loop import LoopCandidate
from gausem_core.slam.loop_closure import LoopClosure, LoopOutcome
from gausem_core.slam.loop_graphs import PoseGraphUpdate
from gausem_core.slam.observation import Observation
from gausem_core.slam.persistence import read_document, restore_session, save_session, saved_config
from gausem_core.slam.relocalisation import RelocalisationResult
from gausem_core.slam.submap import FrameRecord, Submap
from gausem_core.slam.tracker import Tracker
from gausem_core.slam.vignetting import Vignetting
from gausem_core.slam.worker import MappingWorker


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
    (the loop database still stores them, unchecked: a saved session holds them either way). ``tracker``: see
    :class:`~gausem_core.slam.front_end.FrontEnd`. Call :meth:`close` (or use ``with``) to stop the mapping worker and
    delete spilled submaps at once; otherwise that happens when the object is collected.

    :meth:`save` writes the whole state to a folder and :meth:`load` restores it (see ``slam.persistence``). A loaded
    system is :attr:`lost`: the first frame given to :meth:`process` is relocalised against the map
    (:meth:`relocalise`) instead of tracked from the last pose; when relocalisation fails the frame is dropped (not
    recorded, the map untouched, ``FrameResult.relocalisation.accepted`` False) and the next frame tries again.

    Every frame's tracking is judged (``FrameResult.health``, see ``slam.health``). A frame judged lost is recorded (its
    pose, for the trajectory) but not mapped, even at a keyframe, and the system becomes :attr:`lost`: the next frames
    are relocalised, the constant-velocity prediction from the last good frames first among the starts, until a
    placement passes the health monitor. That frame is degraded (reason ``relocalised``: it was not tracked from the
    frame before) and tracking goes on from it, the motion model skipping the lost frames.

    ``worker.mode: async``: the tracker tracks against the Gaussians the worker last published (a new map's, placed
    from the first frame's depth at once, optimised in the worker), and a keyframe's events reach the caller with a
    later frame (``FrameResult.mapped``, or :meth:`take_mapped` after :meth:`finish`). Map corrections (keyframe poses,
    anchors) happen under :attr:`lock`, which the front end holds while it reads the poses behind its motion model.
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
        self.back_end = BackEnd(cfg, self.device, num_classes, detect_loops)
        self.front_end = FrontEnd(cfg, self.device, self.back_end, tracker)

    # --- the map, as the back end holds it ---
    @property
    def submaps(self) -> list[Submap]:
        return self.back_end.submaps

    @property
    def frames(self) -> list[FrameRecord]:
        """Every processed frame's record, in order."""
        return self.back_end.frames

    @property
    def active(self) -> Submap:
        return self.back_end.active

    @property
    def loop_closure(self) -> LoopClosure | None:
        return self.back_end.loop_closure

    @property
    def lock(self):
        """The map's lock: held while the map's poses change and while they are read in one piece (what it guards
        and who takes it: where it is created, ``Mapper.__init__``)."""
        return self.back_end.lock

    @property
    def num_classes(self) -> int:
        return self.back_end.num_classes

    @property
    def detect_loops(self) -> bool:
        """Whether loops are detected here (False: elsewhere, see the class docstring); settable, e.g. on a loaded
        system that is to hand its place signatures to another detector."""
        return self.back_end.detect_loops

    @detect_loops.setter
    def detect_loops(self, value: bool) -> None:
        self.back_end.detect_loops = value

    def segments(self) -> list[set[int]]:
        """Submap ids by tracking segment (a new one starts where the tracker lost the map for good), those a loop
        merged together; one set while the map is one."""
        return self.back_end.segments()

    @property
    def worker(self) -> MappingWorker | None:
        """The mapping worker of ``worker.mode: async`` (its queue ``depth``, its ``stats``); None in sync mode."""
        return self.back_end.worker

    @property
    def vignetting(self) -> Vignetting:
        """The online vignetting estimate: V(r) = exp(a r^2), ``a`` its current value."""
        return self.back_end.vignetting

    @property
    def asynchronous(self) -> bool:
        """Whether keyframes are mapped on the mapping thread (``worker.mode: async``)."""
        return self.back_end.worker is not None

    @property
    def lost(self) -> bool:
        """Whether the next frame is relocalised instead of tracked."""
        return self.front_end.lost

    @lost.setter
    def lost(self, value: bool) -> None:
        self.front_end.lost = value

    def process(self, obs: Observation, skipped: int = 0) -> FrameResult:
        """Track the frame against the newest trackable submap (while :attr:`lost`: relocalise it, or drop it when
        that fails); at a keyframe, start a new submap when the allocation policy says so, else map the keyframe into
        the active one (``worker.mode: async``: on the mapping thread, after this call returns). ``skipped``: the
        camera's frames since the previous call that the caller did not pass on (a live node that fell behind, dropped
        inputs); the motion model counts them, as its stamps alone miss a node that is steadily slower than its
        camera."""
        if skipped < 0:
            raise ValueError(f"skipped must be >= 0, got {skipped}")
        back = self.back_end
        back.raise_error()
        obs = self.front_end.observed(back.vignetting.correct(obs))
        frame_id = len(self.frames)
        back.mapper.hurry.clear()
        if not self.submaps:
            return self._start(obs, frame_id)
        placed = self.front_end.place(obs, frame_id, skipped)
        if placed.new_segment:
            return self._start(obs, frame_id, placed.health)
        if placed.record is None:  # lost and not relocalised: the frame is dropped
            reloc = placed.relocalised
            return FrameResult(frame_id, reloc.cam_to_world, False, reloc.tracking_loss, reloc.iterations, None,
                               placed.submap.num_gaussians, placed.submap.submap_id, None, reloc, placed.health,
                               mapped=self.take_mapped(), map_age=placed.map_age)
        mapped = back.add_keyframe(placed.observation, placed.record, placed.pose) if placed.keyframe else None
        events, loss, decision = mapped or (None, None, None)
        tracked = placed.tracked
        return self._result(frame_id, placed.keyframe, tracked.loss, tracked.iterations, loss, decision,
                            placed.relocalised, placed.health, events, placed.map_age)

    def _start(self, obs: Observation, frame_id: int, lost: TrackingHealth | None = None) -> FrameResult:
        """The map's first frame; or, once the tracker has lost the map for good (``lost``: the health of the last
        failed relocalisation), a new tracking segment's first frame (see ``relocalisation.new_segment_after``)."""
        obs = self.front_end.for_map(obs)
        segment = None if lost is None else self.front_end.give_up()
        events, loss = self.back_end.start(obs, frame_id, segment)
        self.front_end.start(obs, self.frames[-1])
        health = None if lost is None else replace(lost, status="degraded", reasons=(*lost.reasons, "new_segment"))
        return self._result(frame_id, True, 0.0, 0, loss, health=health, events=events)

    def _result(self, frame_id: int, is_keyframe: bool, tracking_loss: float, iterations: int,
                mapping_loss: float | None, allocation: Decision | None = None,
                relocalised: RelocalisationResult | None = None, health: TrackingHealth | None = None,
                events: FrameEvents | None = None, map_age: int = 0) -> FrameResult:
        """A recorded frame's result (the first frame, which defines the world frame, is ok)."""
        return FrameResult(frame_id, self.frames[frame_id].cam_to_world, is_keyframe, tracking_loss, iterations,
                           mapping_loss, self.active.num_gaussians, self.active.submap_id, allocation, relocalised,
                           health or TrackingHealth("ok"), events or FrameEvents(), self.take_mapped(), map_age)

    def take_mapped(self) -> tuple[FrameEvents, ...]:
        """``worker.mode: async``: the events of the keyframes mapped since the last call (or frame), in order."""
        return self.back_end.take_mapped()

    def drain(self) -> None:
        """Wait until the mapping worker has mapped every keyframe given to it (nothing to wait for in sync mode);
        their events stay for :meth:`take_mapped`."""
        self.back_end.drain()

    def interrupt(self) -> None:
        """Ask the frame in progress (in another thread) to finish early, e.g. on Ctrl-C: optimisations stop at their
        next iteration, so the map stays consistent, only less refined. The next frame clears it."""
        self.back_end.mapper.hurry.set()

    def relocalise(self, obs: Observation) -> RelocalisationResult:
        """Place a frame against the map without trusting the motion model (see
        :meth:`FrontEnd.relocalise <gausem_core.slam.front_end.FrontEnd.relocalise>`); changes nothing."""
        return self.front_end.relocalise(obs)

    def save(self, folder) -> None:
        """Write the whole state into ``folder`` (see :func:`gausem_core.slam.persistence.save_session`)."""
        self.drain()
        save_session(folder, self.front_end, self.back_end)

    @classmethod
    def load(cls, folder, device: torch.device | str = "cpu", cfg: SlamConfig | None = None,
             relocalise: bool = True) -> "GauSemSLAM":
        """The system saved in ``folder`` (``slam.persistence``), on ``device``, with its saved configuration unless
        ``cfg`` is given. With ``relocalise`` (default) it starts :attr:`lost` with a new tracking segment: its next
        frame is placed against the map by relocalisation, without the motion model, before tracking goes on; without,
        it goes on exactly as the saved system would have (lost too if that was)."""
        document = read_document(folder)
        slam = cls(cfg or saved_config(document), device, document["num_classes"], document["detect_loops"])
        restore_session(folder, document, slam.front_end, slam.back_end)
        if relocalise and slam.submaps:
            slam.front_end.relocalise_next()
        return slam

    def keyframe_states(self, submap_id: int | None = None) -> list[KeyframeState]:
        """The keyframes (of one submap, or all) with their current poses, in order."""
        return self.back_end.keyframe_states(submap_id)

    def submap_states(self) -> list[SubmapChange]:
        """Every submap as opened (e.g. to announce a loaded map), with its current anchor."""
        return self.back_end.submap_states()

    def register_loop(self, candidates: Sequence[LoopCandidate]) -> LoopOutcome | None:
        """Close a loop detected elsewhere: among one query keyframe's ranked candidates (from the detector's
        :meth:`~gausem_core.slam.loop.LoopDetector.add_keyframe` for its place signature, ``FrameEvents.place``) the
        one the loop closure confirms is registered (keyframe alignment or SGR); the outcome's constraint is set when
        accepted; None when none is confirmed. The map is not corrected: that is the pose graph's answer
        (:meth:`apply_pose_graph`). Raises ValueError when loop closure is disabled or the candidates name unknown
        keyframes or several query keyframes."""
        return self.back_end.register_loop(candidates)

    def apply_pose_graph(self, update: PoseGraphUpdate) -> Correction:
        """Move the map to a pose graph's answer: anchors (world-from-submap), then keyframe poses (submap frame),
        each submap whose keyframes moved re-mapped with them held. Unknown ids are ignored."""
        return self.back_end.apply_pose_graph(update)

    def finish(self) -> LoopOutcome | None:
        """Call after the last frame: with ``loop.check_at_end`` (and loops detected here), the loop keyframes whose
        check never came are checked (:meth:`LoopClosure.check_unchecked`), then the two-stage global refinement when
        ``refinement.enabled`` (with or without loop closure: they are separate ablations, paper Tab. VIII). Returns
        the loop closed at the end, if any. Async: the worker maps the keyframes still queued first (their events
        then wait for :meth:`take_mapped`)."""
        return self.back_end.finish()

    def trajectory(self, include_lost: bool = True) -> list[tuple[float, torch.Tensor]]:
        """(timestamp, cam_to_world) of every processed frame, with all corrections applied; without
        ``include_lost``, of those whose tracking was not judged lost."""
        return [(f.timestamp, f.cam_to_world) for f in self.frames if include_lost or not f.lost]

    def global_cloud(self) -> GaussianCloud:
        """All submaps' Gaussians in the world frame, on the compute device (inactive ones read from the store)."""
        return self.back_end.global_cloud()

    def close(self) -> None:
        """Stop the mapping worker, drop the stored submaps and delete their spill folder (idempotent); the map is
        unusable afterwards."""
        self.back_end.close()

    def __enter__(self) -> "GauSemSLAM":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
