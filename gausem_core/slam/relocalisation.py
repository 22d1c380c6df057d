"""Relocalisation: place a frame against the whole saved map when the motion model means nothing (after a restart)
or failed (after a tracking loss).

Start poses are the last tracked pose and keyframe poses (the keyframes nearest to the frame by global descriptor,
completed by the active submap's keyframes); after a tracking loss the system puts the constant-velocity prediction
first, and the feature start from the last good frame before it (``tracking.feature_start``). The frame is tracked
from each start with the map frozen, against the Gaussians of the start's submap, and the result explaining the most
pixels wins: an inlier is a pixel with a valid depth where the map renders (alpha above ``inlier_alpha``) within
``inlier_depth`` of it. The winner is accepted when its inlier fraction reaches ``min_inlier_fraction``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from gausem_core.config import RelocalisationConfig
from gausem_core.geometry import invert_pose
from gausem_core.render import render
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.observation import Observation
from gausem_core.slam.tracker import Tracker


@dataclass(frozen=True)
class Start:
    """A start pose: ``cam_to_world`` in the frame of submap ``submap`` (a system Submap); ``label`` for reports."""

    submap: object
    cam_to_world: torch.Tensor
    label: str


@dataclass
class RelocalisationResult:
    """The best start's tracked pose (world frame) and how well it explains the frame; ``accepted`` when well enough."""

    accepted: bool
    cam_to_world: torch.Tensor
    inlier_fraction: float
    tracking_loss: float
    iterations: int
    start: str  # which start won: "features", "constant velocity", "last pose" or "keyframe N"
    submap_id: int  # the submap it was tracked against
    starts: int  # how many starts were tried
    health: TrackingHealth | None = None  # after a tracking loss: the health monitor's verdict on the placement


def relocalisation_starts(submaps: Sequence, last: tuple[object, torch.Tensor] | None, ranked: Sequence[int],
                          count: int) -> list[Start]:
    """The last tracked pose ((submap, pose in its frame), if any), then the keyframes with frame ids ``ranked``
    (nearest first, at most ``count``), then, when fewer than ``count`` were ranked, the active submap's (the last
    of ``submaps``) other keyframes."""
    owner = {kf.frame_id: (s, kf) for s in submaps for kf in s.keyframes}
    chosen = [f for f in ranked if f in owner][:count]
    if len(chosen) < count:
        chosen += [kf.frame_id for kf in submaps[-1].keyframes if kf.frame_id not in chosen]
    starts = [Start(*last, "last pose")] if last is not None else []
    return starts + [Start(owner[f][0], owner[f][1].cam_to_world, f"keyframe {f}") for f in chosen]


def inlier_fraction(cloud, obs: Observation, cam_to_world: torch.Tensor, cfg: RelocalisationConfig,
                    backend: str) -> float:
    """Fraction of the frame's valid-depth pixels that the map rendered at ``cam_to_world`` covers within
    ``cfg.inlier_depth`` metres with an alpha above ``cfg.inlier_alpha`` (0 for a frame without valid depth)."""
    valid = obs.valid_depth
    if not bool(valid.any()):
        return 0.0
    with torch.no_grad():
        out = render(cloud, invert_pose(cam_to_world.to(cloud.dtype)), obs.camera, backend=backend)
    inliers = valid & (out.alpha > cfg.inlier_alpha) & ((out.expected_depth - obs.depth).abs() < cfg.inlier_depth)
    return float(inliers.sum()) / float(valid.sum())


def track_from_starts(obs: Observation, starts: Sequence[Start], tracker: Tracker, cfg: RelocalisationConfig,
               device: torch.device) -> RelocalisationResult:
    """Track ``obs`` from every start (frozen map) and keep the result with the highest inlier fraction (ties: the
    lower tracking loss)."""
    if not starts:
        raise ValueError("track_from_starts: no start pose (the map is empty)")
    best, clouds = None, {}
    for start in starts:
        submap = start.submap
        if submap.submap_id not in clouds:
            clouds[submap.submap_id] = submap.load_cloud(device)
        cloud = clouds[submap.submap_id]
        tracked = tracker.track(cloud, obs, start.cam_to_world.to(device))
        fraction = inlier_fraction(cloud, obs, tracked.cam_to_world, cfg, tracker.backend)
        key = (fraction, -tracked.loss)
        if best is None or key > best[0]:
            best = (key, start, tracked)
    (fraction, _), start, tracked = best
    world = start.submap.anchor @ tracked.cam_to_world.detach()
    return RelocalisationResult(fraction >= cfg.min_inlier_fraction, world, fraction, tracked.loss,
                                tracked.iterations, start.label, start.submap.submap_id, len(starts))
