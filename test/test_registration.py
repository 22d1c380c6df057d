"""SGR coarse step (Eq. 5): descriptor pairs, chordal-mean init, Gauss-Newton on SE(3)."""
import math

import pytest
import torch

from gausem_core.geometry import invert_pose, make_pose, se3_exp, se3_log, so3_exp
from gausem_core.slam.registration import (chordal_mean_alignment, coarse_registration, gauss_newton_alignment,
                                           top_k_descriptor_pairs)


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
