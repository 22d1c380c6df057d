"""Place recognition without weights: the online binary vocabulary, the bag-of-words index, geometric verification
(a true revisit passes with its relative pose, a repeated texture elsewhere is turned down) and the loop closure's
choice of place recognition."""
import dataclasses

import numpy as np
import pytest
import torch

from gausem_core.config import BowConfig, LoopConfig, MappingConfig
from gausem_core.slam.features import extract_features, feature_pose, refine_with_depth
from gausem_core.slam.features import match_features as match_feature_pairs
from gausem_core.slam.loop.verification import verify
from gausem_core.slam.loop.words import BagOfWords, Vocabulary
from gausem_core.slam.mapper import Mapper
from loop_scene import frame, make_submap, pose_error

CFG = BowConfig()


def _features(obs):
    return extract_features(obs.rgb, obs.depth, obs.camera, CFG)


def _poster(obs, u0: int, v0: int, size: int = 48, depth: float = 1.2):
    """The observation with one textured square (the same one every call) on a plane ``depth`` metres away."""
    texture = torch.rand(size // 4, size // 4, 3, generator=torch.Generator().manual_seed(7))
    rgb, planar = obs.rgb.clone(), obs.depth.clone()
    rgb[v0:v0 + size, u0:u0 + size] = texture.repeat_interleave(4, 0).repeat_interleave(4, 1)
    planar[v0:v0 + size, u0:u0 + size] = depth
    return dataclasses.replace(obs, rgb=rgb, depth=planar)


def test_vocabulary_learns_words_online_and_quantises_without_growing():
    rng = np.random.default_rng(0)
    words = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    vocabulary = Vocabulary(radius=40)
    assert vocabulary.quantise(words, grow=True).tolist() == list(range(50))
    noisy = words.copy()
    noisy[:, 0] ^= 0b111  # 3 bits off: the same words (random words lie ~128 bits apart)
    assert vocabulary.quantise(noisy, grow=False).tolist() == list(range(50))
    unknown = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    assert vocabulary.quantise(unknown, grow=False).tolist() == [-1] * 5 and len(vocabulary) == 50
    assert vocabulary.quantise(unknown, grow=True).tolist() == list(range(50, 55))
    with pytest.raises(ValueError, match="uint8"):
        vocabulary.quantise(words.astype(np.int32), grow=False)


def test_bag_of_words_ranks_the_same_place_first_and_round_trips():
    places = [0, 60, 120, 180, 240, 300]
    bow = BagOfWords(CFG)
    for n, index in enumerate(places):
        bow.add(n, _features(frame(index)[0]))
    query = _features(frame(123)[0])  # 3 frames after place 2
    ids, distances = bow.search(query)
    assert ids[0] == 2 and 0 <= distances[0] < 1 - CFG.min_score < distances[1] <= 1
    assert np.all(np.diff(distances) >= 0)
    assert 2 not in bow.search(query, exclude_recent=4)[0]  # the newest 4 (ids 2..5) are not searched
    restored = BagOfWords(CFG)
    restored.load_state_dict(bow.state_dict())
    for got, expected in zip(restored.search(query), bow.search(query)):
        np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError, match="not larger"):
        bow.add(3, query)


def test_verification_passes_a_revisit_with_its_relative_pose():
    (query, query_pose), (match, match_pose) = frame(36), frame(30)
    result = verify(_features(query), _features(match), query, match, CFG, 0.1)
    assert result.passed and result.inliers >= CFG.min_inliers and result.fitness > 0.9
    translation, rotation = pose_error(result.relative, torch.linalg.inv(match_pose.double()) @ query_pose.double())
    assert translation < 0.05 and rotation < 1.5  # a start for registration (which converges from 8 cm, 3 deg)


def test_the_query_depth_tightens_the_feature_pose():
    """Frames 0 and 1 of the synthetic loop at 160x120: PnP from 144 inliers is 0.7 deg and 2.2 cm off the truth
    (reprojection trades a small turn for a sideways shift); the query's depth in the refinement brings it closer."""
    (current, current_pose), (previous, previous_pose) = frame(1), frame(0)
    truth = torch.linalg.inv(current_pose.double()) @ previous_pose.double()
    errors = []
    for depth_noise in (0.0, 0.01):
        found = feature_pose(_features(current), _features(previous), current.camera, CFG.match_ratio,
                             CFG.max_reprojection_error, CFG.min_inliers, depth_noise)
        errors.append(pose_error(found.query_from_match, truth))
    (translation, rotation), (translation_with_depth, rotation_with_depth) = errors
    assert translation_with_depth < 0.01 and rotation_with_depth < 0.4
    assert translation_with_depth < translation / 2 and rotation_with_depth < rotation / 2


