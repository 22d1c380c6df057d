"""A start pose for tracking from ORB feature matches with the last good frame.

Dense alignment converges from a pixel or two at its coarsest pyramid level; a live node slower than its camera sees
larger motions between the frames it processes. Features match across those: the current frame's ORB keypoints are
matched to the last good frame's, whose depth makes them 3D points, and RANSAC PnP gives the current camera's pose
relative to it (:func:`~gausem_core.slam.features.feature_pose`, as loop verification uses). That pose is one
more start for the tracker, which keeps the start its coarsest level aligns best, so a wrong feature pose costs one
coarse alignment, not the frame.
"""
from __future__ import annotations

import torch

from gausem_core.config import FeatureStartConfig, check_gap_mode, gap_mode_applies
from gausem_core.geometry import invert_pose, project_to_se3
from gausem_core.slam.features import OrbFeatures, extract_features, feature_pose
from gausem_core.slam.observation import Observation


class FeatureStart:
    """Remembers the last good frame (:meth:`remember`) and predicts a frame's pose from feature matches with it
    (:meth:`predict`). Each frame's features are extracted once; a saved session keeps the last good frame's
    (:meth:`state_dict`)."""

    def __init__(self, cfg: FeatureStartConfig):
        check_gap_mode("tracking.feature_start.mode", cfg.mode)
        self.cfg = cfg
        self._reference: tuple[Observation | None, OrbFeatures | None] | None = None  # the last good frame
        self._latest: tuple[Observation, OrbFeatures] | None = None  # the last frame predicted

    def wanted(self, gap: bool) -> bool:
        """Whether to predict a frame that follows the last good one after a gap (or directly)."""
        return gap_mode_applies(self.cfg.mode, gap)

    def remember(self, obs: Observation) -> None:
        """``obs`` is the last good frame now."""
        if self.cfg.mode != "never":
            self._reference = obs, self._latest[1] if self._latest and self._latest[0] is obs else None

    def predict(self, obs: Observation, previous: torch.Tensor) -> torch.Tensor | None:
        """``obs``'s cam_to_world from the last good frame's ``previous`` cam_to_world moved by the feature pose;
        None without a remembered frame or when too few features agree on a pose."""
        if self._reference is None:
            return None
        features = self._reference_features()
        current = self._features(obs)
        self._latest = obs, current
        cfg = self.cfg
        found = feature_pose(current, features, obs.camera, cfg.match_ratio, cfg.max_reprojection_error,
                             cfg.min_inliers, cfg.depth_noise)
        if found.query_from_match is None:
            return None
        return project_to_se3(previous.double() @ invert_pose(found.query_from_match).to(previous.device)).to(previous)

    def state_dict(self) -> dict | None:
        """The last good frame's features as tensors (None without one)."""
        return None if self._reference is None else self._reference_features().tensors()

    def load_state_dict(self, state: dict | None) -> None:
        """Remember the features of :meth:`state_dict`."""
        self._reference = None if state is None else (None, OrbFeatures.from_tensors(state))

    def _reference_features(self) -> OrbFeatures:
        reference, features = self._reference
        if features is None:
            features = self._features(reference)
            self._reference = reference, features
        return features

    def _features(self, obs: Observation) -> OrbFeatures:
        return extract_features(obs.rgb, obs.depth, obs.camera, self.cfg)
