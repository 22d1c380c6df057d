"""SGR: coarse step (Eq. 5: descriptor pairs, chordal-mean init, Gauss-Newton on SE(3)), fine step (Eq. 6), the
combined registration and the keyframe-pair alignment of intra-submap loops."""
import math

import pytest
import torch

from gausem_core.config import RegistrationConfig
from gausem_core.geometry import invert_pose, make_pose, se3_exp, se3_log, so3_exp
from gausem_core.semantics.descriptors import make_descriptor
from gausem_core.slam.registration import (FeatureProjection, align_keyframes, chordal_mean_alignment,
                                           coarse_registration, consistent_pairs, fine_registration,
                                           gauss_newton_alignment, is_acceptable, semantic_guided_registration,
                                           top_k_descriptor_pairs)
from loop_scene import frame, make_submap, perturbation, pose_error


def _known_transform():
    """30 degrees about a tilted axis, 1 m translation."""
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    return make_pose(so3_exp(math.radians(30) * axis / axis.norm()),
                     torch.tensor([0.6, -0.48, 0.64], dtype=torch.float64))


def _random_poses(n, g):
    return se3_exp(torch.cat([torch.randn(n, 3, generator=g, dtype=torch.float64),
                              0.8 * torch.randn(n, 3, generator=g, dtype=torch.float64)], 1))


def _noise(n, sigma, g):
    return se3_exp(sigma * torch.randn(n, 6, generator=g, dtype=torch.float64))


def _error(a, b):
    return float(se3_log(invert_pose(a) @ b).norm())


def test_gauss_newton_recovers_known_transform_exactly():
    g = torch.Generator().manual_seed(0)
    T = _known_transform()
    src = _random_poses(10, g)
    tgt = T @ src
    assert _error(chordal_mean_alignment(src, tgt), T) < 1e-9
    est, rms, iterations = gauss_newton_alignment(src, tgt, init=torch.eye(4, dtype=torch.float64))
    assert _error(est, T) < 1e-8 and rms < 1e-8
    assert iterations <= 8


def test_gauss_newton_noisy_pairs_and_wrong_init():
    g = torch.Generator().manual_seed(1)
    T = _known_transform()
    src = _random_poses(10, g)
    tgt = T @ src @ _noise(10, 5e-4, g)
    init = chordal_mean_alignment(src, tgt)
    est, rms, iterations = gauss_newton_alignment(src, tgt)
    assert _error(est, T) < 1e-3 and iterations <= 8
    # a wrong coarse init (60 degrees and 2 m off) converges to the same minimum
    wrong = se3_exp(torch.tensor([1.5, -1.0, 0.8, 0.0, 0.0, math.radians(60)], dtype=torch.float64)) @ T
    est_wrong, rms_wrong, _ = gauss_newton_alignment(src, tgt, init=wrong)
    assert _error(est_wrong, est) < 1e-9 and rms_wrong == pytest.approx(rms, rel=1e-9)
    # GN minimises Eq. 5: no better than the chordal init would be a failure; small perturbations only increase it
    residual = lambda X: float(se3_log(invert_pose(tgt) @ X @ src).pow(2).sum())  # noqa: E731
    assert residual(est) <= residual(init)
    for step in 1e-4 * torch.eye(6, dtype=torch.float64):
        assert residual(se3_exp(step) @ est) > residual(est) and residual(se3_exp(-step) @ est) > residual(est)
    assert est.dtype == torch.float64
    est32, _, _ = gauss_newton_alignment(src.float(), tgt.float())
    assert est32.dtype == torch.float32 and _error(est32.double(), est) < 1e-5


def test_top_k_descriptor_pairs_hand_example():
    source = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    target = torch.tensor([[0.0, 1.0], [3.0, 0.1], [1.0, 1.0]])
    pairs, dist = top_k_descriptor_pairs(source, target, k=3)
    assert pairs.tolist() == [[1, 0], [0, 1], [0, 2]]  # distances 0, ~0.033, ~0.765 (normalised descriptors)
    assert dist[0] == pytest.approx(0.0) and dist[2] == pytest.approx(math.sqrt(2 - math.sqrt(2)))
    assert top_k_descriptor_pairs(source, target, k=100)[0].shape == (6, 2)


