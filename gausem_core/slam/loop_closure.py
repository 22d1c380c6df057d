"""Semantic-aware loop closure (paper §III-C, Algorithm 1): the object the SLAM system calls at every keyframe.

Per keyframe: the global descriptor of its semantic image is computed (and kept for SGR); keyframes whose frame index
is a multiple of ``keyframe_every`` enter the loop database with their landmark score vector over their submap's
Gaussians, and every ``check_every``-th of them queries it (at the end of a run, with ``check_at_end``, also the ones
whose turn never came: :meth:`LoopClosure.check_unchecked`). Place recognition (``loop.place_recognition``) is either
the paper's: the database holds the global descriptors (DINOv2 of the semantic image when weights are given); or,
without weights ("auto"), a bag of binary ORB words of the keyframe's own image with a vocabulary learned online
(:mod:`~gausem_core.slam.loop.words`), whose candidates must pass geometric verification (feature matches + depth ->
RANSAC PnP, then the views' depth agreement, :mod:`~gausem_core.slam.loop.verification`) before registration; the
verified relative pose is one more start for it. The landmark re-ranking of Algorithm 1 applies to both when there
are classes. With ``proximity_radius`` > 0, the past keyframes near
the new one in the current pose estimate (centre within the radius, similar viewing direction) are candidates at every
keyframe as well: under small drift a revisit is found where a weak descriptor (the fallback) does not see it. A
detected loop (k, j) is closed as follows.

- Intra-submap (k and j in one submap): the relative pose of the two keyframes is measured from their images
  (:func:`~gausem_core.slam.registration.align_keyframes`); a keyframe pose graph with odometry edges between
  consecutive keyframes and the loop edge moves the keyframes (the submap's first keyframe is held), and the submap
  is then re-mapped for ``remap_iterations_per_keyframe`` iterations per keyframe the correction moved beyond the loop
  edges' standard-deviation floors, with the poses fixed.
- Inter-submap: Semantic-Guided Registration of the submap with fewer keyframes (source) to the other (target),
  its fine step starting from the coarse estimate or the anchors' current one, whichever the views agree with more; an
  anchor pose graph with odometry edges between consecutive anchors and every accepted inter-submap loop edge so far
  moves the anchors. Keyframe poses and Gaussian centres are stored in their submap's frame, so a submap moves
  rigidly with its anchor (:meth:`LoopClosure.move_anchors`): its world-frame keyframe poses and centres become C T
  and C x with C = A' A^-1 (the paper's T <- (T_a')^-1 T_a T for camera-from-world anchors), and every frame stored
  relative to a keyframe follows.

A loop is closed only when its registration is accepted (overlap, fitness and per-view consistency, see
``RegistrationConfig``) and the correction it implies is plausible: within ``max_correction_sigmas`` of the odometry
uncertainty accumulated over the keyframes between the two ends (a revisit of a look-alike place implies a jump far
beyond the drift). A loop between two tracking segments not yet merged (the tracker lost the map for good and began
a new one, ``relocalisation.new_segment_after``) has no such bound, their relative pose being a guess: it merges them.
Every detection is recorded, accepted or not.
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gausem_core.config import LoopConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_log
from gausem_core.semantics.descriptors import DescriptorExtractor, make_descriptor
from gausem_core.slam.events import Correction
from gausem_core.slam.features import OrbFeatures, extract_features
from gausem_core.slam.loop import (DescriptorDatabase, LoopCandidate, LoopDetector, PlaceSignature, gaussian_idf,
                                   landmark_scores, nearby_keyframes, observed_gaussians)
from gausem_core.slam.loop.verification import verify
from gausem_core.slam.loop.words import BagOfWords
from gausem_core.slam.loop_graphs import LoopGraphs, PoseGraphUpdate, odometry_sigmas
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.observation import Observation
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
    inliers: int = 0  # geometric verification's PnP inliers (bag of words; 0 without verification)


@dataclass(frozen=True)
class LoopConstraint:
    """An accepted loop as a pose-graph edge a -> b measuring ``relative`` = a^-1 b (float64 4x4). Intra-submap: a, b
    are the match and query keyframes (poses in their submap's frame); inter-submap: the target and source submaps'
    anchors, with keyframe_a / keyframe_b the loop's keyframes in them. ``sigmas``: (rotation, translation)."""

    keyframe_a: int
    keyframe_b: int
    submap_a: int
    submap_b: int
    relative: torch.Tensor
    sigmas: tuple[float, float]
    fitness: float
    intra: bool

    @property
    def edge(self) -> tuple[int, int, torch.Tensor, tuple[float, float]]:
        """(a, b, relative, sigmas) with the node keys of its level (frame ids, or submap ids)."""
        if self.intra:
            return self.keyframe_a, self.keyframe_b, self.relative, self.sigmas
        return self.submap_a, self.submap_b, self.relative, self.sigmas


@dataclass(frozen=True)
class LoopOutcome:
    """A registered loop: its record, the constraint when accepted, and the correction applied to the map (when the
    loop closure corrected it itself)."""

    record: LoopRecord
    constraint: LoopConstraint | None = None
    correction: Correction | None = None


class SemanticPalette:
    """The distinct semantic colours seen so far, in order of discovery; a Gaussian's class is the nearest one.

    Learned from the keyframes' semantic images, so the loop closure needs no class table; classes are only appended,
    which keeps earlier landmark score vectors valid (see :class:`~gausem_core.slam.loop.LoopDetector`).

    Incremental: every colour met is remembered by its key (:func:`colour_keys`), so an image costs one lookup of its
    pixels' keys among those (a binary search), and only the pixels of colours never met before are sorted. A new
    image's new colours are appended in ascending (r, g, b) order; one within 1e-4 of a known colour is not added.
    """

    def __init__(self):
        self.colors = torch.zeros(0, 3)
        self._seen = torch.zeros(0, dtype=torch.long)  # sorted keys of every colour met, added or not

    def __len__(self) -> int:
        return len(self.colors)

    def update(self, semantic: torch.Tensor) -> None:
        """Add the colours of a semantic image (H, W, 3) in [0, 1] not seen before."""
        pixels = semantic.detach().reshape(-1, 3).float()
        keys = colour_keys(pixels)
        unseen = ~sorted_contains(self._seen.to(keys.device), keys)
        new_keys, found = distinct_colours(keys[unseen], pixels[unseen])
        self._seen = torch.sort(torch.cat([self._seen, new_keys.cpu()])).values
        found = found.cpu()
        if len(self.colors):
            found = found[torch.cdist(found, self.colors).min(1).values > 1e-4]
        self.colors = torch.cat([self.colors, found])

    def class_ids(self, cloud: GaussianCloud) -> torch.Tensor:
        """(N,) class id of each Gaussian (the nearest colour's index), on the cloud's device."""
        return cloud.class_ids(self.colors)


_KEY_BITS = 21  # per channel: 3 x 21 bits fit an int64; colours closer than 2^-21 share a key


def colour_keys(colors: torch.Tensor) -> torch.Tensor:
    """(N,) int64 keys of colours (N, 3) in [0, 1]: each channel quantised to 21 bits, packed as (r, g, b); ascending
    keys are ascending (r, g, b) order."""
    levels = (colors.clamp(0, 1) * (2**_KEY_BITS - 1)).round().long()
    return (levels[:, 0] << 2 * _KEY_BITS) | (levels[:, 1] << _KEY_BITS) | levels[:, 2]


def sorted_contains(sorted_keys: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which ``keys`` occur in the ascending ``sorted_keys`` (binary search, no sort of ``keys``)."""
    if len(sorted_keys) == 0:
        return torch.zeros_like(keys, dtype=torch.bool)
    at = torch.searchsorted(sorted_keys, keys).clamp_max(len(sorted_keys) - 1)
    return sorted_keys[at] == keys


def distinct_colours(keys: torch.Tensor, colors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct ``keys`` (ascending) and, for each, the colour of its first occurrence in ``colors`` (N, 3)."""
    distinct, inverse = torch.unique(keys, return_inverse=True)
    order = torch.arange(len(keys), device=keys.device)
    first = torch.full_like(distinct, len(keys)).scatter_reduce_(0, inverse, order, "amin")
    return distinct, colors[first]


class LoopClosure:
    """Loop detection and correction over the SLAM system's submaps (:class:`~gausem_core.slam.system.Submap`:
    anchor world-from-submap, Gaussians and keyframes in the submap frame, possibly offloaded), edited in place.

    :meth:`on_keyframe` runs the steps, which are also usable one by one when detection and pose graphs run elsewhere
    (the ROS nodes): :meth:`describe` gives a keyframe's :class:`~gausem_core.slam.loop.PlaceSignature`,
    :meth:`detect` queries the loop database (:attr:`detector`, built by ``LoopDetector.from_config``) with it for
    ranked candidates, :meth:`confirm` picks the loop among them (geometric verification with the bag of words),
    :meth:`register` measures it as a :class:`LoopConstraint`, :meth:`correct` optimises the pose graph of its level
    (:class:`LoopGraphs`) and moves the map (:meth:`apply`).

    ``mapper`` re-maps submaps after intra-submap loops; ``descriptor`` gives the global descriptors and the dense
    features of the SGR feature term (default: the colour-layout fallback); ``device``: where submaps are loaded for
    registration and re-mapping. :attr:`place_recognition` names what finds candidates ("bow", or the descriptor's
    kind); :attr:`seconds` accumulates the time per phase (describe, detect, verify, register, correct).
    """

    def __init__(self, cfg: LoopConfig, mapper: Mapper, descriptor: DescriptorExtractor | None = None,
                 backend: str = "auto", device: torch.device | str = "cpu", database_backend: str = "auto"):
        self.cfg = cfg
        self.mapper = mapper
        self.backend = backend
        self.device = torch.device(device)
        self.descriptor = descriptor if descriptor is not None else make_descriptor("fallback")
        self.place_recognition = cfg.place_recognition_for(self.descriptor.kind)
        self.detector = LoopDetector.from_config(cfg, self.place_recognition, descriptor_dim=self.descriptor.dim,
                                                 backend=database_backend)
        self.seconds = dict.fromkeys(PHASES, 0.0)
        self.rejected_candidates = 0  # candidates geometric verification turned down
        self.palette = SemanticPalette()
        self.records: list[LoopRecord] = []
        self.graphs = LoopGraphs(cfg)
        self._descriptors: dict[int, torch.Tensor] = {}  # keyframe frame id -> global descriptor
        self._features: dict[int, OrbFeatures] = {}  # loop keyframe frame id -> ORB features ("bow")

    @property
    def constraints(self) -> list[LoopConstraint]:
        """The accepted loops corrected here, both levels, in order."""
        return self.graphs.constraints

    @property
    def loops(self) -> list[LoopRecord]:
        """The accepted (closed) loops."""
        return [r for r in self.records if r.accepted]

    def on_keyframe(self, submaps: Sequence, submap, keyframe: Keyframe) -> LoopOutcome | None:
        """Algorithm 1 for a new keyframe of ``submap`` (one of ``submaps``): :meth:`describe` it and, at a loop
        keyframe, :meth:`detect` loops, :meth:`confirm` one and close it (register, then correct when accepted)."""
        place = self.describe(submaps, submap, keyframe)
        if place is None:
            return None
        candidate = self.confirm(submaps, self.detect(place))
        if candidate is None:
            return None
        start = time.perf_counter()
        outcome = self.register(submaps, candidate)
        correction = self.correct(submaps, outcome.constraint) if outcome.constraint is not None else None
        record = dataclasses.replace(outcome.record, seconds=time.perf_counter() - start)
        self.records[-1] = record
        return LoopOutcome(record, outcome.constraint, correction)

    def check_unchecked(self, submaps: Sequence) -> LoopOutcome | None:
        """At the end of a run: the loop keyframes stored since the last check (:attr:`LoopDetector.unchecked`, whose
        turn never came) are checked in order as :meth:`on_keyframe` checks one (:meth:`LoopDetector.check_stored`,
        :meth:`confirm`, :meth:`register`) until a loop is accepted, which is then corrected (like a check in its turn,
        one loop; the rest are dropped unchecked). A revisit in a run's last keyframes is closed so. None when no loop
        was accepted."""
        places = {p.keyframe_id: p for p in self.stored_places() if p.keyframe_id in self.detector.unchecked}
        for keyframe_id in list(self.detector.unchecked):
            start = time.perf_counter()
            candidates = self.detector.check_stored(places[keyframe_id])
            self.seconds["detect"] += time.perf_counter() - start
            candidate = self.confirm(submaps, candidates)
            if candidate is None:
                continue
            start = time.perf_counter()
            outcome = self.register(submaps, candidate)
            if outcome.constraint is None:
                continue
            correction = self.correct(submaps, outcome.constraint)
            self.records[-1] = dataclasses.replace(outcome.record, seconds=time.perf_counter() - start)
            self.detector.unchecked.clear()
            return LoopOutcome(self.records[-1], outcome.constraint, correction)
        return None

    def describe(self, submaps: Sequence, submap, keyframe: Keyframe) -> PlaceSignature | None:
        """Describe a new keyframe of ``submap``: its semantic colours join the palette and its global descriptor is
        kept (for SGR). A loop keyframe (every ``keyframe_every``-th frame) gets its place signature, what
        :meth:`detect` takes (here or in another process): the database's appearance (the global descriptor, or with
        place recognition "bow" the keyframe's ORB features), the Eq. 7 landmark scores over the submap's Gaussians
        and the earlier keyframes near it in the current estimates. None for other keyframes or when disabled."""
        if not self.cfg.enabled:
            return None
        start = time.perf_counter()
        self.palette.update(keyframe.obs.semantic)
        descriptor = self._descriptor(submap, keyframe)
        place = None
        if self.detector.is_keyframe(keyframe.frame_id):
            appearance = self._keyframe_features(submap, keyframe) if self.place_recognition == "bow" else descriptor
            place = PlaceSignature(keyframe.frame_id, submap.submap_id, appearance,
                                   self._landmark_scores(submap, keyframe),
                                   tuple(self._nearby(submaps, submap.world_pose(keyframe))))
        self.seconds["describe"] += time.perf_counter() - start
        return place

    def detect(self, place: PlaceSignature, check: bool = True) -> list[LoopCandidate]:
        """Algorithm 1's query of the loop database for a described keyframe, which it then stores: the ranked
        candidates (:meth:`LoopDetector.add_keyframe`). ``check`` false: only store it (its loops are detected
        elsewhere, e.g. by the ROS loop_detection node)."""
        start = time.perf_counter()
        candidates = self.detector.add_keyframe(place, check)
        self.seconds["detect"] += time.perf_counter() - start
        return candidates

    def stored_places(self) -> list[PlaceSignature]:
        """The place signatures of the keyframes in the loop database, in the order they were stored, as
        :meth:`describe` gave them (less ``nearby``): what another detector stores to hold the same keyframes."""
        bow = self.place_recognition == "bow"
        return [PlaceSignature(frame_id, submap_id,
                               self.detector.database.features[frame_id] if bow else self._descriptors[frame_id],
                               scores) for frame_id, (submap_id, scores) in self.detector.keyframes.items()]

    def confirm(self, submaps: Sequence, candidates: Sequence[LoopCandidate]) -> LoopCandidate | None:
        """The loop among one query keyframe's ranked candidates (as :meth:`detect` gives them): with place recognition
        "bow" the first that passes geometric verification, with its verified relative pose (the ones before it are
        counted in :attr:`rejected_candidates`); else the first. None when there is none. Raises ValueError when the
        candidates are of several query keyframes or name a keyframe not in ``submaps``."""
        queries = sorted({c.query_keyframe for c in candidates})
        if len(queries) > 1:
            raise ValueError(f"loop candidates of several query keyframes: {queries}")
        if self.place_recognition != "bow":
            return next(iter(candidates), None)
        by_id = {s.submap_id: s for s in submaps}
        for candidate in candidates:
            start = time.perf_counter()
            query_submap, query = _find_keyframe(by_id, candidate, candidate.query_submap, candidate.query_keyframe)
            match_submap, match = _find_keyframe(by_id, candidate, candidate.match_submap, candidate.match_keyframe)
            obs = query_submap.observation(query)
            result = verify(self._keyframe_features(query_submap, query),
                            self._keyframe_features(match_submap, match), obs,
                            match_submap.observation(match, obs.depth.device), self.cfg.bow,
                            self.cfg.registration.max_depth_residual)
            self.seconds["verify"] += time.perf_counter() - start
            if result.passed:
                return dataclasses.replace(candidate, relative=result.relative, inliers=result.inliers)
            self.rejected_candidates += 1
        return None

    def nearest_keyframes(self, obs: Observation, k: int) -> list[int]:
        """Frame ids of the ``k`` keyframes most like an observation, most alike first: with place recognition
        "bow", the database keyframes whose bag-of-words score reaches ``bow.min_score`` (best first); then, or
        else, every described keyframe by the L2 distance between the unit global descriptors of the semantic images
        (as the loop database)."""
        if k <= 0:
            return []
        recognised = []
        if self.place_recognition == "bow":
            ids, distances = self.detector.database.search(self._observation_features(obs), k=k)
            recognised = ids[distances <= self.detector.max_descriptor_distance].tolist()
        if not self._descriptors:
            return recognised
        ids = list(self._descriptors)
        query = torch.from_numpy(np.asarray(self.descriptor.describe(obs.semantic.detach().cpu()))).double()
        stack = torch.stack([self._descriptors[i] for i in ids]).double()
        unit = torch.nn.functional.normalize
        distances = (unit(stack, dim=1) - unit(query, dim=0)).norm(dim=1)
        by_descriptor = [ids[i] for i in torch.argsort(distances, stable=True).tolist() if ids[i] not in recognised]
        return (recognised + by_descriptor)[:k]

    # --- persistence ----------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything learned so far (palette, keyframe descriptors, loop database, records, accepted constraints)
        as plain values and CPU tensors; :meth:`load_state_dict` restores it bit-identically."""
        database = self.detector.database
        return {
            "palette": self.palette.colors,
            "descriptors": [[frame_id, d] for frame_id, d in self._descriptors.items()],
            "database": (database.state_dict() if self.place_recognition == "bow" else
                         {"ids": torch.from_numpy(database.ids.copy()),
                          "vectors": torch.from_numpy(database.vectors.copy())}),
            "rejected_candidates": self.rejected_candidates,
            "landmarks": [[frame_id, submap_id, scores] for frame_id, (submap_id, scores)
                          in self.detector.keyframes.items()],
            "records": [dataclasses.asdict(r) for r in self.records],
            "detections": [list(pair) for pair in self.detector.detections],
            "constraints": [{**dataclasses.asdict(c), "sigmas": list(c.sigmas)} for c in self.constraints],
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned (onto a loop closure built with the same configuration)."""
        saved_bow = "words" in state["database"]
        if saved_bow != (self.place_recognition == "bow"):
            raise ValueError(f"the saved loop closure's place recognition was {'bow' if saved_bow else 'a descriptor'}"
                             f", this one's is {self.place_recognition}: load it with loop.place_recognition: "
                             f"{'bow' if saved_bow else 'descriptor'}")
        self.palette.colors = state["palette"]
        self._descriptors = {int(frame_id): d for frame_id, d in state["descriptors"]}
        if saved_bow:
            self.detector.database = BagOfWords(self.cfg.bow)
            self.detector.database.load_state_dict(state["database"])
            self._features = dict(self.detector.database.features)
        else:
            database = self.detector.database = DescriptorDatabase(self.detector.database.dim,
                                                                   self.detector.database.backend)
            database.restore(state["database"]["ids"].tolist(), state["database"]["vectors"].numpy())
        self.rejected_candidates = int(state.get("rejected_candidates", 0))  # sessions saved before verification
        self.detector.keyframes = {int(f): (int(s), scores) for f, s, scores in state["landmarks"]}
        self.records = [LoopRecord(**r) for r in state["records"]]
        self.detector.detections = [(int(q), int(m)) for q, m in state.get("detections", [])]  # none before they were
        self.graphs.constraints = [LoopConstraint(**{**c, "sigmas": tuple(c["sigmas"])}) for c in state["constraints"]]

    # --- detection inputs ---------------------------------------------------------------------------------------
    def _descriptor(self, submap, keyframe: Keyframe) -> torch.Tensor:
        """The keyframe's global descriptor (computed once; an offloaded keyframe's image is read back for it)."""
        if keyframe.frame_id not in self._descriptors:
            semantic = submap.observation(keyframe).semantic.detach().cpu()
            self._descriptors[keyframe.frame_id] = torch.from_numpy(np.asarray(self.descriptor.describe(semantic)))
        return self._descriptors[keyframe.frame_id]

    def _keyframe_features(self, submap, keyframe: Keyframe) -> OrbFeatures:
        """The keyframe's ORB features (computed once, like its global descriptor)."""
        if keyframe.frame_id not in self._features:
            self._features[keyframe.frame_id] = self._observation_features(submap.observation(keyframe))
        return self._features[keyframe.frame_id]

    def _observation_features(self, obs: Observation) -> OrbFeatures:
        return extract_features(obs.rgb, obs.depth, obs.camera, self.cfg.bow)

    def _landmark_scores(self, submap, keyframe: Keyframe) -> torch.Tensor:
        """Eq. 7 over the submap's Gaussians that the keyframe observes, computed where they are; (C,) on the CPU.
        The Gaussians are read once: in ``worker.mode: async`` the tracker grows the submap meanwhile."""
        cloud = submap.cloud
        if len(cloud) == 0:
            return torch.zeros(len(self.palette), dtype=torch.float64)
        ids = self.palette.class_ids(cloud)
        seen = observed_gaussians(cloud.means.detach(), keyframe.cam_to_world, keyframe.obs.camera, keyframe.obs.depth)
        return landmark_scores(ids, seen, gaussian_idf(ids, len(self.palette))).cpu()

    def _nearby(self, submaps: Sequence, cam_to_world: torch.Tensor) -> list[int]:
        """Frame ids of the keyframes near ``cam_to_world`` (world frame) in the current estimates."""
        if self.cfg.proximity_radius <= 0:
            return []
        poses = {kf.frame_id: s.world_pose(kf) for s in submaps for kf in s.keyframes}
        return nearby_keyframes(cam_to_world, poses, self.cfg.proximity_radius, self.cfg.proximity_max_angle_deg)

    def _plausible(self, current: torch.Tensor, measured: torch.Tensor, keyframes: int) -> bool:
        """Whether a measured relative pose differs from the current estimate by at most ``max_correction_sigmas``
        odometry standard deviations over ``keyframes`` steps, in rotation and in translation."""
        error = invert_pose(current.detach().cpu().double()) @ measured.detach().cpu().double()
        rotation, translation = odometry_sigmas(self.cfg, keyframes)
        bound = self.cfg.max_correction_sigmas
        return (float(se3_log(error)[3:].norm()) <= bound * rotation
                and float(error[:3, 3].norm()) <= bound * translation)

    # --- registration -------------------------------------------------------------------------------------------
    def register(self, submaps: Sequence, candidate: LoopCandidate) -> LoopOutcome:
        """Measure a detected loop (intra: keyframe alignment; inter: SGR) and decide whether to accept it; the
        decision is recorded in :attr:`records`. The outcome's constraint is set when accepted. Raises ValueError
        when a keyframe or submap of the candidate is unknown."""
        start = time.perf_counter()
        by_id = {s.submap_id: s for s in submaps}
        _find_keyframe(by_id, candidate, candidate.query_submap, candidate.query_keyframe)
        _find_keyframe(by_id, candidate, candidate.match_submap, candidate.match_keyframe)
        measure = self._register_intra if candidate.intra else self._register_inter
        constraint, accepted = measure(candidate, by_id)
        seconds = time.perf_counter() - start
        self.seconds["register"] += seconds
        record = LoopRecord(candidate.query_keyframe, candidate.match_keyframe, candidate.query_submap,
                            candidate.match_submap, candidate.intra, accepted, constraint.fitness, seconds,
                            candidate.inliers)
        self.records.append(record)
        return LoopOutcome(record, constraint if accepted else None)

    def _register_intra(self, candidate: LoopCandidate, by_id: dict) -> tuple[LoopConstraint, bool]:
        submap = by_id[candidate.query_submap]
        keyframes = submap.keyframes
        index = {kf.frame_id: i for i, kf in enumerate(keyframes)}
        j, k = index[candidate.match_keyframe], index[candidate.query_keyframe]
        init = invert_pose(keyframes[k].cam_to_world) @ keyframes[j].cam_to_world
        start = init if candidate.relative is None else invert_pose(candidate.relative).to(init)
        motion, (overlap, fitness) = align_keyframes(submap.observation(keyframes[j], self.device),
                                                     submap.observation(keyframes[k], self.device), start,
                                                     self.cfg.registration)
        reg = self.cfg.registration
        constraint = LoopConstraint(candidate.match_keyframe, candidate.query_keyframe, candidate.match_submap,
                                    candidate.query_submap, invert_pose(motion.detach().cpu().double()),
                                    (reg.sigma_rotation, reg.sigma_translation), fitness, True)
        accepted = overlap >= reg.min_overlap and fitness >= reg.min_fitness
        return constraint, accepted and self._plausible(init, motion, abs(k - j))

    def _register_inter(self, candidate: LoopCandidate, by_id: dict) -> tuple[LoopConstraint, bool]:
        query, match = by_id[candidate.query_submap], by_id[candidate.match_submap]
        ends = {candidate.query_submap: candidate.query_keyframe, candidate.match_submap: candidate.match_keyframe}
        target, source = (match, query) if len(match.keyframes) >= len(query.keyframes) else (query, match)
        loop_pair = tuple([kf.frame_id for kf in s.keyframes].index(ends[s.submap_id]) for s in (source, target))
        current = invert_pose(target.anchor) @ source.anchor
        registration = semantic_guided_registration(
            source.load_cloud(self.device), self._poses(source), self._descriptor_stack(source),
            target.load_cloud(self.device), self._poses(target), self._descriptor_stack(target),
            source.keyframes[0].obs.camera, self.cfg.registration, self.descriptor, self.backend,
            self.cfg.descriptor_threshold(self.descriptor.kind), loop_pair, current.detach().cpu().double(),
            self._verified_transform(candidate, source, target, loop_pair))
        first, last = sorted((target.submap_id, source.submap_id))
        between = sum(len(s.keyframes) for s in by_id.values() if first <= s.submap_id < last)
        constraint = LoopConstraint(ends[target.submap_id], ends[source.submap_id], target.submap_id,
                                    source.submap_id, registration.transform.detach().cpu().double(),
                                    registration.sigmas, registration.fine.fitness, False)
        self._set_graph(by_id.values())
        judged = self.graphs.connected(source.submap_id, target.submap_id)  # else the anchors' pose is a guess
        return constraint, registration.accepted and (not judged or self._plausible(current, registration.transform,
                                                                                    between))

    @staticmethod
    def _verified_transform(candidate: LoopCandidate, source, target, loop_pair: tuple[int, int]) -> tuple:
        """The source -> target submap transform that geometric verification measured (none without it):
        T = T_t C T_s^-1 with the loop keyframes' poses T_s, T_t in their submaps and C target-camera-from-source."""
        if candidate.relative is None:
            return ()
        target_from_source = (candidate.relative if target.submap_id == candidate.match_submap
                              else invert_pose(candidate.relative))
        pose_s, pose_t = (s.keyframes[i].cam_to_world.detach().cpu().double()
                          for s, i in ((source, loop_pair[0]), (target, loop_pair[1])))
        return (pose_t @ target_from_source.double() @ invert_pose(pose_s),)

    def _poses(self, submap) -> torch.Tensor:
        return torch.stack([kf.cam_to_world.detach().double().cpu() for kf in submap.keyframes])

    def _descriptor_stack(self, submap) -> torch.Tensor:
        return torch.stack([self._descriptor(submap, kf) for kf in submap.keyframes])

    # --- correction ---------------------------------------------------------------------------------------------
    def correct(self, submaps: Sequence, constraint: LoopConstraint) -> Correction:
        """Add an accepted loop to the pose graph of its level (:class:`LoopGraphs`, given the current keyframe poses
        and anchors), optimise it with every loop of that level so far and move the map (:meth:`apply`)."""
        start = time.perf_counter()
        self._set_graph(submaps)
        correction = self.apply(submaps, self.graphs.add(constraint))
        self.seconds["correct"] += time.perf_counter() - start
        return correction

    def _set_graph(self, submaps) -> None:
        """The pose graphs given the map's current anchors, segments and keyframe poses."""
        for s in submaps:
            self.graphs.set_anchor(s.submap_id, s.anchor, s.starts_segment)
            for kf in s.keyframes:
                self.graphs.set_keyframe(kf.frame_id, s.submap_id, kf.cam_to_world)

    def apply(self, submaps: Sequence, update: PoseGraphUpdate) -> Correction:
        """Move the map to a pose-graph answer: anchors (:meth:`move_anchors`), then keyframes grouped by their
        submap (:meth:`move_keyframes`), all under the mapper's lock so that a tracker in another thread sees the map
        before or after, never between; then the submaps whose keyframes moved beyond the loop edges' sigma floors are
        re-mapped (:meth:`remap`). Unknown ids are ignored."""
        by_id = {s.submap_id: s for s in submaps}
        owner = {kf.frame_id: s.submap_id for s in submaps for kf in s.keyframes}
        grouped: dict[int, dict[int, object]] = {}
        for frame_id, pose in update.keyframes.items():
            if frame_id in owner:
                grouped.setdefault(owner[frame_id], {})[frame_id] = pose
        with self.mapper.lock:
            anchors = self.move_anchors(submaps, update.anchors)
            moved = {s: self.move_keyframes(by_id[s], poses) for s, poses in grouped.items()}
        for s, (_, displaced) in moved.items():
            self.remap(by_id[s], displaced)
        return Correction(anchors, sum(count for count, _ in moved.values()), tuple(sorted(grouped)))

    def move_keyframes(self, submap, poses: dict[int, object]) -> tuple[int, int]:
        """Set the poses (submap frame, by frame id) of ``submap``'s non-fixed keyframes. Returns how many moved and
        how many of them moved by more than the loop edges' standard-deviation floors (``registration.sigma_translation``
        / ``sigma_rotation``)."""
        moved, displaced = 0, 0
        reg = self.cfg.registration
        for kf in submap.keyframes:
            if kf.frame_id in poses and not kf.fixed:
                pose = torch.as_tensor(np.array(poses[kf.frame_id]), dtype=kf.cam_to_world.dtype,
                                       device=kf.cam_to_world.device)
                change = invert_pose(kf.cam_to_world.detach().cpu().double()) @ pose.detach().cpu().double()
                displaced += (float(change[:3, 3].norm()) > reg.sigma_translation
                              or float(se3_log(change)[3:].norm()) > reg.sigma_rotation)
                kf.cam_to_world = pose
                moved += 1
        return moved, displaced

    def remap(self, submap, displaced: int) -> None:
        """Re-map ``submap`` with its keyframe poses held, ``remap_iterations_per_keyframe`` iterations per
        ``displaced`` keyframe (none for 0: a correction within the measurement's own uncertainty leaves the map as it
        is)."""
        if not displaced:
            return
        keyframes = [Keyframe(kf.frame_id, submap.observation(kf, self.device), kf.cam_to_world.to(self.device),
                              True) for kf in submap.keyframes]
        iterations = self.cfg.remap_iterations_per_keyframe * displaced
        submap.cloud, _ = self.mapper.optimise(submap.take_cloud(self.device), keyframes, iterations,
                                               optimise_poses=False)

    @staticmethod
    def move_anchors(submaps: Sequence, poses: dict[int, object]) -> int:
        """Set the anchors (world-from-submap, by submap id) of ``submaps``; their keyframes, frames and Gaussians
        follow, being stored in the submap frame. Returns how many moved."""
        moved = [s for s in submaps if s.submap_id in poses]
        for submap in moved:
            submap.anchor = torch.as_tensor(np.array(poses[submap.submap_id]), dtype=submap.anchor.dtype,
                                            device=submap.anchor.device)
        return len(moved)


def _find_keyframe(by_id: dict, candidate: LoopCandidate, submap_id: int, frame_id: int) -> tuple:
    """(submap, keyframe) of a loop candidate's keyframe; ValueError when the submap does not hold it."""
    submap = by_id.get(submap_id)
    keyframe = next((kf for kf in getattr(submap, "keyframes", []) if kf.frame_id == frame_id), None)
    if keyframe is None:
        raise ValueError(f"loop candidate {candidate.query_keyframe}->{candidate.match_keyframe}: no keyframe "
                         f"{frame_id} in submap {submap_id}")
    return submap, keyframe


PHASES = ("describe", "detect", "verify", "register", "correct")  # LoopClosure.seconds
