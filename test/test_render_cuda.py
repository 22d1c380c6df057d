"""Parity of the gsplat (CUDA) back-end with the torch reference: images and gradients.

Needs a CUDA device and the gsplat package (skipped otherwise). Scenes keep opacities <= 0.8 so that the documented
differences of the back-ends stay below the 1e-3 tolerance: gsplat clamps alpha at 0.999 (we: 0.99, never reached
here) and drops the Gaussian that would take a pixel's transmittance to <= 1e-4 (<= 4e-4 at alpha <= 0.8).
"""
import pytest
import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.render import render, select_backend
from gausem_core.render.gsplat_backend import gsplat_available

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    pytest.mark.skipif(not gsplat_available(), reason="needs the gsplat package"),
]

CAM = PinholeCamera(fx=60.0, fy=64.0, cx=32.5, cy=23.0, width=64, height=48)
FIELDS = ("color", "depth", "semantic", "alpha")


def scene(n=300) -> GaussianCloud:
    gen = torch.Generator().manual_seed(3)
    z = 1.5 + 2.0 * torch.rand(n, 1, generator=gen)
    xy = (torch.rand(n, 2, generator=gen) - 0.5) * torch.tensor([1.1, 0.9]) * z
    return GaussianCloud.from_points(torch.cat([xy, z], 1), torch.rand(n, 3, generator=gen),
                                     torch.rand(n, 3, generator=gen), 0.01 + 0.03 * torch.rand(n, generator=gen),
                                     0.1 + 0.7 * torch.rand(n, generator=gen)).to("cuda")


def render_with_grads(backend):
    cloud = scene().requires_grad_()
    xi = torch.zeros(6, device="cuda", requires_grad=True)
    base = se3_exp(torch.tensor([0.03, -0.02, 0.05, 0.02, -0.01, 0.03], device="cuda"))
    out = render(cloud, se3_exp(xi) @ base, CAM, backend=backend)
    weights = torch.Generator(device="cuda").manual_seed(1)
    loss = sum((getattr(out, f) * torch.rand(getattr(out, f).shape, device="cuda", generator=weights)).sum()
               for f in FIELDS)
    loss.backward()
    return out, {**{k: t.grad for k, t in cloud.tensors().items()}, "xi": xi.grad}


def test_auto_picks_gsplat_for_float32_cuda_clouds():
    assert select_backend("auto", "cuda") == "gsplat"
    assert select_backend("auto", "cuda", torch.float64) == "torch"


def test_gsplat_images_match_the_torch_reference():
    ours, _ = render_with_grads("torch")
    theirs, _ = render_with_grads("gsplat")
    assert ours.alpha.max() > 0.9  # the scene overlaps enough to exercise compositing
    for field in FIELDS:
        assert (getattr(ours, field) - getattr(theirs, field)).abs().max().item() < 1e-3, field


def test_gsplat_gradients_match_the_torch_reference():
    _, ours = render_with_grads("torch")
    _, theirs = render_with_grads("gsplat")
    for name, grad in ours.items():
        scale = grad.abs().max().clamp_min(1e-6)
        assert ((grad - theirs[name]).abs().max() / scale).item() < 1e-2, name