def test_coarse_registration_uses_matching_keyframes_only():
    """Target submap: 12 keyframes at the source viewpoints (mapped by T) and 8 unrelated ones with other
    descriptors; the matched pairs must be the true ones and T recovered."""
    g = torch.Generator().manual_seed(2)
    T = _known_transform()
    src_poses = _random_poses(12, g)
    src_desc = torch.randn(12, 32, generator=g, dtype=torch.float64)
    tgt_poses = torch.cat([_random_poses(8, g), T @ src_poses @ _noise(12, 2e-4, g)])
    tgt_desc = torch.cat([torch.randn(8, 32, generator=g, dtype=torch.float64),
                          src_desc + 0.05 * torch.randn(12, 32, generator=g, dtype=torch.float64)])
    result = coarse_registration(src_desc, src_poses, tgt_desc, tgt_poses, k=10)
    assert result.pairs.shape == (10, 2)
    assert (result.pairs[:, 1] - 8 == result.pairs[:, 0]).all()
    assert _error(result.transform, T) < 1e-3 and result.rms < 2e-3 and result.iterations <= 8


def test_registration_rejects_bad_input():
    poses = torch.eye(4).expand(3, 4, 4)
    with pytest.raises(ValueError, match="equal length"):
        gauss_newton_alignment(poses, poses[:2])
    with pytest.raises(ValueError, match="non-finite"):
        chordal_mean_alignment(poses * float("nan"), poses)
    with pytest.raises(ValueError, match="counts differ"):
        coarse_registration(torch.randn(2, 4), poses, torch.randn(3, 4), poses)
    with pytest.raises(ValueError, match="k must be positive"):
        top_k_descriptor_pairs(torch.randn(2, 4), torch.randn(3, 4), k=0)


# --- fine step (Eq. 6) and the combined registration on a synthetic scene ------------------------------------------
def _overlapping_submaps():
    """Target over frames 0-18, source over frames 9-27 of the loop sequence, each in its own (true) frame."""
    target = make_submap(0, [0, 6, 12, 18])
    source = make_submap(1, [9, 15, 21, 27])
    truth = (invert_pose(target.anchor) @ source.anchor).double()
    poses = torch.stack([kf.cam_to_world for kf in source.keyframes])
    return source, target, truth, poses


@pytest.mark.parametrize("seed", [0, 1])
def test_fine_step_recovers_a_perturbed_submap_transform(seed):
    source, target, truth, poses = _overlapping_submaps()
    cfg = RegistrationConfig()
    init = perturbation(0.06, 4.0, seed) @ truth
    fine = fine_registration(source.cloud, target.cloud, poses, source.keyframes[0].obs.camera, init, cfg,
                             make_descriptor("fallback"), backend="torch")
    translation, rotation = pose_error(fine.transform, truth)
    assert translation < 0.025 and rotation < 1.0  # from 6 cm and 4 degrees
    assert fine.views == 4 and fine.fitness > 0.7 and is_acceptable(fine, cfg)
    at_init = fine_registration(source.cloud, target.cloud, poses, source.keyframes[0].obs.camera, init,
                                RegistrationConfig(iterations=0), make_descriptor("fallback"), backend="torch")
    assert at_init.fitness < fine.fitness and at_init.loss > fine.loss  # Eq. 6 (with the feature term) went down


def test_feature_projection_keeps_distances_inside_the_reference_span():
    """Six distinct 16-d features (scaled arbitrarily: they are L2-normalised) span 5 centred directions: projected on
    5 channels, distances between normalised features are kept; the maps come out at the requested size."""
    g = torch.Generator().manual_seed(0)
    codes = torch.randn(6, 16, generator=g, dtype=torch.float64)
    reference = codes[torch.randint(0, 6, (2, 4, 5), generator=g)] * torch.rand(2, 4, 5, 1, generator=g) * 50
    projection = FeatureProjection(reference, channels=5)
    projected = projection(reference[0], (4, 5))
    assert projected.shape == (4, 5, 5)
    unit = torch.nn.functional.normalize(reference[0], dim=-1).reshape(-1, 16)
    assert torch.allclose(torch.cdist(projected.reshape(-1, 5), projected.reshape(-1, 5)), torch.cdist(unit, unit),
                          atol=1e-9)
    assert projection(reference[1], (8, 10)).shape == (8, 10, 5)


def test_the_feature_term_is_in_the_fine_step_solve():
    """Same start, feature term on or off (lambda_feat 0): different Gauss-Newton paths, both converge."""
    source, target, truth, poses = _overlapping_submaps()
    init = perturbation(0.04, 3.0, 0) @ truth
    results = [fine_registration(source.cloud, target.cloud, poses[:2], source.keyframes[0].obs.camera, init,
                                 RegistrationConfig(lambda_feat=weight), make_descriptor("fallback"), backend="torch")
               for weight in (0.5, 0.0)]
    assert not torch.allclose(results[0].transform, results[1].transform, atol=1e-6)
    for fine in results:
        translation, rotation = pose_error(fine.transform, truth)
        assert translation < 0.025 and rotation < 1.0


