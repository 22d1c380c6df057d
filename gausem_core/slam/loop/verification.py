"""Geometric verification of a loop candidate before registration: feature matches + depth -> RANSAC PnP, then the
whole views' depth agreement under that pose.

The query's ORB descriptors are matched to the match keyframe's (nearest neighbour whose Hamming distance is below
``match_ratio`` times the second nearest's, and mutual); the matches whose match-keyframe point has depth give 3D-2D
correspondences for RANSAC PnP (minimal samples of 4 for AP3P, then Levenberg-Marquardt on the inliers: under sensor
noise two matches in three can be wrong, where samples of EPnP's 5 seldom come out clean within the iterations). A
candidate passes when at least ``min_inliers`` correspondences agree on a pose and, under it, the match keyframe's
depth image lands in the query's view (``min_overlap``) and agrees with its depth there (``min_fitness``). The last
test rejects perceptual aliasing: a texture repeated elsewhere (the same poster on another wall) gives a consistent
PnP pose on its own pixels, but the rest of the view is somewhere else.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.config import BowConfig
from gausem_core.geometry import invert_pose
from gausem_core.slam.features import OrbFeatures, feature_pose
from gausem_core.slam.observation import Observation
from gausem_core.slam.registration import warp_agreement


@dataclass(frozen=True)
class Verification:
    """A candidate's check: ``matches`` with depth, PnP ``inliers``, the views' ``overlap`` and ``fitness`` under
    the PnP pose, whether it passed, and ``relative``: the query camera's pose in the match camera's frame
    (match-camera-from-query-camera, float64 4x4; None when PnP found none)."""

    passed: bool
    matches: int
    inliers: int
    overlap: float
    fitness: float
    relative: torch.Tensor | None


def verify(query: OrbFeatures, match: OrbFeatures, query_obs: Observation, match_obs: Observation,
           cfg: BowConfig, max_depth_residual: float) -> Verification:
    """Check that the query keyframe sees the match keyframe's place (see the module docstring)."""
    found = feature_pose(query, match, query_obs.camera, cfg.match_ratio, cfg.max_reprojection_error, cfg.min_inliers,
                         cfg.depth_noise)
    if found.query_from_match is None:
        return Verification(False, found.matches, found.inliers, 0.0, 0.0, None)
    with torch.no_grad():
        overlap, fitness = warp_agreement(match_obs, query_obs, found.query_from_match, max_depth_residual)
    passed = overlap >= cfg.min_overlap and fitness >= cfg.min_fitness
    return Verification(passed, found.matches, found.inliers, overlap, fitness, invert_pose(found.query_from_match))
