"""The front end: every frame's pose, from the motion model, frame-to-model tracking (paper Eq. 2), the health monitor
and relocalisation, and the keyframe decision (``slam.keyframes``).

It reads the map through the back end (the submap to track against, the recorded frames behind the motion model, all
under the back end's lock, so that a correction lands between frames) and records each placed frame there; it never
changes Gaussians or keyframe poses.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch

from gausem_core.config import SlamConfig, gap_mode_applies
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose
from gausem_core.slam.back_end import TIMES_KEPT, BackEnd
from gausem_core.slam.depth_filter import filter_observation, filters_every_frame
from gausem_core.slam.feature_start import FeatureStart
from gausem_core.slam.health import HealthMonitor, TrackingHealth, image_signals
from gausem_core.slam.keyframe_view import FILL_MODES, KeyframeView
from gausem_core.slam.keyframes import KeyframePolicy
from gausem_core.slam.observation import Observation
from gausem_core.slam.relocalisation import RelocalisationResult, Start, relocalisation_starts, track_from_starts
from gausem_core.slam.submap import FrameRecord, Submap
from gausem_core.slam.tracker import Tracker, TrackingResult, inspect_pose, repeat_motion

MAX_PREDICTION_S = 1.0  # the constant-velocity prediction extrapolates at most this far past the last good frame
STAMP_JITTER = 0.5  # ... and goes by the stamps only where they disagree with the frame count by more than this
# share: camera stamps jitter (TUM fr1/rpy: intervals 27-40 ms at 30 Hz), skipped frames are a clear gap


class MotionPrediction(NamedTuple):
    """What the motion model knows of the next frame (:meth:`FrontEnd.motion_model`)."""

    previous: torch.Tensor  # the last good frame's cam_to_world in the submap tracked against
    predicted: torch.Tensor | None  # the constant-velocity prediction (None without two good frames in a row)
    gap: bool  # camera frames were missed since the last good one (lost, dropped or skipped; or by the stamps)
    steps: float  # the latest motions the prediction repeats: frames since the last good one, or by the stamps


@dataclass
class Placement:
    """A frame as the front end placed it. ``record`` is None when the frame was dropped (lost and not relocalised:
    ``relocalised`` says why); else it is the frame's record, already in the back end's frames, and ``pose`` its
    cam_to_world in ``submap``, the submap tracked against. At a keyframe, ``observation`` is the frame as the map
    takes it (:meth:`FrontEnd.for_map`)."""

    submap: Submap
    map_age: int  # frames between the newest keyframe of ``submap`` and this frame
    record: FrameRecord | None = None
    pose: torch.Tensor | None = None
    tracked: TrackingResult | None = None
    relocalised: RelocalisationResult | None = None
    health: TrackingHealth | None = None
    keyframe: bool = False
    observation: Observation | None = None
    new_segment: bool = False  # dropped, and the frame is to start a new tracking segment (:meth:`FrontEnd.give_up`)


class FrontEnd:
    """Places frames against the back end's map (:meth:`place`).

    While :attr:`lost` (after a tracking loss, or a loaded session) frames are relocalised instead of tracked; a
    frame that cannot be relocalised is dropped. ``tracker``: another object with :meth:`Tracker.track`'s signature
    may stand in (e.g. a benchmark's oracle)."""

    def __init__(self, cfg: SlamConfig, device: torch.device, back_end: BackEnd, tracker: Tracker | None = None):
        self.cfg = cfg
        self.device = device
        self.back_end = back_end
        self.tracker = tracker if tracker is not None else Tracker(cfg.tracking, cfg.backend)
        self.feature_start = FeatureStart(cfg.tracking.feature_start)
        self.health = HealthMonitor(cfg.health)
        self.keyframes = KeyframePolicy(cfg.mapping)
        if cfg.tracking.keyframe_fill not in FILL_MODES:
            raise ValueError(f"tracking.keyframe_fill must be one of {FILL_MODES}, got {cfg.tracking.keyframe_fill!r}")
        self.fill = cfg.tracking.keyframe_fill == "always" or (cfg.tracking.keyframe_fill == "async"
                                                             and cfg.worker.mode == "async")
        self.filter_every_frame = filters_every_frame(cfg.depth_filter, cfg.worker.mode)
        self._keyframe: tuple[KeyframeView, FrameRecord] | None = None  # the newest keyframe handed over, its record
        self.lost = False  # the next frame is relocalised (:meth:`relocalise_next`; a caller may set it after a
        # tracking failure)
        self.segment_start = 0  # first frame id of the current tracking segment (the motion model stays inside it;
        # :meth:`relocalise_next` starts a new one)
        self.dropped = 0  # frames dropped (not relocalised while lost) since the last recorded frame
        self.skipped = 0  # frames the caller skipped since the last recorded frame
        self.tracking_seconds: deque[float] = deque(maxlen=TIMES_KEPT)  # wall time of the latest frames' :meth:`place`
        # (not counting its waits for the mapping worker)

    @property
    def frames(self) -> list[FrameRecord]:
        return self.back_end.frames

    def observed(self, obs: Observation) -> Observation:
        """A frame as tracking takes it: its depth filtered where every frame's is (``depth_filter.frames``)."""
        return filter_observation(obs, self.cfg.depth_filter) if self.filter_every_frame else obs

    def for_map(self, obs: Observation) -> Observation:
        """A keyframe (an :meth:`observed` frame) as the map takes it: its depth filtered."""
        return obs if self.filter_every_frame else filter_observation(obs, self.cfg.depth_filter)

    def start(self, obs: Observation, record: FrameRecord) -> None:
        """A submap's first keyframe that the back end placed without tracking (the map's first frame, or a new tracking
        segment's), recorded as ``record``, is the last good frame."""
        self.skipped = 0
        self.feature_start.remember(obs)
        self.keyframes.remember(record.frame_id, record.cam_to_world)
        self._keyframe = (KeyframeView.of(obs, torch.eye(4, device=self.device)), record) if self.fill else None

    def give_up(self) -> tuple[torch.Tensor, int]:
        """Stop relocalising (the map is lost for good): the next frame starts a new tracking segment. Returns the
        guess of its pose, the last good frame's, and the camera frames missed before it (dropped or skipped)."""
        with self.back_end.lock:
            guess = self.frames[self._last_good()].cam_to_world
        missed, self.dropped, self.skipped = self.dropped + self.skipped, 0, 0
        self.lost, self.segment_start = False, len(self.frames)
        return guess, missed

    def state_dict(self) -> dict:
        """What the front end carries from frame to frame besides the map: the tracking segment's start, whether it is
        lost, the frames dropped and skipped since the last recorded one, the health monitor's histories and the
        feature start's last good frame, as plain values and tensors; :meth:`load_state_dict` restores it."""
        return {"segment_start": self.segment_start, "lost": self.lost, "dropped": self.dropped,
                "skipped": self.skipped, "health": self.health.state_dict(),
                "feature_start": self.feature_start.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`, once the back end holds the map (the keyframe decision goes on from its newest
        keyframe); other keys of ``state`` are ignored. A state saved before tracking loss was judged (no ``lost``,
        ``dropped``, ``health``) is never lost, with empty health histories."""
        self.segment_start = state["segment_start"]
        self.lost = state.get("lost", False)
        self.dropped = state.get("dropped", 0)
        self.skipped = state.get("skipped", 0)
        if "health" in state:
            self.health.load_state_dict(state["health"])
        self.feature_start.load_state_dict(state.get("feature_start"))
        keyframes = [(submap, kf) for submap in self.back_end.submaps for kf in submap.keyframes]
        if keyframes:
            submap, newest = max(keyframes, key=lambda pair: pair[1].frame_id)
            self.keyframes.remember(newest.frame_id, submap.world_pose(newest))

    def relocalise_next(self) -> None:
        """Relocalise the next frame against the map instead of tracking it, in a new tracking segment (a loaded
        session's first frame: the motion before the save says nothing of where the camera is now)."""
        self.lost, self.segment_start = True, len(self.frames)

    def place(self, obs: Observation, frame_id: int, skipped: int) -> Placement:
        """Track the frame against the newest trackable submap (while :attr:`lost`: relocalise it, or drop it), judge
        its health, record it and decide whether it is a keyframe. ``skipped``: camera frames the caller did not pass
        on since the previous call (see :meth:`GauSemSLAM.process <gausem_core.slam.system.GauSemSLAM.process>`)."""
        self.skipped += skipped
        start = time.perf_counter()
        placement = self._place(obs, frame_id)
        self.tracking_seconds.append(time.perf_counter() - start)
        return placement

    def _place(self, obs: Observation, frame_id: int) -> Placement:
        """:meth:`place` once the map to track against is there."""
        with self.back_end.lock:  # the map the frame is tracked against, and the poses behind the motion model
            submap = self.back_end.tracked_submap()
            cloud = submap.cloud
            motion = self.motion_model(obs.timestamp)
            keyframe = self._keyframe_view(submap)
        placement = Placement(submap, frame_id - submap.keyframes[-1].frame_id)
        tracked, relocalised = self._track_or_relocalise(obs, motion, submap, cloud, keyframe)
        if tracked is None:
            new_segment = self._gives_up(obs)
            self.dropped += not new_segment
            judged = relocalised.health or TrackingHealth("lost")
            return replace(placement, relocalised=relocalised, new_segment=new_segment,
                           health=replace(judged, status="lost", reasons=(*judged.reasons, "relocalisation_failed")))
        health = self._assess(obs, tracked, relocalised, motion, cloud, keyframe)
        missed, self.dropped, self.skipped = self.dropped + self.skipped, 0, 0
        pose = tracked.cam_to_world.detach()
        self.lost = health.status == "lost"
        if not self.lost:
            self.feature_start.remember(obs)
        reference = submap.keyframes[-1]
        record = FrameRecord(frame_id, obs.timestamp, submap, reference, invert_pose(reference.cam_to_world) @ pose,
                             self.lost, missed)
        with self.back_end.lock:
            self.frames.append(record)
            world = record.cam_to_world
        keyframe = not self.lost and self.keyframes.is_keyframe(frame_id, world, obs, health,
                                                                motion.gap or relocalised is not None)
        mapped = self.for_map(obs) if keyframe else None
        if keyframe and self.fill:
            self._keyframe = (KeyframeView.of(mapped, pose), record)
        return replace(placement, record=record, pose=pose, tracked=tracked, relocalised=relocalised, health=health,
                       keyframe=keyframe, observation=mapped)

    def _gives_up(self, obs: Observation) -> bool:
        """Whether a frame that relocalisation failed to place starts a new tracking segment instead of being dropped
        (the ``relocalisation.new_segment_after``-th failure in a row)."""
        after, depth = self.cfg.relocalisation.new_segment_after, float(obs.valid_depth.float().mean())
        return 0 < after <= self.dropped + 1 and depth >= self.cfg.health.degraded_valid_depth

    def _track_or_relocalise(self, obs: Observation, motion: MotionPrediction, submap: Submap, cloud: GaussianCloud,
                             keyframe: KeyframeView | None
                             ) -> tuple[TrackingResult | None, RelocalisationResult | None]:
        """The frame's pose in ``submap`` (its Gaussians ``cloud`` as published, ``keyframe`` filling where they render
        no silhouette): tracked, or relocalised while :attr:`lost` (None when that fails)."""
        if not self.lost:
            return self._track(obs, motion, cloud, keyframe), None
        relocalised = self.relocalise(obs)
        if not relocalised.accepted:
            return None, relocalised
        self.lost = False
        with self.back_end.lock:
            local = invert_pose(submap.anchor) @ relocalised.cam_to_world
        return TrackingResult(local, relocalised.tracking_loss, relocalised.iterations), relocalised

    def _track(self, obs: Observation, motion: MotionPrediction, cloud: GaussianCloud,
               keyframe: KeyframeView | None) -> TrackingResult:
        """Track from the motion model's prediction; where the motion since the last good frame is unknown (frames were
        missed, or there is no motion model yet: a segment's second frame) the gap measures apply: the feature start
        (``feature_start``), else, where it gives no pose, the search starts (``gauss_newton.search``)."""
        unknown = motion.gap or motion.predicted is None
        featured = self.feature_start.predict(obs, motion.previous) if self.feature_start.wanted(unknown) else None
        search = featured is None and gap_mode_applies(self.cfg.tracking.gauss_newton.search, unknown)
        alternatives = [] if featured is None else [featured]
        if motion.predicted is None:
            return self.tracker.track(cloud, obs, motion.previous, alternatives, search=search, keyframe=keyframe)
        return self.tracker.track(cloud, obs, motion.predicted, [motion.previous, *alternatives], search=search,
                                  keyframe=keyframe)

    def _keyframe_view(self, submap: Submap) -> KeyframeView | None:
        """The newest keyframe handed over, posed in ``submap``, where ``tracking.keyframe_fill`` applies; under the
        back end's lock."""
        if self._keyframe is None:
            return None
        keyframe, record = self._keyframe
        return keyframe.posed(invert_pose(submap.anchor) @ record.cam_to_world)

    def motion_model(self, timestamp: float) -> MotionPrediction:
        """For a frame stamped ``timestamp``: the last good (not lost) frame's pose in the submap tracked against, the
        constant-velocity prediction, whether camera frames were missed since the last good one (lost, dropped or
        skipped ones, or by the stamps), and how many times the prediction repeats the latest motion. That motion is
        the one between the latest two consecutively recorded good frames of the tracking segment; it is repeated once
        per the camera frames it spans in the camera frames since the last good one (lost, dropped and skipped frames
        count), or, where the stamps say clearly more or less time passed (:data:`STAMP_JITTER`: a gap that nobody
        counted), over the time since the last good frame in units of that pair's interval (at most
        :data:`MAX_PREDICTION_S` ahead). No prediction without such a pair or with ``tracking.constant_velocity``
        off. Read under the back end's lock."""
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

    def _local_pose(self, index: int) -> torch.Tensor:
        """A recorded frame's pose in the frame of the submap tracked against."""
        return invert_pose(self.back_end.tracked_submap().anchor) @ self.frames[index].cam_to_world

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
                motion: MotionPrediction, cloud: GaussianCloud, keyframe: KeyframeView | None) -> TrackingHealth:
        """The health of a frame tracked to ``tracked`` against ``cloud`` (``keyframe`` filling it, as in tracking;
        before the frame is recorded), its pose jump judged against ``motion``. A relocalised frame was judged by
        relocalisation (against the submap that placed it): after a restart ok, and a new motion history starts; after
        a tracking loss as the health monitor judged it, degraded at least (``relocalised``)."""
        if relocalised is not None:
            return self._relocalised_health(obs, relocalised)
        view, moved, hessian = inspect_pose(cloud, obs, tracked.cam_to_world, self.cfg.tracking, self.cfg.backend,
                                            tracked, keyframe)  # the view tracking aligned against where it holds
        image = image_signals(view, obs, hessian, self.cfg.health, moved)
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

    def relocalise(self, obs: Observation) -> RelocalisationResult:
        """Place a frame against the map without trusting the motion model (``slam.relocalisation``): tracked from
        the constant-velocity prediction when the tracking segment has one (after a tracking loss), the last good pose
        and the ``relocalisation.candidates`` keyframes nearest by global descriptor (or the active submap's
        keyframes) of the active submap's segment (merged ones included: the others' poses are unrelated), the best
        start kept. After a tracking loss it accepts from ``health.recovery_inlier_fraction``
        (the map lacks what the lost frames would have added) and only a placement that passes the health monitor
        (:meth:`_judge_recovery`). With ``tracking.feature_start`` on, the feature start from the last good frame
        comes first. Changes nothing."""
        if not self.frames:
            raise ValueError("relocalise: the map is empty (no frame processed or loaded)")
        cfg = self.cfg.relocalisation
        recovering = self.frames[-1].lost
        if recovering:
            cfg = replace(cfg, min_inlier_fraction=min(cfg.min_inlier_fraction,
                                                       self.cfg.health.recovery_inlier_fraction))
        last = self.frames[self._last_good()]
        loop_closure = self.back_end.loop_closure
        ranked = loop_closure.nearest_keyframes(obs, cfg.candidates) if loop_closure is not None else []
        local = invert_pose(last.submap.anchor) @ last.cam_to_world
        starts = relocalisation_starts(self.back_end.segment_submaps(), (last.submap, local), ranked, cfg.candidates)
        with self.back_end.lock:
            predicted = self.motion_model(obs.timestamp).predicted
        if predicted is not None:
            starts.insert(0, Start(self.back_end.tracked_submap(), predicted, "constant velocity"))
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
        submap = self.back_end.submaps[placed.submap_id]
        local = invert_pose(submap.anchor) @ placed.cam_to_world
        view, moved, hessian = inspect_pose(submap.load_cloud(self.device), obs, local, self.cfg.tracking,
                                            self.cfg.backend)
        health = self.health.judge(placed.tracking_loss, image_signals(view, obs, hessian, self.cfg.health, moved),
                                   local, None)
        fits = health.status != "lost" and health.residual_z <= self.cfg.health.recovery_residual_z
        return replace(placed, accepted=fits, health=health)
