"""The loop-closure orchestrator on hand-made submaps: inter-submap loops (SGR, anchor graph, rigid correction),
intra-submap loops (keyframe-pair registration, keyframe graph, re-mapping), switches and the learned palette."""
import dataclasses

import pytest
import torch

from gausem_core.config import LoopConfig, MappingConfig, RegistrationConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose
from gausem_core.slam.loop import LoopDetector
from gausem_core.slam.mapper import Mapper
from loop_scene import PALETTE, frame, make_submap, perturbation, pose_error

pytest.importorskip("gtsam")
from gausem_core.slam.loop_closure import LoopClosure, SemanticPalette  # noqa: E402


def _closure(**overrides) -> LoopClosure:
    cfg = LoopConfig(**{"check_every": 1, "max_fallback_descriptor_distance": 0.45, **overrides})
    return LoopClosure(cfg, Mapper(MappingConfig()), backend="torch", database_backend="torch")


def _feed(closure, submaps):
    for submap in submaps:
        for kf in submap.keyframes:
            closure.on_keyframe(submaps, submap, kf)


def test_inter_submap_loop_moves_the_drifted_submap_rigidly():
    """Submap 0 starts the loop; submap 1 ends it with a drifted anchor. Its last keyframe revisits frame 0 (found
    by the paper's descriptor of the semantic image; the bag of words finds it one keyframe earlier)."""
    first = make_submap(0, list(range(0, 50, 5)))
    truth = frame(330)[1]
    last = make_submap(1, list(range(330, 360, 5)), anchor=perturbation(0.08, 3.0, 1).float() @ truth)
    old_anchor = last.anchor.clone()
    world_poses = torch.stack([last.world_pose(kf) for kf in last.keyframes])
    local_means = last.cloud.means.clone()
    closure = _closure(place_recognition="descriptor")
    _feed(closure, [first, last])
    closed = closure.loops
    assert [(r.query_frame, r.match_frame, r.intra) for r in closed] == [(355, 0, False)]
    assert closed[0].fitness > 0.9
    before, after = pose_error(old_anchor, truth), pose_error(last.anchor, truth)
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]
    assert pose_error(first.anchor, frame(0)[1]) == pytest.approx((0.0, 0.0), abs=1e-5)  # the graph's prior
    # rigid correction: world keyframe poses and centres move by C = A' A^-1, the submap-frame data stay as they were
    correction = last.anchor @ invert_pose(old_anchor)
    moved = torch.stack([last.world_pose(kf) for kf in last.keyframes])
    torch.testing.assert_close(moved, correction @ world_poses, atol=1e-5, rtol=0)
    torch.testing.assert_close(last.cloud.transformed(last.anchor).means,
                               last.cloud.transformed(old_anchor).transformed(correction).means, atol=1e-4, rtol=0)
    assert torch.equal(last.cloud.means, local_means)


def test_a_revisit_in_the_last_keyframes_is_closed_at_the_end():
    """The revisit of frame 0 at the end of the loop falls between the checks (every 7th loop keyframe: frames 30
    and 345); checking the keyframes whose turn never came, at the end of the run, closes it."""
    first = make_submap(0, list(range(0, 50, 5)))
    truth = frame(330)[1]
    last = make_submap(1, list(range(330, 360, 5)), anchor=perturbation(0.08, 3.0, 1).float() @ truth)
    closure = _closure(check_every=7)
    _feed(closure, [first, last])
    assert closure.records == [] and closure.detector.unchecked == [350, 355]
    outcome = closure.check_unchecked([first, last])
    assert outcome is not None and outcome.constraint is not None and outcome.correction.anchors >= 1
    assert [(r.query_frame, r.match_frame, r.accepted) for r in closure.records] == [(350, 0, True)]
    assert pose_error(last.anchor, truth)[0] < 0.5 * 0.08
    assert closure.check_unchecked([first, last]) is None and len(closure.records) == 1  # nothing left to check


