"""Semantic-aware loop closure (paper §III-C, Algorithm 1): the object the SLAM system calls at every keyframe.

Per keyframe: the global descriptor of its semantic image is computed (and kept for SGR); keyframes whose frame index
is a multiple of ``keyframe_every`` enter the loop database with their landmark score vector over their submap's
Gaussians, and every ``check_every``-th of them queries it. A detected loop (k, j) is closed as follows.

- Intra-submap (k and j in one submap): the relative pose of the two keyframes is measured from their images
  (:func:`~gausem_core.slam.registration.align_keyframes`); a keyframe pose graph with odometry edges between
  consecutive keyframes and the loop edge moves the keyframes (the submap's first keyframe is held), and the submap
  is then re-mapped for ``remap_iterations_per_keyframe`` iterations per keyframe with the poses fixed.
- Inter-submap: Semantic-Guided Registration of the submap with fewer keyframes (source) to the other (target); an
  anchor pose graph with odometry edges between consecutive anchors and every accepted inter-submap loop edge so far
  moves the anchors. Keyframe poses and Gaussian centres are stored in their submap's frame, so a submap moves
  rigidly with its anchor: its world-frame keyframe poses and centres become C T and C x with C = A' A^-1
  (:func:`~gausem_core.slam.correction.anchor_correction`, the paper's T <- (T_a')^-1 T_a T for camera-from-world
  anchors), and every frame stored relative to a keyframe follows.

A loop is closed only when its registration is accepted (overlap, fitness and per-view consistency, see
``RegistrationConfig``) and the correction it implies is plausible: within ``max_correction_sigmas`` of the odometry
uncertainty accumulated over the keyframes between the two ends (a revisit of a look-alike place implies a jump far
beyond the drift). Every detection is recorded, accepted or not.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gausem_core.config import LoopConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_log
from gausem_core.semantics.descriptors import DescriptorExtractor, make_descriptor
from gausem_core.slam.loop import LoopCandidate, LoopDetector, gaussian_idf, landmark_scores, observed_gaussians
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.pose_graph import PoseGraph
from gausem_core.slam.refinement import global_refinement
from gausem_core.slam.registration import align_keyframes, semantic_guided_registration


@dataclass(frozen=True)
class LoopRecord:
    """A detected loop: query keyframe k revisits match keyframe j (frame ids); whether it was closed."""

    query_frame: int
    match_frame: int
    query_submap: int
    match_submap: int
    intra: bool
    accepted: bool
    fitness: float
    seconds: float  # registration, pose graph and (intra) re-mapping


class SemanticPalette:
    """The distinct semantic colours seen so far, in order of discovery; a Gaussian's class is the nearest one.

    Learned from the keyframes' semantic images, so the loop closure needs no class table; classes are only appended,
    which keeps earlier landmark score vectors valid (see :class:`~gausem_core.slam.loop.LoopDetector`).
    """

    def __init__(self):
        self.colors = torch.zeros(0, 3)

    def __len__(self) -> int:
        return len(self.colors)

    def update(self, semantic: torch.Tensor) -> None:
        """Add the colours of a semantic image (H, W, 3) not seen before."""
        found = torch.unique(semantic.detach().reshape(-1, 3).float().cpu(), dim=0)
        if len(self.colors):
            found = found[torch.cdist(found, self.colors).min(1).values > 1e-4]
        self.colors = torch.cat([self.colors, found])

    def class_ids(self, cloud: GaussianCloud) -> torch.Tensor:
        return cloud.class_ids(self.colors).cpu()


class LoopClosure:
    """Loop detection and correction over the SLAM system's submaps (:class:`~gausem_core.slam.system.Submap`:
    anchor world-from-submap, Gaussians and keyframes in the submap frame, possibly offloaded), edited in place.

    ``mapper`` re-maps submaps after intra-submap loops; ``descriptor`` gives the global descriptors and the dense
    features of the SGR and refinement feature terms (default: the colour-layout fallback); ``device``: where
    submaps are loaded for registration and refinement.
    """

    def __init__(self, cfg: LoopConfig, mapper: Mapper, descriptor: DescriptorExtractor | None = None,
                 backend: str = "auto", device: torch.device | str = "cpu", database_backend: str = "auto"):
        self.cfg = cfg
        self.mapper = mapper
        self.backend = backend
        self.device = torch.device(device)
        self.descriptor = descriptor if descriptor is not None else make_descriptor("fallback")
        self.detector = LoopDetector.from_config(cfg, descriptor_dim=self.descriptor.dim, backend=database_backend)
        self.palette = SemanticPalette()
        self.records: list[LoopRecord] = []
        self._descriptors: dict[int, torch.Tensor] = {}  # keyframe frame id -> global descriptor
        self._inter_edges: list[tuple[int, int, torch.Tensor, tuple[float, float]]] = []  # target, source, T, sigmas

    @property
    def loops(self) -> list[LoopRecord]:
        """The accepted (closed) loops."""
        return [r for r in self.records if r.accepted]

    def on_keyframe(self, submaps: Sequence, submap, keyframe: Keyframe) -> LoopRecord | None:
        """Algorithm 1 for a new keyframe of ``submap`` (one of ``submaps``); closes a detected loop."""
        if not self.cfg.enabled:
            return None
        self.palette.update(keyframe.obs.semantic)
        descriptor = self._descriptor(submap, keyframe)
        if not self.detector.is_keyframe(keyframe.frame_id):
            return None
        candidate = self.detector.add_keyframe(keyframe.frame_id, submap.submap_id, descriptor,
                                               self._landmark_scores(submap, keyframe))
        if candidate is None:
            return None
        start = time.perf_counter()
        by_id = {s.submap_id: s for s in submaps}
        if candidate.intra:
            accepted, fitness = self._close_intra(candidate, submap)
        else:
            accepted, fitness = self._close_inter(candidate, by_id)
        record = LoopRecord(candidate.query_keyframe, candidate.match_keyframe, candidate.query_submap,
                            candidate.match_submap, candidate.intra, accepted, fitness, time.perf_counter() - start)
        self.records.append(record)
        return record

    def finish(self, submaps: Sequence) -> None:
        """After the last frame: the two-stage global refinement, when enabled."""
        if self.cfg.enabled and self.cfg.global_refinement:
            global_refinement(submaps, self.mapper, self.cfg, self.descriptor, self.backend, self.device)

    # --- detection inputs ---------------------------------------------------------------------------------------
    def _descriptor(self, submap, keyframe: Keyframe) -> torch.Tensor:
        """The keyframe's global descriptor (computed once; an offloaded keyframe's image is read back for it)."""
        if keyframe.frame_id not in self._descriptors:
            semantic = submap.observation(keyframe).semantic.detach().cpu()
            self._descriptors[keyframe.frame_id] = torch.from_numpy(np.asarray(self.descriptor.describe(semantic)))
        return self._descriptors[keyframe.frame_id]

    def _landmark_scores(self, submap, keyframe: Keyframe) -> torch.Tensor:
        """Eq. 7 over the submap's Gaussians that the keyframe observes."""
        if len(submap.cloud) == 0:
            return torch.zeros(len(self.palette), dtype=torch.float64)
        ids = self.palette.class_ids(submap.cloud)
        seen = observed_gaussians(submap.cloud.means.detach(), keyframe.cam_to_world, keyframe.obs.camera,
                                  keyframe.obs.depth).cpu()
        return landmark_scores(ids, seen, gaussian_idf(ids, len(self.palette)))

    def _odometry_sigmas(self, keyframes: int) -> tuple[float, float]:
        """Odometry standard deviations over ``keyframes`` keyframe steps (random-walk growth)."""
        scale = max(keyframes, 1) ** 0.5
        return self.cfg.odometry_sigma_rotation * scale, self.cfg.odometry_sigma_translation * scale

    def _plausible(self, current: torch.Tensor, measured: torch.Tensor, keyframes: int) -> bool:
        """Whether a measured relative pose differs from the current estimate by at most ``max_correction_sigmas``
        odometry standard deviations over ``keyframes`` steps, in rotation and in translation."""
        error = invert_pose(current.detach().cpu().double()) @ measured.detach().cpu().double()
        rotation, translation = self._odometry_sigmas(keyframes)
        bound = self.cfg.max_correction_sigmas
        return (float(se3_log(error)[3:].norm()) <= bound * rotation
                and float(error[:3, 3].norm()) <= bound * translation)

    # --- intra-submap loops -------------------------------------------------------------------------------------
    def _close_intra(self, candidate: LoopCandidate, submap) -> tuple[bool, float]:
        keyframes = submap.keyframes
        index = {kf.frame_id: i for i, kf in enumerate(keyframes)}
        j, k = index[candidate.match_keyframe], index[candidate.query_keyframe]
        init = invert_pose(keyframes[k].cam_to_world) @ keyframes[j].cam_to_world
        motion, fitness = align_keyframes(keyframes[j].obs, keyframes[k].obs, init, self.cfg.registration)
        if fitness < self.cfg.registration.min_fitness or not self._plausible(init, motion, k - j):
            return False, fitness
        graph = PoseGraph(odometry_sigmas=self._odometry_sigmas(1), robust_kernel=self.cfg.robust_kernel)
        for i, kf in enumerate(keyframes):
            graph.add_node(i, kf.cam_to_world)
            if i:
                graph.add_odometry(i - 1, i)
        reg = self.cfg.registration
        graph.add_loop(j, k, invert_pose(motion), (reg.sigma_rotation, reg.sigma_translation))
        poses = graph.optimize().poses
        for i, kf in enumerate(keyframes):
            if not kf.fixed:
                kf.cam_to_world = torch.as_tensor(poses[i], dtype=kf.cam_to_world.dtype,
                                                  device=kf.cam_to_world.device)
        iterations = self.cfg.remap_iterations_per_keyframe * len(keyframes)
        submap.cloud, _ = self.mapper.optimise(submap.cloud, keyframes, iterations, optimise_poses=False)
        return True, fitness

    # --- inter-submap loops -------------------------------------------------------------------------------------
    def _close_inter(self, candidate: LoopCandidate, by_id: dict) -> tuple[bool, float]:
        query, match = by_id[candidate.query_submap], by_id[candidate.match_submap]
        ends = {candidate.query_submap: candidate.query_keyframe, candidate.match_submap: candidate.match_keyframe}
        target, source = (match, query) if len(match.keyframes) >= len(query.keyframes) else (query, match)
        loop_pair = tuple([kf.frame_id for kf in s.keyframes].index(ends[s.submap_id]) for s in (source, target))
        registration = semantic_guided_registration(
            source.load_cloud(self.device), self._poses(source), self._descriptor_stack(source),
            target.load_cloud(self.device), self._poses(target), self._descriptor_stack(target),
            source.keyframes[0].obs.camera, self.cfg.registration, self.descriptor, self.backend,
            self.cfg.max_descriptor_distance, loop_pair)
        first, last = sorted((target.submap_id, source.submap_id))
        between = sum(len(s.keyframes) for s in by_id.values() if first <= s.submap_id < last)
        current = invert_pose(target.anchor) @ source.anchor
        accepted = registration.accepted and self._plausible(current, registration.transform, between)
        if accepted:
            self._inter_edges.append((target.submap_id, source.submap_id, registration.transform,
                                      registration.sigmas))
            self._optimise_anchors(list(by_id.values()))
        return accepted, registration.fine.fitness

    def _poses(self, submap) -> torch.Tensor:
        return torch.stack([kf.cam_to_world.detach().double().cpu() for kf in submap.keyframes])

    def _descriptor_stack(self, submap) -> torch.Tensor:
        return torch.stack([self._descriptor(submap, kf) for kf in submap.keyframes])

    def _optimise_anchors(self, submaps: list) -> None:
        """Anchor pose graph: odometry between consecutive submaps, every accepted inter-submap loop edge."""
        ordered = sorted(submaps, key=lambda s: s.submap_id)
        graph = PoseGraph(robust_kernel=self.cfg.robust_kernel)
        for i, submap in enumerate(ordered):
            graph.add_node(submap.submap_id, submap.anchor)
            if i:
                previous = ordered[i - 1]
                graph.add_odometry(previous.submap_id, submap.submap_id,
                                   self._odometry_sigmas(len(previous.keyframes)))
        for target, source, transform, sigmas in self._inter_edges:
            graph.add_loop(target, source, transform, sigmas)
        poses = graph.optimize().poses
        for submap in ordered:
            submap.anchor = torch.as_tensor(poses[submap.submap_id], dtype=submap.anchor.dtype,
                                            device=submap.anchor.device)
