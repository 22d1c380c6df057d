"""The fused alignment step (one Triton kernel) computes the torch reference's normal equations: on the CPU through
Triton's interpreter (test/conftest.py sets it without CUDA), on CUDA compiled."""
import dataclasses
import importlib.util
from pathlib import Path

import pytest
import torch
from rounding import assert_within_rounding
from test_direct_alignment import (CAMERA, MOTION, WEIGHTS, assert_normal_equations_within_rounding, jitter_edges,
                                   ray_cast)

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


def assert_within_float32(sums, *args):
    """``(H, g, cost, count)`` of a float32 implementation within float32's rounding of the float64 sums."""
    assert_normal_equations_within_rounding(sums, torch.float32, *args)


@pytest.mark.parametrize("features", [0, 2])
@pytest.mark.parametrize("motion", MOTIONS, ids=["identity", "moved"])
def test_the_fused_step_sums_what_the_torch_step_sums_on_the_cpu(features, motion):
    if not fused_alignment._INTERPRETED:
        pytest.skip("Triton compiles here (TRITON_INTERPRET unset): the CUDA test below checks it")
    weights = dataclasses.replace(WEIGHTS, feature=0.3 if features else 0.0)
    model, observed = level(features, "cpu")
    points, ref = direct_alignment.model_samples(model, observed)
    args = (observed, motion, weights, points, ref)
    reference = direct_alignment.normal_equation_sums(*args)
    assert float(reference[3]) > 1000  # most of the model lands on valid observed pixels
    assert_within_float32(fused_alignment.fused_normal_equation_sums(*args), *args)
    assert_within_float32(reference, *args)  # and so does the torch reference
    assert not fused_alignment.fused_available("cpu")  # the tracker never runs the interpreter


# one term of the kernel written wrong: a Jacobian entry's sign or part of it, a residual's IRLS weight, the depth
# residual's motion with z
MUTANTS = {"du_dwy_without_its_1": ("(1 + xn * xn)[:, None]", "(xn * xn)[:, None]"),
           "dz_dwx_of_the_wrong_sign": ("tl.where(col == 3, y[:, None], 0.0)", "tl.where(col == 3, -y[:, None], 0.0)"),
           "colour_without_irls": ("irls = weight / tl.maximum(tl.abs(residual), huber)", "irls = weight"),
           "depth_residual_without_z": ("jd = depth_u[:, None] * du + depth_v[:, None] * dv - dz",
                                        "jd = depth_u[:, None] * du + depth_v[:, None] * dv")}


@pytest.mark.parametrize("mutant", MUTANTS)
def test_a_kernel_with_one_term_wrong_fails_the_bound(mutant, tmp_path):
    if not fused_alignment._INTERPRETED:
        pytest.skip("the mutant runs through Triton's interpreter")
    right, wrong = MUTANTS[mutant]
    source = Path(fused_alignment.__file__).read_text()
    assert source.count(right) == 1, right
    path = tmp_path / "fused_mutant.py"  # a file: Triton reads a kernel's source
    path.write_text(source.replace(right, wrong))
    spec = importlib.util.spec_from_file_location("fused_mutant", path)
    mutated = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mutated)
    model, observed = level(2, "cpu")
    points, ref = direct_alignment.model_samples(model, observed)
    args = (observed, MOTIONS[1], dataclasses.replace(WEIGHTS, feature=0.3), points, ref)
    with pytest.raises(AssertionError, match="rounding in"):
        assert_within_float32(mutated.fused_normal_equation_sums(*args), *args)


def test_the_model_behind_the_camera_sums_to_nothing_but_its_cost():
    if not fused_alignment._INTERPRETED:
        pytest.skip("Triton compiles here (TRITON_INTERPRET unset): the CUDA test below checks it")
    model, observed = level(0, "cpu")
    points, ref = direct_alignment.model_samples(model, observed)
    behind = se3_exp(torch.tensor([0.0, 0.0, -3.0, 0.0, 0.0, 0.0]))
    h, g, cost, count = fused_alignment.fused_normal_equation_sums(observed, behind, WEIGHTS, points, ref)
    assert int(count) == 0 and float(h.abs().max()) == 0 and float(g.abs().max()) == 0
    cap = direct_alignment.cost_cap(WEIGHTS, 0)  # every point's, summed in float32
    assert_within_rounding(cost, len(points) * cap, len(points) * cap, len(points), torch.float32, "cost")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("features", [0, 2])
def test_the_fused_step_sums_what_the_torch_step_sums_on_cuda_and_tracks_as_the_host_does(features):
    weights = dataclasses.replace(WEIGHTS, feature=0.3 if features else 0.0)
    model, observed = level(features, "cuda")
    points, ref = direct_alignment.model_samples(model, observed)
    assert fused_alignment.fused_available("cuda")
    for motion in MOTIONS:
        args = (observed, motion.cuda(), weights, points, ref)
        assert_within_float32(fused_alignment.fused_normal_equation_sums(*args), *args)
        assert_within_float32(direct_alignment.normal_equation_sums(*args), *args)
    # a whole level on the device (the fused sums) takes the host level's steps
    on_cuda, cost = align_level_on_device(model, observed, torch.eye(4, device="cuda"), weights, 8)
    on_host, host_cost = direct_alignment.align_level(*level(features, "cpu"), torch.eye(4), weights, 8)
    assert (on_cuda.cpu() - on_host).abs().max() <= 1e-4 and cost == pytest.approx(host_cost, rel=1e-4)
