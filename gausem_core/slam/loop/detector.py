"""Semantic-aware loop detection (paper Algorithm 1): descriptor radius search, re-ranked by landmark scores."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from gausem_core.config import LoopConfig
from gausem_core.slam.loop.database import DescriptorDatabase
from gausem_core.slam.loop.landmarks import landmark_distance
from gausem_core.slam.features import OrbFeatures
from gausem_core.slam.loop.words import BagOfWords


@dataclass(frozen=True)
class PlaceSignature:
    """What the loop detector learns of a keyframe: ``appearance``, what its place-recognition database compares (a
    global descriptor (D,), or the bag of words' ORB features), the Eq. 7 landmark score vector over the keyframe's
    submap's Gaussians (C,), and ``nearby``: the ids of earlier keyframes near it in the current pose estimate."""

    keyframe_id: int
    submap_id: int
    appearance: torch.Tensor | OrbFeatures
    landmark_scores: torch.Tensor
    nearby: tuple[int, ...] = ()


@dataclass(frozen=True)
class LoopCandidate:
    """A detected loop: the query keyframe revisits the place of the match keyframe."""

    query_keyframe: int
    match_keyframe: int
    query_submap: int
    match_submap: int
    descriptor_distance: float
    landmark_distance: float
    relative: torch.Tensor | None = None  # geometric verification's match-camera-from-query-camera (float64 4x4)
    inliers: int = 0  # geometric verification's PnP inliers

    @property
    def intra(self) -> bool:
        """True when both keyframes belong to the same submap (an intra-submap loop)."""
        return self.query_submap == self.match_submap


class LoopDetector:
    """Algorithm 1. Every ``check_every``-th keyframe is compared with all stored keyframes except the newest
    ``exclude_recent``; those with a descriptor distance below ``max_descriptor_distance`` (and, when
    ``min_submap_gap`` > 0, from a submap at least that many ids older) are candidates, and the one whose landmark
    score vector is closest to the query's is the loop. With ``min_relative_similarity`` > 0 (the bag of words), only
    keyframes whose similarity (1 - distance) reaches that fraction of the best one's are descriptor candidates: a
    bag-of-words score passes ``min_score`` for much of a room, and the landmark order among all of those would bury
    the revisit the words found. Stored keyframes the caller names as ``nearby`` (close in the
    current pose estimate) are candidates too, at every keyframe: a revisit under small drift needs no descriptor.
    :meth:`add_keyframe` returns the ranked candidates, at most ``max_candidates`` of them: the first is the loop, or
    (the bag of words) the caller verifies them in order and the first confirmed is the loop.

    ``database`` holds the keyframes' appearances: by default a
    :class:`~gausem_core.slam.loop.DescriptorDatabase` of global descriptors; anything with its ``add``, ``search``
    (ids and distances, closest first), ``ids`` and ``len`` will do (the bag of words,
    :class:`~gausem_core.slam.loop.words.BagOfWords`, the only one that takes ORB features). The landmark re-ranking
    needs classes: with score vectors of fewer than two classes the candidates keep their descriptor order.

    Landmark score vectors (:func:`~gausem_core.slam.loop.landmarks.landmark_scores`) are computed by the caller, who
    owns the Gaussians; a stored keyframe is compared with the vector it was added with. Vectors may grow as classes
    are discovered (classes appended at the end): a shorter vector is compared zero-padded, which is exact, since a
    class unknown when the vector was made was not observed (score 0).
    """

    def __init__(self, *, keyframe_every: int = 5, check_every: int = 6, max_descriptor_distance: float = 0.2,
                 exclude_recent: int = 6, min_submap_gap: int = 0, descriptor_dim: int = 384, backend: str = "auto",
                 database=None, max_candidates: int = 1, min_relative_similarity: float = 0.0):
        for name, value, low in (("keyframe_every", keyframe_every, 1), ("check_every", check_every, 1),
                                 ("exclude_recent", exclude_recent, 0), ("min_submap_gap", min_submap_gap, 0),
                                 ("max_candidates", max_candidates, 1)):
            if value < low:
                raise ValueError(f"LoopDetector: {name} must be >= {low}, got {value}")
        if max_descriptor_distance <= 0:
            raise ValueError(f"LoopDetector: max_descriptor_distance must be positive, got {max_descriptor_distance}")
        if not 0.0 <= min_relative_similarity <= 1.0:
            raise ValueError(f"LoopDetector: min_relative_similarity must lie in [0, 1], got {min_relative_similarity}")
        self.keyframe_every = keyframe_every
        self.check_every = check_every
        self.max_descriptor_distance = max_descriptor_distance
        self.exclude_recent = exclude_recent
        self.min_submap_gap = min_submap_gap
        self.max_candidates = max_candidates
        self.min_relative_similarity = min_relative_similarity
        self.database = database if database is not None else DescriptorDatabase(descriptor_dim, backend)
        # the stored keyframes in the order stored: id -> (submap id, landmark scores)
        self.keyframes: dict[int, tuple[int, torch.Tensor]] = {}
        self.unchecked: list[int] = []  # keyframes stored for checking since the last check, whose turn never came
        # every (query, match) keyframe pair a check found (all its candidates, before the max_candidates cut): the
        # detections that the paper's protocol scores, apart from the loops that verification then accepts
        self.detections: list[tuple[int, int]] = []

    @classmethod
    def from_config(cls, cfg: LoopConfig, descriptor_kind: str, **kwargs) -> "LoopDetector":
        """The detector of ``cfg`` for signatures of ``descriptor_kind`` (which picks the distance threshold; "bow":
        a :class:`~gausem_core.slam.loop.words.BagOfWords` database, whose ``bow.candidates`` best are returned)."""
        if descriptor_kind == "bow":
            kwargs.setdefault("database", BagOfWords(cfg.bow))
            kwargs.setdefault("max_candidates", cfg.bow.candidates)
            kwargs.setdefault("min_relative_similarity", cfg.bow.min_relative_score)
        return cls(keyframe_every=cfg.keyframe_every, check_every=cfg.check_every,
                   max_descriptor_distance=cfg.descriptor_threshold(descriptor_kind),
                   exclude_recent=cfg.exclude_recent, **kwargs)

    def is_keyframe(self, frame_index: int) -> bool:
        """Algorithm 1, line 1: a keyframe every ``keyframe_every`` frames (frame 0 is one)."""
        return frame_index % self.keyframe_every == 0

    def add_keyframe(self, place: PlaceSignature, check: bool = True) -> list[LoopCandidate]:
        """Check a keyframe for loops (its appearance on every ``check_every``-th call, its ``nearby`` keyframes on
        every call; with ``check`` false not at all: a keyframe of a loaded map, or one checked elsewhere), then store
        it. Returns the ranked candidates (at most ``max_candidates``; none: no loop)."""
        if place.landmark_scores.dim() != 1:
            raise ValueError(f"LoopDetector.add_keyframe: landmark scores of keyframe {place.keyframe_id} must be a "
                             f"vector, got shape {tuple(place.landmark_scores.shape)}")
        if isinstance(place.appearance, OrbFeatures) != isinstance(self.database, BagOfWords):
            raise ValueError(f"LoopDetector.add_keyframe: keyframe {place.keyframe_id} is described by "
                             f"{type(place.appearance).__name__}, but the database is a {type(self.database).__name__}")
        is_check = check and (len(self.database) + 1) % self.check_every == 0
        nearby = set(place.nearby) if check else set()
        ranked = self._candidates(place, is_check, nearby) if is_check or nearby else []
        self.detections += [(c.query_keyframe, c.match_keyframe) for c in ranked]
        self.database.add(place.keyframe_id, place.appearance)
        self.keyframes[place.keyframe_id] = (place.submap_id, place.landmark_scores.detach().cpu())
        if is_check:
            self.unchecked = []
        elif check:
            self.unchecked.append(place.keyframe_id)
        return ranked[:self.max_candidates]

    def check_stored(self, place: PlaceSignature) -> list[LoopCandidate]:
        """The appearance check of a stored keyframe (one of :attr:`unchecked`, e.g. at the end of a run) against the
        keyframes stored before it, less the ``exclude_recent`` newest of those, as :meth:`add_keyframe` would have
        made it in its turn; it is no longer unchecked. Raises ValueError for a keyframe not stored."""
        order = list(self.keyframes)
        if place.keyframe_id not in self.keyframes:
            raise ValueError(f"LoopDetector.check_stored: keyframe {place.keyframe_id} is not stored")
        if place.keyframe_id in self.unchecked:
            self.unchecked.remove(place.keyframe_id)
        later = len(order) - order.index(place.keyframe_id)  # itself and the keyframes stored after it
        ranked = self._candidates(place, True, set(), later)
        self.detections += [(c.query_keyframe, c.match_keyframe) for c in ranked]
        return ranked[:self.max_candidates]

    def _candidates(self, place: PlaceSignature, by_descriptor: bool, nearby: set[int],
                    later: int = 0) -> list[LoopCandidate]:
        """The candidates among the stored keyframes but the ``later`` newest and the ``exclude_recent`` before those,
        closest landmark vector first when there are classes (ties: closest descriptor first)."""
        exclude = later + self.exclude_recent
        searchable = len(self.database) - exclude
        if searchable <= 0:
            return []
        ids, distances = self.database.search(place.appearance, k=searchable, exclude_recent=exclude)
        submap_id, landmark_scores = place.submap_id, place.landmark_scores
        # similarity 1 - distance at least min_relative_similarity of the best one's (DBoW2-style relative score)
        best = 1.0 - float(distances.min()) if len(distances) else 0.0
        max_distance = min(self.max_descriptor_distance, 1.0 - self.min_relative_similarity * best + 1e-12)
        candidates = []
        for match, desc_dist in zip(ids.tolist(), distances.tolist()):
            if not ((by_descriptor and desc_dist < max_distance) or match in nearby):
                continue
            match_submap, match_scores = self.keyframes[match]
            if submap_id - match_submap < self.min_submap_gap:
                continue
            land_dist = landmark_distance(*_zero_padded(landmark_scores.detach().cpu(), match_scores))
            candidates.append(LoopCandidate(place.keyframe_id, match, submap_id, match_submap, desc_dist, land_dist))
        if len(landmark_scores) > 1:
            candidates.sort(key=lambda c: c.landmark_distance)  # stable: descriptor order on ties
        return candidates


def nearby_keyframes(query: torch.Tensor, poses: Mapping[int, torch.Tensor], radius: float,
                     max_angle_deg: float) -> list[int]:
    """Ids of ``poses`` (cam_to_world 4x4, one frame with ``query``) whose camera centre lies within ``radius`` of
    the query's and whose optical axis is within ``max_angle_deg`` of its (none when ``radius`` <= 0)."""
    if radius <= 0 or not poses:
        return []
    ids = list(poses)
    stacked = torch.stack([torch.as_tensor(poses[i]).detach().cpu().double() for i in ids])
    query = torch.as_tensor(query).detach().cpu().double()
    close = (stacked[:, :3, 3] - query[:3, 3]).norm(dim=1) < radius
    aligned = stacked[:, :3, 2] @ query[:3, 2] >= math.cos(math.radians(max_angle_deg))
    return [i for i, keep in zip(ids, (close & aligned).tolist()) if keep]


def _zero_padded(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two score vectors padded with zeros to the same length."""
    n = max(len(a), len(b))
    return torch.nn.functional.pad(a, (0, n - len(a))), torch.nn.functional.pad(b, (0, n - len(b)))