def test_refine_with_depth_converges_with_and_without_depth():
    rng = np.random.default_rng(0)
    intrinsics = np.array([[130.0, 0, 80], [0, 130.0, 60], [0, 0, 1]])
    points = np.column_stack([rng.uniform(-1.2, 1.2, 150), rng.uniform(-0.9, 0.9, 150), rng.uniform(1.8, 2.2, 150)])
    truth = np.eye(4)
    truth[:3, 3] = [0.03, 0.0, 0.01]
    moved = points @ truth[:3, :3].T + truth[:3, 3]
    pixels = moved[:, :2] / moved[:, 2:] * 130.0 + [80, 60] + rng.normal(0, 0.3, (150, 2))
    depths = moved[:, 2] + rng.normal(0, 0.01 * moved[:, 2] ** 2 / 3)
    depths[::3] = np.nan  # no reading there
    angle = np.radians(0.7)
    start = np.eye(4)
    start[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    start[0, 3] = -np.sin(angle) * 2.0  # turned and shifted so that the points at 2 m stay where they were
    start = start @ truth
    for query_depths in (depths, np.full(150, np.nan)):
        refined = refine_with_depth(points, pixels, query_depths, intrinsics, start, depth_noise=0.01)
        translation, rotation = pose_error(torch.from_numpy(refined), torch.from_numpy(truth))
        assert translation < 0.006 and rotation < 0.15


def test_verification_finds_a_revisit_whose_matches_are_mostly_wrong():
    """Sensor noise can leave a third of the matches right (measured on the noisy loop's revisit: 21 of 66). With
    two thirds of a revisit's matches given wrong depth points, in 20 draws, the PnP RANSAC still finds the pose (EPnP's
    samples of 5, 200 of them, found it in 9 of the 20)."""
    (query, _), (match, _) = frame(36), frame(30)
    query_features, match_features = _features(query), _features(match)
    matched = match_feature_pairs(query_features, match_features, CFG.match_ratio)[:, 1]
    passed = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        points = match_features.points.copy()
        wrong = rng.choice(matched, 2 * len(matched) // 3, replace=False)
        points[wrong] = points[rng.permutation(wrong)]  # each takes another matched feature's point
        result = verify(query_features, dataclasses.replace(match_features, points=points), query, match, CFG, 0.1)
        passed += result.passed
    assert passed >= 18


def test_perceptual_aliasing_is_rejected():
    """The same poster on two walls: the bag of words ranks the other place first and PnP agrees on the poster's
    pixels, but under that pose the rest of the views disagree in depth."""
    query, elsewhere = _poster(frame(0)[0], 20, 30), _poster(frame(240)[0], 90, 50)
    bow = BagOfWords(CFG)
    for n, index in enumerate([30, 60, 90, 150, 210]):
        bow.add(n, _features(frame(index)[0]))
    bow.add(10, _features(elsewhere))
    assert bow.search(_features(query), k=1)[0].tolist() == [10]
    result = verify(_features(query), bow.features[10], query, elsewhere, CFG, 0.1)
    assert result.inliers >= CFG.min_inliers  # the poster alone makes a consistent pose ...
    assert result.fitness < CFG.min_fitness and not result.passed  # ... which the whole views refute
    # in the loop closure: the candidate is verified, turned down, and never registered
    pytest.importorskip("gtsam")
    from gausem_core.slam.loop_closure import LoopClosure
    cfg = LoopConfig(check_every=1, exclude_recent=0)
    closure = LoopClosure(cfg, Mapper(MappingConfig()), backend="torch", database_backend="torch")
    submaps = [make_submap(0, [60, 120, 180, 240], ids=[0, 5, 10, 15]), make_submap(1, [0], ids=[20])]
    submaps[0].keyframes[-1].obs, submaps[1].keyframes[0].obs = elsewhere, query
    for submap in submaps:
        for keyframe in submap.keyframes:
            closure.on_keyframe(submaps, submap, keyframe)
    assert closure.place_recognition == "bow"
    assert closure.records == [] and closure.rejected_candidates >= 1


def test_place_recognition_setting():
    def resolved(setting, kind):
        return LoopConfig(place_recognition=setting).place_recognition_for(kind)
    assert resolved("auto", "fallback") == "bow" and resolved("auto", "dinov2") == "dinov2"
    assert resolved("descriptor", "fallback") == "fallback" and resolved("bow", "dinov2") == "bow"
    with pytest.raises(ValueError, match="place_recognition"):
        resolved("orb", "fallback")