def test_proximity_finds_the_revisit_the_descriptor_misses():
    """With a descriptor threshold nothing passes and checks that never come, only keyframes near in the (drifted)
    pose estimate are candidates: the revisit is found, registered from the current anchors and closed."""
    truth = frame(330)[1]
    results = []
    for radius in (0.0, 0.5):
        first = make_submap(0, list(range(0, 50, 5)))
        last = make_submap(1, list(range(330, 360, 5)), anchor=perturbation(0.08, 3.0, 1).float() @ truth)
        closure = _closure(check_every=100, max_fallback_descriptor_distance=1e-6, proximity_radius=radius)
        _feed(closure, [first, last])
        results.append((closure, last))
    assert results[0][0].records == []
    closure, last = results[1]
    assert closure.loops and all(r.match_frame <= 10 and r.query_frame >= 345 for r in closure.records)
    assert pose_error(last.anchor, truth)[0] < 0.5 * 0.08


def test_intra_submap_loop_pulls_drifted_keyframes_back():
    """One submap: out along frames 0..36, back along 30..0 with growing drift; the way back revisits the way out."""
    frames = [0, 6, 12, 18, 24, 30, 36, 30, 24, 18, 12, 6, 0]
    submap = make_submap(0, frames, ids=list(range(0, 5 * len(frames), 5)), size=(80, 60))
    truth = [kf.cam_to_world.clone() for kf in submap.keyframes]
    drift = torch.eye(4)
    for kf in submap.keyframes[7:]:
        drift = drift @ perturbation(0.01, 0.6, kf.frame_id).float()
        kf.cam_to_world = kf.cam_to_world @ drift
    before = [pose_error(kf.cam_to_world, t) for kf, t in zip(submap.keyframes, truth)]
    closure = _closure(check_every=6, max_fallback_descriptor_distance=0.2, remap_iterations_per_keyframe=1)
    gaussians = len(submap.cloud)
    _feed(closure, [submap])
    assert [(r.query_frame, r.match_frame, r.intra, r.accepted) for r in closure.records] == [(55, 5, True, True)]
    after = [pose_error(kf.cam_to_world, t) for kf, t in zip(submap.keyframes, truth)]
    assert after[0] == (0.0, 0.0)  # the fixed first keyframe
    assert after[11][0] < 0.3 * before[11][0] and after[11][1] < 0.3 * before[11][1]  # the loop keyframe
    assert sum(e[0] for e in after[7:]) < 0.5 * sum(e[0] for e in before[7:])
    assert 0 < len(submap.cloud) <= gaussians  # re-mapped (and pruned) with the corrected poses


@pytest.mark.parametrize("place_recognition", ["descriptor", "auto"])
def test_detection_in_another_process_closes_the_same_loops(place_recognition):
    """The steps of on_keyframe run apart, as the ROS nodes run them: describe here, detect in a LoopDetector of its
    own (the loop_detection node's, from the same configuration), confirm, register and correct here. The same loop
    records as on_keyframe, accepted or not (with the bag of words: verified in order, with the same inliers)."""
    def scene():
        first = make_submap(0, list(range(0, 50, 5)))
        return [first, make_submap(1, list(range(330, 360, 5)),
                                   anchor=perturbation(0.08, 3.0, 1).float() @ frame(330)[1])]

    together = _closure(place_recognition=place_recognition)
    _feed(together, scene())
    apart, submaps = _closure(place_recognition=place_recognition), scene()
    detector = LoopDetector.from_config(apart.cfg, apart.place_recognition, backend="torch")
    for submap in submaps:
        for kf in submap.keyframes:
            place = apart.describe(submaps, submap, kf)
            candidate = apart.confirm(submaps, detector.add_keyframe(place)) if place is not None else None
            outcome = apart.register(submaps, candidate) if candidate is not None else None
            if outcome is not None and outcome.constraint is not None:
                apart.correct(submaps, outcome.constraint)
    assert together.loops and len(apart.detector.database) == 0  # apart's own database was never used
    assert [dataclasses.replace(r, seconds=0.0) for r in apart.records] == \
        [dataclasses.replace(r, seconds=0.0) for r in together.records]
    assert apart.rejected_candidates == together.rejected_candidates


