"""Which tracked frames become keyframes (``mapping.keyframes``).

- ``every`` (the paper's d_map): every ``mapping.every``-th frame.
- ``motion``: by need. A frame is a keyframe when its view has moved far from the last keyframe's (:func:`view_motion`
  at least ``mapping.keyframe_motion``), or ``mapping.max_keyframe_interval`` frames after the last keyframe. A still
  camera adds no keyframes, a fast one adds them as often as its views change, whatever share of the camera's frames
  the tracker processes.

Either way (``mapping.coverage_keyframes``: after gaps, always or never), a frame whose view the map covers less than
``mapping.min_coverage`` of is a keyframe too: a camera outrunning its map.
"""
from __future__ import annotations

import math

import torch

from gausem_core.config import MappingConfig, gap_mode_applies
from gausem_core.slam.health import TrackingHealth, motion
from gausem_core.slam.observation import Observation

KEYFRAME_POLICIES = ("every", "motion")


def view_motion(keyframe: torch.Tensor, pose: torch.Tensor, depth: float) -> float:
    """How far a camera at ``pose`` looks away from one at ``keyframe`` (world-from-camera): the translation over the
    scene's median ``depth`` plus the rotation in radians, to first order the image motion in focal lengths."""
    translation, rotation = motion(keyframe, pose)
    return translation / depth + math.radians(rotation)


class KeyframePolicy:
    """Decides on each tracked frame (:meth:`is_keyframe`); remembers the last keyframe it chose."""

    def __init__(self, cfg: MappingConfig):
        if cfg.keyframes not in KEYFRAME_POLICIES:
            raise ValueError(f"mapping.keyframes must be one of {KEYFRAME_POLICIES}, got {cfg.keyframes!r}")
        if cfg.max_keyframe_interval < 1:
            raise ValueError(f"mapping.max_keyframe_interval must be >= 1, got {cfg.max_keyframe_interval}")
        self.cfg = cfg
        self.last: tuple[int, torch.Tensor] | None = None  # the last keyframe's frame id and world-from-camera

    def is_keyframe(self, frame_id: int, cam_to_world: torch.Tensor, obs: Observation, health: TrackingHealth,
                    gap: bool) -> bool:
        """Whether the frame (tracked to ``cam_to_world`` in the world, judged ``health``; ``gap``: camera frames were
        missed before it) is a keyframe; a keyframe is remembered as the last one."""
        cfg = self.cfg
        if cfg.keyframes == "every":
            chosen = frame_id % cfg.every == 0
        else:
            last_id, last_pose = self.last
            valid = obs.depth[obs.valid_depth]
            depth = float(valid.median()) if valid.numel() else 1.0
            chosen = (frame_id - last_id >= cfg.max_keyframe_interval
                      or view_motion(last_pose, cam_to_world, depth) >= cfg.keyframe_motion)
        chosen = chosen or (gap_mode_applies(cfg.coverage_keyframes, gap) and health.coverage < cfg.min_coverage)
        if chosen:
            self.remember(frame_id, cam_to_world)
        return chosen

    def remember(self, frame_id: int, cam_to_world: torch.Tensor) -> None:
        """The frame ``frame_id`` at ``cam_to_world`` (world) is the last keyframe."""
        self.last = frame_id, cam_to_world.detach()
