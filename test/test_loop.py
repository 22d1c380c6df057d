"""Loop detection: descriptor database (FAISS vs torch), Gaussian-IDF landmark scores, Algorithm 1."""
import math

import numpy as np
import pytest
import torch

from gausem_core.config import LoopConfig
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.loop import (DescriptorDatabase, LoopDetector, PlaceSignature, gaussian_idf,
                                   landmark_distance, landmark_scores, nearby_keyframes, observed_gaussians)
from gausem_core.slam.loop.database import _import_faiss

BACKENDS = ["torch"] + (["faiss"] if _import_faiss() is not None else [])


def _filled(backend, vectors, ids):
    db = DescriptorDatabase(vectors.shape[1], backend)
    for i, v in zip(ids, vectors):
        db.add(i, v)
    return db


# --- database -----------------------------------------------------------------------------------------------------
def test_database_faiss_and_torch_agree_with_exclusion_window():
    pytest.importorskip("faiss")
    rng = np.random.default_rng(1)
    vectors = rng.normal(size=(300, 24)).astype(np.float32)
    ids = np.cumsum(rng.integers(1, 4, size=300))  # increasing, not consecutive
    dbs = [_filled(b, vectors, ids) for b in ("faiss", "torch")]
    assert [db.backend for db in dbs] == ["faiss", "torch"]
    unit = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    for q in rng.normal(size=(10, 24)):
        for kwargs in ({"k": 7}, {"radius": 1.25}, {"k": 3, "radius": 1.3}, {"k": 400, "exclude_recent": 40},
                       {"radius": 1.3, "exclude_recent": 250}):
            (fi, fd), (ti, td) = (db.search(q, **kwargs) for db in dbs)
            np.testing.assert_array_equal(fi, ti)
            np.testing.assert_allclose(fd, td, atol=1e-5)
            # independent check: true L2 distances of unit vectors, newest entries excluded, sorted, within radius
            rows = np.searchsorted(ids, ti)
            np.testing.assert_allclose(td, np.linalg.norm(unit[rows] - q / np.linalg.norm(q), axis=1), atol=1e-5)
            assert np.all(rows < 300 - kwargs.get("exclude_recent", 0))
            assert np.all(np.diff(td) >= 0)
            if "radius" in kwargs:
                assert np.all(td < kwargs["radius"]) and len(td) > 0
        assert len(dbs[0].search(q, k=5, exclude_recent=300)[0]) == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_database_hand_example(backend):
    db = _filled(backend, np.array([[2.0, 0.0], [0.0, 3.0], [1.0, 1.0]]), [10, 11, 12])
    ids, dist = db.search(np.array([5.0, 0.0]), radius=0.8)
    np.testing.assert_array_equal(ids, [10, 12])
    np.testing.assert_allclose(dist, [0.0, math.sqrt(2 - math.sqrt(2))], atol=1e-6)  # |(1,0) - (1,1)/sqrt2|
    ids, dist = db.search(np.array([0.0, 1.0]), k=1, exclude_recent=1)
    np.testing.assert_array_equal(ids, [11])


