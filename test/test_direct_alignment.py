"""Dense direct alignment (the Gauss-Newton tracker's core) on analytically ray-cast views with depth steps."""
import dataclasses

import numpy as np
import pytest
import torch

from rounding import assert_within_rounding

from gausem_core.geometry import PinholeCamera, invert_pose, se3_exp, so3_log
from gausem_core.native import kernel_available
from gausem_core.slam import direct_alignment
from gausem_core.slam.direct_alignment import (AlignmentWeights, ModelView, ObservedImages, model_samples,
                                               _normal_equations_compiled, _normal_equations_torch, align_level)

CAMERA = PinholeCamera(100.0, 100.0, 80.0, 60.0, 160, 120)


def ray_cast(cam_to_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour (H, W, 3) and depth (H, W) of a textured wall at z = 1.2 m with a box face 8 cm in front of it."""
    rays = CAMERA.pixel_rays(torch.float64)
    dirs = rays @ cam_to_world[:3, :3].T
    origin = cam_to_world[:3, 3]
    depth_along = torch.full(rays.shape[:2], float("inf"), dtype=torch.float64)
    for plane_z, half_size in [(1.2, None), (1.12, 0.2)]:
        t = (plane_z - origin[2]) / dirs[..., 2]
        hit = origin + t[..., None] * dirs
        inside = t > 0
        if half_size is not None:
            inside = inside & (hit[..., 0].abs() < half_size) & (hit[..., 1].abs() < half_size)
        depth_along = torch.where(inside & (t < depth_along), t, depth_along)
    hit = origin + depth_along[..., None] * dirs
    x, y = hit[..., 0], hit[..., 1]
    color = torch.stack([0.5 + 0.4 * torch.sin(9 * x) * torch.cos(7 * y), 0.5 + 0.4 * torch.cos(11 * x + 3 * y),
                         0.5 + 0.3 * torch.sin(13 * y - 5 * x)], -1)
    return color, depth_along * rays[..., 2]  # ray parameter -> z depth (rays have unit z)


def jitter_edges(depth: torch.Tensor) -> torch.Tensor:
    """Depth-sensor edge noise: pixels next to a depth step take their neighbour's depth at random (seeded)."""
    generator = torch.Generator().manual_seed(0)
    neighbour = torch.roll(depth, 1, 1)
    step = (neighbour - depth).abs() > 0.02
    flip = step & (torch.rand(depth.shape, generator=generator, dtype=depth.dtype) < 0.5)
    return torch.where(flip, neighbour, depth)


def align(motion_truth: torch.Tensor, weights: AlignmentWeights, features: bool = False) -> torch.Tensor:
    """Align the view at identity to the view at ``motion_truth``; with ``features``, a 2-channel feature image (a
    smooth function of the colour, like upsampled patch features) rides along as feature channels."""
    model_color, model_depth = ray_cast(torch.eye(4, dtype=torch.float64))
    observed_color, observed_depth = ray_cast(invert_pose(motion_truth))
    observed_depth = jitter_edges(observed_depth)
    model_features, observed_features = ((torch.stack([c[..., 0] - c[..., 1], c[..., 2]], -1) for c in
                                          (model_color, observed_color)) if features else (None, None))
    model = ModelView(model_color, model_color, model_depth, torch.ones_like(model_depth, dtype=torch.bool), CAMERA,
                      model_features)
    observed = ObservedImages.build(observed_color, observed_color, observed_depth, CAMERA, observed_features)
    motion, _ = align_level(model, observed, torch.eye(4, dtype=torch.float64), weights, 30)
    return motion


@pytest.fixture(params=["torch", pytest.param("compiled", marks=pytest.mark.skipif(
    not kernel_available(), reason="compiled CPU kernels unavailable"))])
def implementation(request, monkeypatch):
    """Each alignment test runs with the torch normal equations and with the compiled kernel's."""
    if request.param == "torch":
        monkeypatch.setattr(direct_alignment, "kernel_available", lambda: False)
    return request.param


MOTION = se3_exp(torch.tensor([0.004, -0.003, 0.002, 0.003, 0.004, -0.002], dtype=torch.float64))
WEIGHTS = AlignmentWeights(0.5, 0.0, 5.0, huber_delta=0.002)  # the depth term dominates, as in params/*.yaml


# the longest chain of rounded operations that makes one term of the normal equations (projection, bilinear sample,
# residual, IRLS weight, Jacobian, product): the terms' own rounding, added to the sum's
TERM_OPERATIONS = 64


def assert_normal_equations_within_rounding(sums, dtype: torch.dtype, observed: ObservedImages, motion: torch.Tensor,
                                            weights: AlignmentWeights, points: torch.Tensor, ref: torch.Tensor):
    """An implementation's ``(H, g, summed cost[, count])`` computed in ``dtype``, each entry within ``dtype``'s
    rounding of the same terms summed in float64 (the inputs widened exactly): a sum of n terms in any order, each
    made in at most ``TERM_OPERATIONS`` operations, lies within gamma(n + TERM_OPERATIONS) * sum|term|. The count
    of valid points, where given, is exact."""
    wide = ObservedImages(observed.samples.double(), observed.camera)
    terms = direct_alignment.alignment_terms(wide, motion.double(), weights, points.double(), ref.double())
    jacobian, residual = terms.jacobian.reshape(-1, 6), terms.residual.reshape(-1)
    weighted = (terms.jacobian * terms.weight[..., None]).reshape(-1, 6)  # IRLS weights are never negative
    h, g, cost, *count = sums
    operations = len(residual) + TERM_OPERATIONS
    assert [int(c) for c in count] == [int(terms.valid.sum())] * len(count)
    assert_within_rounding(h, weighted.T @ jacobian, weighted.abs().T @ jacobian.abs(), operations, dtype, "H")
    assert_within_rounding(g, weighted.T @ residual, weighted.abs().T @ residual.abs(), operations, dtype, "g")
    assert_within_rounding(cost, terms.cost.sum(), terms.cost.sum(), len(points) + TERM_OPERATIONS, dtype, "cost")


def test_depth_steps_do_not_bias_the_alignment(implementation):
    error = invert_pose(MOTION) @ align(MOTION, WEIGHTS)
    assert error[:3, 3].norm() < 5e-4
    assert np.degrees(float(so3_log(error[:3, :3]).norm())) < 0.05


def test_the_depth_step_mask_is_what_keeps_the_alignment_unbiased(implementation):
    unmasked = dataclasses.replace(WEIGHTS, max_depth_slope=float("inf"))
    errors = [float((invert_pose(MOTION) @ align(MOTION, w))[:3, 3].norm()) for w in (WEIGHTS, unmasked)]
    assert errors[0] < 0.5 * errors[1]


def test_feature_channels_alone_recover_the_motion(implementation):
    """Colour, semantics and depth weighted zero: the feature residuals carry the whole solve."""
    features_only = AlignmentWeights(0.0, 0.0, 0.0, huber_delta=0.002, feature=1.0)
    error = invert_pose(MOTION) @ align(MOTION, features_only, features=True)
    assert error[:3, 3].norm() < 1e-3
    assert np.degrees(float(so3_log(error[:3, :3]).norm())) < 0.1
    unaligned = invert_pose(MOTION)
    assert error[:3, 3].norm() < 0.2 * unaligned[:3, 3].norm()


def test_feature_channels_survive_the_pyramid_and_must_match_the_model():
    color, depth = ray_cast(torch.eye(4, dtype=torch.float64))
    observed = ObservedImages.build(color, color, depth, CAMERA, color[..., :2])
    half = observed.downsampled()
    assert observed.feature_channels == half.feature_channels == 2 and half.stack.shape[1:] == (60, 80)
    assert torch.allclose(half.stack[7:], torch.nn.functional.avg_pool2d(color[None, ..., :2].permute(0, 3, 1, 2),
                                                                         2)[0])
    model = ModelView(color, color, depth, depth > 0, CAMERA)  # no features
    with pytest.raises(ValueError, match="0 feature channels, the observation 2"):
        align_level(model, observed, torch.eye(4, dtype=torch.float64), AlignmentWeights(1.0, 0.0, 1.0), 1)


@pytest.mark.parametrize("size, levels, coarsest_width, widths", [
    ((160, 120), 2, 80, [160, 80]),  # the shipped parameters at the tuned size: the minimum count
    ((640, 480), 2, 80, [640, 320, 160, 80]),  # larger frames: halved down to the same coarsest width
    ((320, 240), 3, 80, [320, 160, 80]),
    ((80, 60), 2, 80, [80, 40]),  # smaller ones keep the minimum count
    ((6, 4), 5, 1, [6, 3, 1]),  # never below a pixel
])
def test_the_pyramid_keeps_the_coarsest_level_about_the_same_width_at_any_size(size, levels, coarsest_width, widths):
    camera = CAMERA.scaled(*size)
    images = ObservedImages.build(torch.rand(size[1], size[0], 3), torch.rand(size[1], size[0], 3),
                                  torch.ones(size[1], size[0]), camera)
    pyramid = images.pyramid(levels, coarsest_width)
    assert [level.camera.width for level in pyramid] == widths
    assert [tuple(level.stack.shape[1:]) for level in pyramid] == [(level.camera.height, level.camera.width)
                                                                   for level in pyramid]


@pytest.mark.skipif(not kernel_available(), reason="compiled CPU kernels unavailable")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_normal_equations_are_the_torch_ones(dtype):
    """Same H, g and cost from both implementations (each within its rounding of the float64 sums), with feature
    channels, model points that leave the view, occlusions (depth residuals beyond the limit) and depth steps;
    neither solves for a view behind the camera."""
    model_color, model_depth = ray_cast(torch.eye(4, dtype=torch.float64))
    observed_color, observed_depth = ray_cast(invert_pose(MOTION))
    features = [torch.stack([c[..., 0] - c[..., 1], c[..., 2]], -1).to(dtype) for c in (model_color, observed_color)]
    model_depth = model_depth.clone()
    model_depth[40:50, 20:30] += 0.3  # occluded in the observation
    model = ModelView(model_color.to(dtype), model_color.flip(-1).to(dtype), model_depth.to(dtype),
                      torch.ones_like(model_depth, dtype=torch.bool), CAMERA, features[0])
    observed = ObservedImages.build(observed_color.to(dtype), observed_color.flip(-1).to(dtype),
                                    jitter_edges(observed_depth).to(dtype), CAMERA, features[1])
    weights = AlignmentWeights(0.5, 0.3, 5.0, huber_delta=0.002, feature=0.7)
    points, ref = model_samples(model, observed)
    for twist in ([0.004, -0.003, 0.002, 0.003, 0.004, -0.002], [0.5, 0.1, 0.0, 0.0, 0.0, 0.0]):  # a third out of view
        motion = se3_exp(torch.tensor(twist, dtype=torch.float64)).to(dtype)
        args = (observed, motion, weights, points, ref)
        for implementation in (_normal_equations_compiled, _normal_equations_torch):
            h, g, mean_cost = implementation(*args)
            assert_normal_equations_within_rounding((h, g, mean_cost * len(points)), dtype, *args)
    behind = se3_exp(torch.tensor([0.0, 0.0, -3.0, 0.0, 0.0, 0.0], dtype=torch.float64)).to(dtype)
    assert _normal_equations_compiled(observed, behind, weights, points, ref) is None
    assert _normal_equations_torch(observed, behind, weights, points, ref) is None


@pytest.mark.skipif(not kernel_available(), reason="compiled CPU kernels unavailable")
def test_the_compiled_level_takes_the_torch_loops_steps(monkeypatch):
    """align_level on CPU runs its loop in the compiled kernel: the same motion and cost as the torch loop (float64)
    when it runs all its iterations, stops at a small step, and makes no step for a view behind the camera."""
    model_color, model_depth = ray_cast(torch.eye(4, dtype=torch.float64))
    observed_color, observed_depth = ray_cast(invert_pose(MOTION))
    model = ModelView(model_color, model_color.flip(-1), model_depth, torch.ones_like(model_depth, dtype=torch.bool),
                      CAMERA)
    observed = ObservedImages.build(observed_color, observed_color.flip(-1), jitter_edges(observed_depth), CAMERA)
    weights = AlignmentWeights(0.5, 0.3, 5.0, huber_delta=0.002)
    eye = torch.eye(4, dtype=torch.float64)
    behind = se3_exp(torch.tensor([0.0, 0.0, -3.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    cases = [(eye, 6, 0.0), (eye, 30, 1e-2), (behind, 5, 0.0)]
    compiled = [align_level(model, observed, start, weights, steps, min_step=small) for start, steps, small in cases]
    monkeypatch.setattr(direct_alignment, "kernel_available", lambda: False)
    reference = [align_level(model, observed, start, weights, steps, min_step=small) for start, steps, small in cases]
    for (motion, cost), (motion_ref, cost_ref) in zip(compiled[:2], reference[:2]):
        assert torch.allclose(motion, motion_ref, atol=1e-9)
        assert cost == pytest.approx(cost_ref, rel=1e-9)
    assert not torch.allclose(compiled[0][0], compiled[1][0], atol=1e-6)  # the small step stopped the second early
    assert torch.equal(compiled[2][0], behind) and np.isnan(compiled[2][1]) and np.isnan(reference[2][1])


def test_compared_costs_leave_out_the_points_that_leave_the_view(monkeypatch):
    """Two motions compared over the model points inside the image under both: where every point stays inside they
    are alignment_cost's; with the whole view (its border leaves the image under a motion) fewer points count, and
    the true motion still costs less than none."""
    model_color, model_depth = ray_cast(torch.eye(4, dtype=torch.float64))
    observed_color, observed_depth = ray_cast(invert_pose(MOTION))
    observed = ObservedImages.build(observed_color, observed_color, observed_depth, CAMERA)
    centre = torch.zeros_like(model_depth, dtype=torch.bool)
    centre[30:90, 40:120] = True
    eye = torch.eye(4, dtype=torch.float64)
    inner = ModelView(model_color, model_color, model_depth, centre, CAMERA)
    assert direct_alignment.compared_costs(inner, observed, [MOTION, eye], WEIGHTS) == pytest.approx(
        [direct_alignment.alignment_cost(inner, observed, m, WEIGHTS) for m in (MOTION, eye)], rel=1e-12)
    whole = ModelView(model_color, model_color, model_depth, torch.ones_like(centre), CAMERA)
    counted, normal_equations = [], direct_alignment.normal_equations
    monkeypatch.setattr(direct_alignment, "normal_equations",
                        lambda observed, motion, weights, points, ref: counted.append(len(points)) or normal_equations(
                            observed, motion, weights, points, ref))
    true_cost, no_motion_cost = direct_alignment.compared_costs(whole, observed, [MOTION, eye], WEIGHTS)
    assert counted[0] == counted[1] < CAMERA.width * CAMERA.height
    assert true_cost < no_motion_cost
