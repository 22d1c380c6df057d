"""Place recognition on the images themselves, without pretrained weights: a bag of binary words over ORB features
with a vocabulary built online.

Each keyframe's ORB features come from :mod:`gausem_core.slam.features`.

Vocabulary: a descriptor within ``word_radius`` bits (Hamming) of a known word is that word; otherwise it becomes a
new word (words are never merged or moved, so a keyframe's word ids stay valid). A query's descriptors are quantised
without growing the vocabulary. Keyframes are scored against a query by tf-idf: word weights count x log(N / n_w)
(N keyframes stored, n_w of them holding word w), each vector L1-normalised, and the score is the L1 similarity
1 - |a - b|_1 / 2 = sum_w min(a_w, b_w), in [0, 1]. Only keyframes sharing a word with the query are scored (the
word -> keyframe postings are the inverted index). :class:`BagOfWords` hands out ``1 - score`` as a distance, so the
loop detector treats it as it treats global-descriptor distances.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from gausem_core.config import BowConfig
from gausem_core.slam.features import DESCRIPTOR_BYTES, OrbFeatures


class Vocabulary:
    """Binary words learned online: a descriptor farther than ``radius`` bits from every word becomes one."""

    def __init__(self, radius: int):
        if not 0 <= radius < 8 * DESCRIPTOR_BYTES:
            raise ValueError(f"Vocabulary: radius must lie in [0, {8 * DESCRIPTOR_BYTES}), got {radius}")
        self.radius = radius
        self.words = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def __len__(self) -> int:
        return len(self.words)

    def quantise(self, descriptors: np.ndarray, grow: bool) -> np.ndarray:
        """(N,) word ids of descriptors (N, 32) uint8: the nearest word within the radius; otherwise a new word
        (``grow``) or -1."""
        if descriptors.ndim != 2 or descriptors.shape[1] != DESCRIPTOR_BYTES or descriptors.dtype != np.uint8:
            raise ValueError(f"Vocabulary.quantise: need (N, {DESCRIPTOR_BYTES}) uint8 descriptors, got "
                             f"{descriptors.dtype} {descriptors.shape}")
        ids = np.full(len(descriptors), -1, np.int64)
        if len(self.words) and len(descriptors):
            for match in self._matcher.match(descriptors, self.words):
                if match.distance <= self.radius:
                    ids[match.queryIdx] = match.trainIdx
        if grow:
            new = np.flatnonzero(ids < 0)
            ids[new] = len(self.words) + np.arange(len(new))
            self.words = np.concatenate([self.words, descriptors[new]])
        return ids


class BagOfWords:
    """Keyframes as bags of binary words, searched by tf-idf L1 similarity (see the module docstring).

    The same interface as :class:`~gausem_core.slam.loop.DescriptorDatabase` towards the loop detector: keyframe
    ids added in increasing order, ``search`` returns ids and distances (``1 - score``), closest first.
    """

    def __init__(self, cfg: BowConfig):
        self.cfg = cfg
        self.vocabulary = Vocabulary(cfg.word_radius)
        self.features: dict[int, OrbFeatures] = {}  # keyframe id -> its features, in insertion order
        self.words: dict[int, np.ndarray] = {}  # keyframe id -> word id of each feature
        self._rows = np.zeros(0, np.int64)  # postings: (keyframe row, word, count) per distinct word of a keyframe
        self._posted_words = np.zeros(0, np.int64)
        self._counts = np.zeros(0, np.float64)
        self._frequency = np.zeros(0, np.int64)  # per word: keyframes holding it

    def __len__(self) -> int:
        return len(self.features)

    @property
    def ids(self) -> np.ndarray:
        return np.fromiter(self.features, np.int64, len(self.features))

    def add(self, keyframe_id: int, features: OrbFeatures) -> None:
        """Store a keyframe's features; their descriptors grow the vocabulary."""
        if self.features and keyframe_id <= next(reversed(self.features)):
            raise ValueError(f"BagOfWords.add: keyframe id {keyframe_id} is not larger than the last one "
                             f"({next(reversed(self.features))})")
        self._post(keyframe_id, features, self.vocabulary.quantise(features.descriptors, grow=True))

    def _post(self, keyframe_id: int, features: OrbFeatures, words: np.ndarray) -> None:
        distinct, counts = np.unique(words, return_counts=True)
        self._frequency = np.concatenate([self._frequency, np.zeros(len(self.vocabulary) - len(self._frequency),
                                                                    np.int64)])
        self._frequency[distinct] += 1
        self._rows = np.concatenate([self._rows, np.full(len(distinct), len(self.features))])
        self._posted_words = np.concatenate([self._posted_words, distinct])
        self._counts = np.concatenate([self._counts, counts.astype(np.float64)])
        self.features[keyframe_id] = features
        self.words[keyframe_id] = words

    def scores(self, features: OrbFeatures, exclude_recent: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(ids, scores) of the stored keyframes, except the newest ``exclude_recent``, that share a word with the
        query; in storage order."""
        searchable = len(self) - exclude_recent
        words = self.vocabulary.quantise(features.descriptors, grow=False)
        words = words[words >= 0]
        if searchable <= 0 or len(words) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        idf = np.log(len(self) / np.maximum(self._frequency, 1))
        query_words, query_counts = np.unique(words, return_counts=True)
        query = np.zeros(len(self.vocabulary))
        query[query_words] = query_counts * idf[query_words]
        if query.sum() <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        query /= query.sum()
        weights = self._counts * idf[self._posted_words]
        norms = np.bincount(self._rows, weights, minlength=len(self))
        shared = (query[self._posted_words] > 0) & (self._rows < searchable) & (norms[self._rows] > 0)
        rows = self._rows[shared]
        common = np.minimum(weights[shared] / norms[rows], query[self._posted_words[shared]])
        scores = np.bincount(rows, common, minlength=searchable)[:searchable]
        hit = np.flatnonzero(np.bincount(rows, minlength=searchable)[:searchable] > 0)
        return self.ids[hit], scores[hit]

    def search(self, features: OrbFeatures, k: int | None = None,
               exclude_recent: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` (all when None) best-scoring keyframes as (ids, distances = 1 - score), closest first."""
        ids, scores = self.scores(features, exclude_recent)
        order = np.argsort(-scores, kind="stable")[:k]
        return ids[order], (1.0 - scores[order]).astype(np.float32)

    # --- persistence --------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The vocabulary and every keyframe's features and word ids, as CPU tensors; the postings are rebuilt."""
        return {"words": torch.from_numpy(self.vocabulary.words.copy()),
                "keyframes": [[i, f.tensors(), torch.from_numpy(self.words[i])] for i, f in self.features.items()]}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (onto an empty index built with the same configuration)."""
        if len(self):
            raise ValueError("BagOfWords.load_state_dict: the index is not empty")
        self.vocabulary.words = state["words"].numpy().copy()
        for keyframe_id, features, words in state["keyframes"]:
            self._post(int(keyframe_id), OrbFeatures.from_tensors(features), words.numpy().copy())