def test_fine_step_rejects_a_far_initial_guess():
    source, target, truth, poses = _overlapping_submaps()
    cfg = RegistrationConfig()
    init = perturbation(0.5, 25.0, 3) @ truth
    fine = fine_registration(source.cloud, target.cloud, poses[:2], source.keyframes[0].obs.camera, init, cfg,
                             backend="torch")
    assert not is_acceptable(fine, cfg)


def test_fine_step_starts_from_the_alternative_the_views_agree_with():
    """A far initial guess (as a misled coarse step gives) and a near alternative (as the anchors give): the fine step
    refines the near one, whichever order they come in."""
    source, target, truth, poses = _overlapping_submaps()
    cfg = RegistrationConfig()
    far, near = perturbation(0.5, 25.0, 3) @ truth, perturbation(0.05, 3.0, 1) @ truth
    camera = source.keyframes[0].obs.camera
    for init, alternative in ((far, near), (near, far)):
        fine = fine_registration(source.cloud, target.cloud, poses[:2], camera, init, cfg, backend="torch",
                                 alternatives=[alternative])
        translation, rotation = pose_error(fine.transform, truth)
        assert translation < 0.025 and rotation < 1.0 and is_acceptable(fine, cfg)


def test_semantic_guided_registration_coarse_then_fine():
    """Keyframe descriptors pair source views with similar target views (closer than the loop threshold); Eq. 5 on
    their poses lands within reach of the fine step, which recovers the transform. A seed pair leads the coarse
    step."""
    source, target, truth, _ = _overlapping_submaps()
    describe = make_descriptor("fallback")
    descriptors = [torch.stack([torch.from_numpy(describe.describe(kf.obs.semantic)) for kf in s.keyframes])
                   for s in (source, target)]
    poses = [torch.stack([kf.cam_to_world for kf in s.keyframes]).double() for s in (source, target)]
    for loop_pair in (None, (1, 2)):
        reg = semantic_guided_registration(source.cloud, poses[0], descriptors[0], target.cloud, poses[1],
                                           descriptors[1], source.keyframes[0].obs.camera, RegistrationConfig(),
                                           describe, "torch", max_pair_distance=0.35, loop_pair=loop_pair)
        translation, rotation = pose_error(reg.transform, truth)
        assert translation < 0.025 and rotation < 1.0
        assert reg.coarse.pairs[0].tolist() == [1, 2]  # the closest pair, and the seed
        assert reg.accepted and reg.seconds_coarse > 0 and reg.seconds_fine > 0
        floors = RegistrationConfig()
        assert reg.sigmas[0] >= floors.sigma_rotation and reg.sigmas[1] >= floors.sigma_translation


def test_align_keyframes_measures_the_relative_pose_of_two_views():
    (ref, ref_pose), (cur, cur_pose) = frame(30), frame(36)
    truth = invert_pose(cur_pose) @ ref_pose  # current-from-reference
    init = perturbation(0.05, 3.0, 4).float() @ truth
    motion, (overlap, fitness) = align_keyframes(ref, cur, init, RegistrationConfig(pyramid_levels=3))
    translation, rotation = pose_error(motion, truth)
    assert translation < 0.01 and rotation < 0.3
    assert 0.7 < overlap < 0.95  # the rest left the view ...
    assert fitness > 0.95  # ... and what stayed agrees in depth
    _, (overlap_far, fitness_far) = align_keyframes(ref, frame(120)[0], init, RegistrationConfig(pyramid_levels=3))
    assert overlap_far * fitness_far < 0.5 * overlap * fitness  # another place: little agreement near the guess


def test_consistent_pairs_drop_look_alike_views_of_other_places():
    g = torch.Generator().manual_seed(5)
    T = _known_transform()
    src = _random_poses(6, g)
    tgt = T @ src @ _noise(6, 1e-3, g)
    tgt[1] = _known_transform() @ tgt[1]  # pair 1 and 4 match views of other places
    tgt[4] = se3_exp(torch.tensor([2.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)) @ tgt[4]
    keep = consistent_pairs(src, tgt, 0.05, math.radians(2.0))
    assert keep.tolist() == [0, 2, 3, 5]
    est, _, _ = gauss_newton_alignment(src[keep], tgt[keep])
    assert _error(est, T) < 5e-3
    # with a seed, the pairs that agree with it (here a look-alike: only itself)
    assert consistent_pairs(src, tgt, 0.05, math.radians(2.0), reference=4).tolist() == [4]