def test_database_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    db = _filled("torch", rng.normal(size=(40, 8)), range(0, 80, 2))
    path = tmp_path / "descriptors"  # no suffix: must be written under exactly this name
    db.save(path)
    loaded = DescriptorDatabase.load(path, backend=BACKENDS[-1])
    np.testing.assert_array_equal(loaded.ids, db.ids)
    np.testing.assert_array_equal(loaded.vectors, db.vectors)
    q = rng.normal(size=8)
    for a, b in zip(loaded.search(q, k=5), db.search(q, k=5)):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_database_rejects_bad_input(tmp_path):
    db = DescriptorDatabase(3, "torch")
    db.add(5, [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="ids must increase"):
        db.add(5, [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="non-zero"):
        db.add(6, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="expected 3"):
        db.search([1.0, 0.0], k=1)
    with pytest.raises(ValueError, match="give k, radius"):
        db.search([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="backend"):
        DescriptorDatabase(3, "annoy")
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(3))
    with pytest.raises(ValueError, match="not a DescriptorDatabase"):
        DescriptorDatabase.load(bad)


# --- landmarks ----------------------------------------------------------------------------------------------------
def test_gaussian_idf_and_landmark_scores_hand_example():
    classes = torch.tensor([0, 0, 0, 1, 1, 2])  # N = 6; N_c = 3, 2, 1, 0
    idf = gaussian_idf(classes, 4)
    np.testing.assert_allclose(idf.numpy(), [math.log(6 / 4), math.log(6 / 3), math.log(6 / 2), math.log(6)])
    observed = torch.tensor([True, False, False, True, True, False])  # M = 3; M_c = 1, 2, 0, 0
    w = landmark_scores(classes, observed, idf)
    np.testing.assert_allclose(w.numpy(), [3 * math.log(1.5), 1.5 * math.log(2), 0.0, 0.0])
    assert landmark_scores(classes, torch.zeros(6, dtype=torch.bool), idf).abs().sum() == 0
    assert landmark_distance(torch.tensor([3.0, 0.0]), torch.tensor([0.0, 4.0])) == pytest.approx(5.0)


def test_landmarks_reject_bad_input():
    with pytest.raises(ValueError, match=r"\[0, 3\)"):
        gaussian_idf(torch.tensor([0, 3]), 3)
    with pytest.raises(ValueError, match="no Gaussians"):
        gaussian_idf(torch.zeros(0, dtype=torch.long), 3)
    with pytest.raises(ValueError, match="integer"):
        gaussian_idf(torch.tensor([0.0, 1.0]), 3)
    with pytest.raises(ValueError, match="bool mask"):
        landmark_scores(torch.tensor([0, 1]), torch.tensor([1, 0]), torch.ones(3))
    with pytest.raises(ValueError, match="equal length"):
        landmark_distance(torch.ones(3), torch.ones(4))


# --- detector -----------------------------------------------------------------------------------------------------
def _unit(v):
    return v / v.norm()


def _loop(detector, keyframe_id, submap_id, descriptor, scores, nearby=()):
    """Add a keyframe; the loop (the first ranked candidate) or None."""
    ranked = detector.add_keyframe(PlaceSignature(keyframe_id, submap_id, descriptor, scores, tuple(nearby)))
    assert len(ranked) <= detector.max_candidates
    return ranked[0] if ranked else None


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_finds_revisit_and_reranks_by_landmarks(backend):
    """18 keyframes; the 18th (a check point) revisits the place of keyframe 3. Keyframe 5 looks even more alike
    (repetitive texture) but holds other classes, and keyframe 16 is an identical but too recent view."""
    g = torch.Generator().manual_seed(3)
    places = torch.stack([_unit(torch.randn(16, generator=g)) for _ in range(17)])
    scores = torch.rand(17, 5, generator=g) * 4
    query = _unit(places[3] + 0.05 * _unit(torch.randn(16, generator=g)))
    descriptors = list(places)
    descriptors[5] = _unit(query + 0.02 * _unit(torch.randn(16, generator=g)))  # closer to the query than kf 3
    descriptors[16] = query.clone()
    detector = LoopDetector(keyframe_every=5, check_every=6, max_descriptor_distance=0.2, exclude_recent=6,
                            descriptor_dim=16, backend=backend)
    for kf in range(17):
        assert _loop(detector, kf, kf // 9, descriptors[kf], scores[kf]) is None
    loop = _loop(detector, 17, 1, query, scores[3] + 0.01)
    assert loop is not None
    assert (loop.query_keyframe, loop.match_keyframe, loop.query_submap, loop.match_submap) == (17, 3, 1, 0)
    assert not loop.intra
    assert loop.descriptor_distance == pytest.approx(float((query - places[3]).norm()), abs=1e-5)
    assert loop.landmark_distance == pytest.approx(0.01 * math.sqrt(5), abs=1e-6)
    assert float((query - descriptors[5]).norm()) < loop.descriptor_distance < 0.2  # kf 5 was a candidate


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_checks_only_every_sixth_keyframe(backend):
    """Every keyframe revisits keyframe 0's place; only the 6th, 12th, ... keyframes are compared."""
    g = torch.Generator().manual_seed(4)
    place = _unit(torch.randn(8, generator=g))
    detector = LoopDetector(check_every=6, exclude_recent=2, descriptor_dim=8, backend=backend)
    found = []
    for kf in range(18):
        loop = _loop(detector, kf, 0, _unit(place + 0.01 * torch.randn(8, generator=g)), torch.ones(3))
        if loop is not None:
            found.append(kf)
            assert loop.intra
    assert found == [5, 11, 17]
    assert detector.is_keyframe(10) and not detector.is_keyframe(11)


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_checks_a_stored_keyframe_whose_turn_never_came(backend):
    """After keyframes 0..15 (checks at 5 and 11), 12..15 are unchecked; checking 14 then gives what a check in its
    turn gave (keyframe 15, stored after it, and the recent ones before it are not searched)."""
    g = torch.Generator().manual_seed(5)
    place = _unit(torch.randn(8, generator=g))
    signatures = [PlaceSignature(kf, 0, _unit(place + 0.01 * torch.randn(8, generator=g)), torch.ones(3))
                  for kf in range(16)]
    detector = LoopDetector(check_every=6, exclude_recent=2, descriptor_dim=8, backend=backend, max_candidates=20)
    in_turn = LoopDetector(check_every=15, exclude_recent=2, descriptor_dim=8, backend=backend, max_candidates=20)
    for signature in signatures:
        detector.add_keyframe(signature)
    expected = [in_turn.add_keyframe(signature) for signature in signatures[:15]][-1]
    assert detector.unchecked == [12, 13, 14, 15]
    candidates = detector.check_stored(signatures[14])
    assert candidates == expected and {c.match_keyframe for c in candidates} == set(range(12))
    assert detector.unchecked == [12, 13, 15]
    detector.add_keyframe(PlaceSignature(16, 0, signatures[0].appearance, torch.ones(3)), check=False)
    assert detector.unchecked == [12, 13, 15]  # a keyframe stored without a check is not awaiting one
    with pytest.raises(ValueError, match="not stored"):
        detector.check_stored(PlaceSignature(99, 0, signatures[0].appearance, torch.ones(3)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_detector_takes_nearby_keyframes_at_every_keyframe(backend):
    """Keyframes the caller names as nearby are candidates on any keyframe, whatever their descriptors; the recent
    window stays excluded, unknown ids are ignored, and on a check keyframe descriptor candidates join them (the
    landmark scores pick the loop)."""
    g = torch.Generator().manual_seed(5)
    descriptors = [_unit(torch.randn(8, generator=g)) for _ in range(11)]
    scores = torch.rand(11, 3, generator=g)
    detector = LoopDetector(check_every=6, exclude_recent=2, max_descriptor_distance=0.2, descriptor_dim=8,
                            backend=backend)
    for kf in range(4):
        assert _loop(detector, kf, 0, descriptors[kf], scores[kf]) is None
    loop = _loop(detector, 4, 1, descriptors[4], scores[1] + 0.01, nearby=[1, 3, 99])  # 3 is too recent
    assert (loop.query_keyframe, loop.match_keyframe, loop.query_submap, loop.match_submap) == (4, 1, 1, 0)
    assert loop.descriptor_distance == pytest.approx(float((descriptors[4] - descriptors[1]).norm()), abs=1e-5)
    assert _loop(detector, 5, 1, descriptors[0], scores[5], nearby=[]).match_keyframe == 0  # 6th: descriptors
    for kf in range(6, 11):  # calls 7-11: no check, nothing nearby
        assert _loop(detector, kf, 1, descriptors[kf], scores[kf]) is None
    loop = _loop(detector, 11, 1, descriptors[0], scores[2], nearby=[2])  # the 12th call: a check, and nearby
    assert loop.match_keyframe == 2  # kf 0 is the descriptor candidate, kf 2 matches the landmark scores
    assert _loop(detector, 12, 1, descriptors[2], scores[2], nearby=[]) is None  # kf 2: no check, not nearby


def test_nearby_keyframes_by_centre_distance_and_viewing_direction():
    def pose(x, yaw_deg):
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # optical axis turned about y
        out[0, 3] = x
        return out

    poses = {0: pose(0.1, 10.0), 5: pose(0.29, 0.0), 10: pose(0.31, 0.0), 15: pose(0.0, 35.0), 20: pose(0.0, -29.0)}
    assert nearby_keyframes(pose(0.0, 0.0), poses, 0.3, 30.0) == [0, 5, 20]
    assert nearby_keyframes(pose(0.0, 0.0), poses, 0.0, 30.0) == []
    assert nearby_keyframes(pose(0.0, 0.0), {}, 0.3, 30.0) == []


def test_detector_min_submap_gap_and_errors():
    place = torch.ones(4)
    detector = LoopDetector(check_every=2, exclude_recent=0, min_submap_gap=1, descriptor_dim=4, backend="torch")
    assert _loop(detector, 0, 7, place, torch.zeros(2)) is None
    assert _loop(detector, 1, 7, place, torch.zeros(2)) is None  # same submap: gap 0 < 1
    with pytest.raises(ValueError, match="landmark scores"):
        _loop(detector, 2, 8, place, torch.zeros(3, 1))
    with pytest.raises(ValueError, match="check_every"):
        LoopDetector(check_every=0)
    cfg = LoopConfig(keyframe_every=3, check_every=4, max_descriptor_distance=0.1,
                     max_fallback_descriptor_distance=0.3, exclude_recent=2)
    from_cfg = LoopDetector.from_config(cfg, "dinov2", backend="torch")
    assert (from_cfg.keyframe_every, from_cfg.check_every, from_cfg.max_descriptor_distance,
            from_cfg.exclude_recent) == (3, 4, 0.1, 2)
    assert LoopDetector.from_config(cfg, "fallback", backend="torch").max_descriptor_distance == 0.3
    with pytest.raises(ValueError, match="descriptor kind"):
        LoopDetector.from_config(cfg, "netvlad")


def test_detector_compares_grown_landmark_vectors_zero_padded():
    """A class discovered later appends a score; older vectors are compared as if it scored 0 there."""
    place = torch.ones(4)
    detector = LoopDetector(check_every=3, exclude_recent=0, descriptor_dim=4, backend="torch")
    _loop(detector, 0, 0, place, torch.tensor([1.0, 2.0]))
    _loop(detector, 1, 0, place, torch.tensor([1.0, 2.5]))
    loop = _loop(detector, 2, 0, place, torch.tensor([1.0, 2.0, 3.0]))
    assert loop is not None and loop.match_keyframe == 0
    assert loop.landmark_distance == pytest.approx(3.0)


def test_observed_gaussians_in_view_and_unoccluded():
    camera = PinholeCamera(10.0, 10.0, 5.0, 5.0, 10, 10)
    depth = torch.full((10, 10), 2.0)
    depth[0, 0] = 0.0  # no reading at the top-left pixel
    means = torch.tensor([[0.0, 0.0, 1.0],  # in front of the surface
                          [0.0, 0.0, 2.05],  # on it (within the margin)
                          [0.0, 0.0, 3.0],  # behind it: occluded
                          [0.0, 0.0, -1.0],  # behind the camera
                          [2.0, 0.0, 1.0],  # outside the image
                          [-0.45, -0.45, 1.0]])  # on the pixel without depth
    seen = observed_gaussians(means, torch.eye(4), camera, depth, margin=0.1)
    assert seen.tolist() == [True, True, False, False, False, False]
    moved = torch.eye(4)
    moved[2, 3] = -1.0  # the camera steps back 1 m: the first point is now 2 m away, still in front
    assert observed_gaussians(means, moved, camera, depth, margin=0.1).tolist()[:3] == [True, False, False]


def test_database_leaves_the_thread_count_of_torch_alone():
    # FAISS and torch share the OpenMP runtime: a FAISS thread setting would silently slow every later render
    pytest.importorskip("faiss")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        DescriptorDatabase(8, "faiss").add(0, torch.ones(8))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_detector_without_classes_keeps_descriptor_order_and_ranks_at_most_max_candidates():
    """One class: landmark vectors say nothing, the closest descriptor comes first; the ranked candidates are cut at
    max_candidates (the bag of words' caller verifies them in that order)."""
    g = torch.Generator().manual_seed(4)
    place = _unit(torch.randn(8, generator=g))
    detector = LoopDetector(check_every=1, max_descriptor_distance=0.5, exclude_recent=0, descriptor_dim=8,
                            backend="torch", max_candidates=2)
    for kf, noise in enumerate([0.3, 0.1, 0.2, 2.0]):  # keyframe 1 is the closest, 3 the farthest
        _loop(detector, kf, 0, _unit(place + noise * _unit(torch.randn(8, generator=g))),
              torch.tensor([float(kf)]))  # one class: differing scores must not re-rank
    ranked = detector.add_keyframe(PlaceSignature(4, 1, place, torch.tensor([0.0])))
    assert [(c.query_keyframe, c.match_keyframe) for c in ranked] == [(4, 1), (4, 2)]  # keyframe 0 cut off
    assert ranked[0].descriptor_distance < ranked[1].descriptor_distance
    assert detector.detections[-4:] == [(4, 1), (4, 2), (4, 0), (4, 3)]  # all detected (the protocol scores them)


class _GivenSimilarities:
    """A place database whose stored keyframes have given similarities to any query (distance = 1 - similarity)."""

    def __init__(self, similarity: dict[int, float]):
        self.similarity, self._ids = similarity, []

    @property
    def ids(self) -> np.ndarray:
        return np.array(self._ids, np.int64)

    def __len__(self) -> int:
        return len(self._ids)

    def add(self, keyframe_id: int, appearance) -> None:
        self._ids.append(keyframe_id)

    def search(self, appearance, k=None, exclude_recent: int = 0):
        ids = sorted(self._ids[:len(self._ids) - exclude_recent], key=lambda i: -self.similarity.get(i, 0.0))[:k]
        return np.array(ids, np.int64), np.array([1.0 - self.similarity.get(i, 0.0) for i in ids], np.float32)


@pytest.mark.parametrize("min_relative, expected", [(0.75, [1, 0]), (0.0, [2, 3, 1])])
def test_only_keyframes_near_the_best_similarity_enter_the_landmark_ranking(min_relative, expected):
    """Bag-of-words scores pass min_score for much of a room: keyframes 0 and 1 share the query's words (0.40, 0.32),
    2 and 3 hardly (0.20, 0.10) but have the closest landmark vectors. Within 0.75 of the best score only 0 and 1 are
    candidates, ranked by their landmarks; without the relative cut the landmarks put 2 and 3 first."""
    detector = LoopDetector(check_every=1, max_descriptor_distance=0.95, exclude_recent=0, max_candidates=3,
                            database=_GivenSimilarities({0: 0.40, 1: 0.32, 2: 0.20, 3: 0.10, 4: 0.0}),
                            min_relative_similarity=min_relative)
    for kf, landmark in enumerate([4.0, 3.0, 1.0, 2.0]):  # distance to the query's vector: 4, 3, 1, 2
        detector.add_keyframe(PlaceSignature(kf, 0, torch.zeros(1), torch.tensor([landmark, 0.0])), check=False)
    ranked = detector.add_keyframe(PlaceSignature(4, 1, torch.zeros(1), torch.tensor([0.0, 0.0])))
    assert [c.match_keyframe for c in ranked] == expected
    with pytest.raises(ValueError, match="min_relative_similarity must lie in"):
        LoopDetector(min_relative_similarity=1.5)


def test_detector_from_config_with_the_bag_of_words_and_a_mismatched_signature():
    """"bow": a bag-of-words database whose bow.candidates best are ranked; a global descriptor is refused clearly
    (and so are ORB features by a descriptor database), before anything is stored."""
    from gausem_core.slam.features import OrbFeatures
    from gausem_core.slam.loop.words import BagOfWords
    cfg = LoopConfig()
    bow = LoopDetector.from_config(cfg, "bow")
    assert isinstance(bow.database, BagOfWords) and bow.max_candidates == cfg.bow.candidates
    with pytest.raises(ValueError, match="described by Tensor, but the database is a BagOfWords"):
        bow.add_keyframe(PlaceSignature(0, 0, torch.ones(384), torch.ones(2)))
    features = OrbFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32), 1)
    descriptors = LoopDetector.from_config(cfg, "fallback", backend="torch")
    assert descriptors.max_candidates == 1
    with pytest.raises(ValueError, match="described by OrbFeatures, but the database is a DescriptorDatabase"):
        descriptors.add_keyframe(PlaceSignature(0, 0, features, torch.ones(2)))
    assert len(bow.database) == len(descriptors.database) == 0


def test_a_loop_keyframe_is_described_from_one_read_of_a_submap_the_tracker_is_growing():
    """``worker.mode: async``: the worker describes a keyframe while the tracker adds Gaussians to the submap; the
    landmark scores come from one read of its Gaussians (two reads of different sizes broke the worker)."""
    from gausem_core.config import load_config
    from gausem_core.data import open_dataset
    from gausem_core.gaussians import GaussianCloud
    from gausem_core.pipeline import Pipeline
    from gausem_core.slam.system import GauSemSLAM

    cfg = load_config("params/synthetic.yaml", {"device": "cpu", "mapping.init_iterations": 5})
    dataset = open_dataset("synthetic", size=(40, 30), max_frames=1)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    slam.process(pipeline.observation(dataset[0]))
    submap, keyframe = slam.active, slam.active.keyframes[0]

    class Growing:
        """The submap, its Gaussians one copy more at every read (as if the tracker grew it in between)."""

        def __init__(self):
            self.reads = 0

        def __getattr__(self, name):
            return getattr(submap, name)

        @property
        def cloud(self):
            self.reads += 1
            return GaussianCloud.cat([submap.cloud] * self.reads)
    loop_closure = slam.back_end.loop_closure
    still = loop_closure.describe([], submap, keyframe)
    growing = loop_closure.describe([], Growing(), keyframe)
    assert still is not None and growing is not None
    assert torch.equal(growing.landmark_scores, still.landmark_scores) and still.landmark_scores.abs().sum() > 0