def test_switches_and_rejected_loops():
    first = make_submap(0, list(range(0, 50, 5)), size=(80, 60))
    last = make_submap(1, list(range(330, 360, 5)), size=(80, 60))
    disabled = _closure(enabled=False)
    _feed(disabled, [first, last])
    assert disabled.records == [] and len(disabled.detector.database) == 0
    # a loop whose registration cannot be verified is recorded but not closed
    strict = _closure(registration=RegistrationConfig(min_fitness=1.01))
    anchor = last.anchor.clone()
    _feed(strict, [first, last])
    assert strict.records and not any(r.accepted for r in strict.records) and strict.loops == []
    assert torch.equal(last.anchor, anchor)


def test_only_keyframes_on_the_loop_grid_enter_the_database():
    submap = make_submap(0, [0, 3, 6, 9, 12], size=(80, 60))
    closure = _closure(keyframe_every=6)
    _feed(closure, [submap])
    assert closure.detector.database.ids.tolist() == [0, 6, 12]


def test_semantic_palette_learns_colours_in_order():
    palette = SemanticPalette()
    palette.update(PALETTE[torch.tensor([[2, 2], [5, 2]])])
    palette.update(PALETTE[torch.tensor([[5, 7]])])
    assert len(palette) == 3
    assert {tuple(c) for c in palette.colors[:2].tolist()} == {tuple(PALETTE[2].tolist()), tuple(PALETTE[5].tolist())}
    torch.testing.assert_close(palette.colors[2], PALETTE[7])
    cloud = GaussianCloud.from_points(torch.zeros(2, 3), torch.zeros(2, 3), PALETTE[[7, 2]] + 0.01, torch.ones(2))
    ids = palette.class_ids(cloud)
    torch.testing.assert_close(palette.colors[ids], PALETTE[[7, 2]])


def test_semantic_palette_learns_what_a_unique_sort_of_all_pixels_learns():
    """The keyed lookup against the unique sort it replaced: new colours in ascending (r, g, b) order, and a colour
    within 1e-4 of a known one never added (also when it comes back)."""
    g = torch.Generator().manual_seed(0)
    images = [PALETTE[torch.randint(0, classes, (6, 8), generator=g)] for classes in (3, 6, 12)]
    images.insert(1, torch.cat([images[0], (PALETTE[1] + 5e-5).expand(1, 8, 3)]))
    palette, expected = SemanticPalette(), torch.zeros(0, 3)
    for image in images + images[1:2]:
        palette.update(image)
        found = torch.unique(image.reshape(-1, 3), dim=0)
        if len(expected):
            found = found[torch.cdist(found, expected).min(1).values > 1e-4]
        expected = torch.cat([expected, found])
    assert torch.equal(palette.colors, expected) and len(palette) == 12


def test_a_loop_implying_a_jump_beyond_the_odometry_bound_is_implausible():
    """A measured relative pose may differ from the current estimate by ``max_correction_sigmas`` odometry sigmas
    (random-walk growth over the keyframes between the loop's two)."""
    closure = _closure(odometry_sigma_translation=0.01, odometry_sigma_rotation=0.01, max_correction_sigmas=4.0)
    current = torch.eye(4, dtype=torch.float64)
    shifted = current.clone()
    shifted[0, 3] = 0.05  # 5 cm: beyond 4 x 1 cm over one keyframe, within 4 x 1 cm x sqrt(4) over four
    assert closure._plausible(current, current, 1)
    assert not closure._plausible(current, shifted, 1)
    assert closure._plausible(current, shifted, 4)
    turned = current.clone()
    turned[:3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert not closure._plausible(current, turned, 4)  # 90 degrees against 4 x 0.01 x 2 rad
