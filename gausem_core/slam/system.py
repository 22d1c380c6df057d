"""The SLAM system: one object that takes observations and owns the map (tracker + mapper over a submap)."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from gausem_core.config import SlamConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.observation import Observation
from gausem_core.slam.tracker import Tracker, constant_velocity


@dataclass
class Submap:
    """Gaussians and keyframes in a local frame anchored at the first keyframe; ``anchor`` is world-from-submap."""

    submap_id: int
    anchor: torch.Tensor
    cloud: GaussianCloud
    keyframes: list[Keyframe] = field(default_factory=list)


@dataclass
class FrameRecord:
    """A processed frame, stored relative to its reference keyframe so map corrections carry it along."""

    frame_id: int
    timestamp: float
    submap: Submap
    reference: Keyframe
    relative: torch.Tensor  # reference-keyframe-from-camera

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
    num_gaussians: int


class GauSemSLAM:
    def __init__(self, cfg: SlamConfig, device: torch.device | str = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)
        self.tracker = Tracker(cfg.tracking, cfg.backend)
        self.mapper = Mapper(cfg.mapping, cfg.backend, cfg.seed)
        self.submaps: list[Submap] = []
        self.frames: list[FrameRecord] = []

    @property
    def active(self) -> Submap:
        return self.submaps[-1]

    def process(self, obs: Observation) -> FrameResult:
        """Track the frame against the active submap, then map when it is a keyframe."""
        frame_id = len(self.frames)
        if not self.submaps:
            return self._start(obs, frame_id)
        submap = self.active
        prev = self._local_pose(-1)
        before = self._local_pose(-2) if len(self.frames) > 1 and self.cfg.tracking.constant_velocity else None
        result = self.tracker.track(submap.cloud, obs, constant_velocity(prev, before))
        pose = result.cam_to_world
        is_keyframe = frame_id % self.cfg.mapping.every == 0
        mapping_loss = None
        if is_keyframe:
            kf = Keyframe(frame_id, obs, pose)
            submap.keyframes.append(kf)
            submap.cloud = self.mapper.densify(submap.cloud, obs, pose)
            window = submap.keyframes[-self.cfg.mapping.window:]
            submap.cloud, losses = self.mapper.optimise(submap.cloud, window, self.cfg.mapping.iterations)
            mapping_loss = losses[-1] if losses else None
            self.frames.append(FrameRecord(frame_id, obs.timestamp, submap, kf, torch.eye(4, dtype=pose.dtype)))
        else:
            reference = submap.keyframes[-1]
            self.frames.append(FrameRecord(frame_id, obs.timestamp, submap, reference,
                                           invert_pose(reference.cam_to_world) @ pose))
        return FrameResult(frame_id, self.frames[-1].cam_to_world, is_keyframe, result.loss, result.iterations,
                           mapping_loss, len(submap.cloud))

    def _start(self, obs: Observation, frame_id: int) -> FrameResult:
        """The first frame defines the world frame (identity pose): no ground truth is ever read."""
        pose = torch.eye(4, device=self.device)
        kf = Keyframe(frame_id, obs, pose, fixed=True)
        cloud = self.mapper.initialise(obs, pose)
        cloud, losses = self.mapper.optimise(cloud, [kf], self.cfg.mapping.init_iterations)
        submap = Submap(len(self.submaps), torch.eye(4, device=self.device), cloud, [kf])
        self.submaps.append(submap)
        self.frames.append(FrameRecord(frame_id, obs.timestamp, submap, kf, torch.eye(4, device=self.device)))
        return FrameResult(frame_id, pose, True, 0.0, 0, losses[-1] if losses else None, len(cloud))

    def _local_pose(self, index: int) -> torch.Tensor:
        """A recent frame's pose in the active submap's frame."""
        record = self.frames[index]
        return invert_pose(self.active.anchor) @ record.cam_to_world

    def trajectory(self) -> list[tuple[float, torch.Tensor]]:
        """(timestamp, cam_to_world) of every processed frame, with all corrections applied."""
        return [(f.timestamp, f.cam_to_world) for f in self.frames]

    def global_cloud(self) -> GaussianCloud:
        """All submaps' Gaussians in the world frame."""
        if not self.submaps:
            return GaussianCloud.empty(device=self.device)
        return GaussianCloud.cat([s.cloud.transformed(s.anchor) for s in self.submaps])
