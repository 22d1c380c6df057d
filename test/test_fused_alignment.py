"""The fused alignment step (one Triton kernel) computes the torch reference's normal equations: on the CPU through
Triton's interpreter (test/conftest.py sets it without CUDA), on CUDA compiled."""
import dataclasses

import pytest
import torch
from test_direct_alignment import CAMERA, MOTION, WEIGHTS, jitter_edges, ray_cast

from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.slam import direct_alignment
from gausem_core.slam.device_alignment import align_level_on_device

pytest.importorskip("triton")
from gausem_core.slam import fused_alignment  # noqa: E402  (after the skip: it imports Triton)

MOTIONS = [torch.eye(4), se3_exp(torch.tensor([0.01, -0.02, 0.01, 0.02, -0.01, 0.01]))]


def level(features: int, device: str):
    """The model at identity (every other pixel of every other row, to keep the interpreter short) and the observed
    level at ``MOTION``, on ``device``, with ``features`` dense feature channels (smooth functions of the colour)."""
    model_color, model_depth = (t.float() for t in ray_cast(torch.eye(4, dtype=torch.float64)))
    observed_color, observed_depth = (t.float() for t in ray_cast(invert_pose(MOTION)))
    extra = (lambda c: torch.stack([c[..., 0] * c[..., 1], c.mean(-1) ** 2], -1)) if features else (lambda c: None)
    sparse = torch.zeros_like(model_depth, dtype=torch.bool)
    sparse[::2, ::2] = True
    to = (lambda t: None if t is None else t.to(device))
    model = direct_alignment.ModelView(to(model_color), to(model_color.flip(-1)), to(model_depth),
                                       to((model_depth > 0) & sparse), CAMERA, to(extra(model_color)))
    observed = direct_alignment.ObservedImages.build(to(observed_color), to(observed_color.flip(-1)),
                                                     to(jitter_edges(observed_depth)), CAMERA,
                                                     to(extra(observed_color)))
    return model, observed


def assert_same_sums(fused, reference):
    for got, want in zip(fused, reference):
        got, want = torch.as_tensor(got).double().cpu(), torch.as_tensor(want).double().cpu()
        assert (got - want).abs().max() <= 1e-5 * max(1.0, float(want.abs().max())), (got, want)


@pytest.mark.parametrize("features", [0, 2])
@pytest.mark.parametrize("motion", MOTIONS, ids=["identity", "moved"])
def test_the_fused_step_sums_what_the_torch_step_sums_on_the_cpu(features, motion):
    if not fused_alignment._INTERPRETED:
        pytest.skip("Triton compiles here (TRITON_INTERPRET unset): the CUDA test below checks it")
    weights = dataclasses.replace(WEIGHTS, feature=0.3 if features else 0.0)
    model, observed = level(features, "cpu")
    points, ref = direct_alignment.model_samples(model, observed)
    reference = direct_alignment.normal_equation_sums(observed, motion, weights, points, ref)
    fused = fused_alignment.fused_normal_equation_sums(observed, motion, weights, points, ref)
    assert float(reference[3]) > 1000  # most of the model lands on valid observed pixels
    assert_same_sums(fused, reference)
    assert not fused_alignment.fused_available("cpu")  # the tracker never runs the interpreter


def test_the_model_behind_the_camera_sums_to_nothing_but_its_cost():
    if not fused_alignment._INTERPRETED:
        pytest.skip("Triton compiles here (TRITON_INTERPRET unset): the CUDA test below checks it")
    model, observed = level(0, "cpu")
    points, ref = direct_alignment.model_samples(model, observed)
    behind = se3_exp(torch.tensor([0.0, 0.0, -3.0, 0.0, 0.0, 0.0]))
    h, g, cost, count = fused_alignment.fused_normal_equation_sums(observed, behind, WEIGHTS, points, ref)
    assert int(count) == 0 and float(h.abs().max()) == 0 and float(g.abs().max()) == 0
    assert float(cost) == pytest.approx(len(points) * direct_alignment.cost_cap(WEIGHTS, 0), rel=1e-6)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("features", [0, 2])
def test_the_fused_step_sums_what_the_torch_step_sums_on_cuda_and_tracks_as_the_host_does(features):
    weights = dataclasses.replace(WEIGHTS, feature=0.3 if features else 0.0)
    model, observed = level(features, "cuda")
    points, ref = direct_alignment.model_samples(model, observed)
    assert fused_alignment.fused_available("cuda")
    for motion in MOTIONS:
        motion = motion.cuda()
        assert_same_sums(fused_alignment.fused_normal_equation_sums(observed, motion, weights, points, ref),
                         direct_alignment.normal_equation_sums(observed, motion, weights, points, ref))
    # a whole level on the device (the fused sums) takes the host level's steps
    on_cuda, cost = align_level_on_device(model, observed, torch.eye(4, device="cuda"), weights, 8)
    on_host, host_cost = direct_alignment.align_level(*level(features, "cpu"), torch.eye(4), weights, 8)
    assert (on_cuda.cpu() - on_host).abs().max() <= 1e-4 and cost == pytest.approx(host_cost, rel=1e-4)
