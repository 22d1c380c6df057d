"""Parity of the gsplat (CUDA) back-end with the torch reference: images and gradients.

Needs a CUDA device and the gsplat package (skipped otherwise). Scenes keep opacities <= 0.8 so that the documented
differences of the back-ends stay below the 1e-3 tolerance: gsplat clamps alpha at 0.999 (we: 0.99, never reached
here) and drops the Gaussian that would take a pixel's transmittance to <= 1e-4 (<= 4e-4 at alpha <= 0.8).
"""
import pytest
import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.render import prepare_backend, render, select_backend
from gausem_core.render.gsplat_backend import gsplat_available

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    pytest.mark.skipif(not gsplat_available(), reason="needs the gsplat package"),
]

CAM = PinholeCamera(fx=60.0, fy=64.0, cx=32.5, cy=23.0, width=64, height=48)
FIELDS = ("color", "depth", "semantic", "alpha")


def wave(i: torch.Tensor, rate: float, phase: float) -> torch.Tensor:
    return 0.5 + 0.5 * torch.sin(rate * i + phase)


def scene(columns=10, rows=8, layers=3) -> GaussianCloud:
    """Layers of overlapping Gaussians across the view, every value from a fixed formula (no random generator, so
    the same scene on any machine and device), drawn on the CPU and then moved to the GPU. All depths differ: the
    back-ends need no tie-break in the compositing order."""
    i = torch.arange(columns * rows * layers, dtype=torch.float64)
    layer, cell = i // (columns * rows), i % (columns * rows)
    z = 1.8 + 0.6 * layer + 0.3 * wave(i, 0.37, 0.0)
    x = ((cell % columns + 0.5) / columns - 0.5 + 0.03 * layer) * 1.1 * z
    y = ((cell // columns + 0.5) / rows - 0.5 + 0.03 * layer) * 0.9 * z
    colors = torch.stack([wave(i, 0.7, phase) for phase in (0, 2, 4)], 1)
    semantics = torch.stack([wave(i, 0.5, phase) for phase in (1, 3, 5)], 1)
    cloud = GaussianCloud.from_points(torch.stack([x, y, z], 1).float(), colors.float(), semantics.float(),
                                      (0.06 + 0.06 * wave(i, 0.9, 0.5)).float(),
                                      (0.1 + 0.7 * wave(i, 1.3, 1.5)).float())
    return cloud.to("cuda")


def render_with_grads(backend):
    """The render of :func:`scene` by ``backend`` and the gradients of a fixed weighted sum of all its images with
    respect to every Gaussian parameter and to the camera pose (a twist ``xi`` left-multiplied onto it)."""
    cloud = scene().requires_grad_()
    xi = torch.zeros(6, device="cuda", requires_grad=True)
    base = se3_exp(torch.tensor([0.03, -0.02, 0.05, 0.02, -0.01, 0.03])).to("cuda")
    out = render(cloud, se3_exp(xi) @ base, CAM, backend=backend)
    weights = torch.Generator().manual_seed(1)
    loss = sum((getattr(out, f) * torch.rand(getattr(out, f).shape, generator=weights).to("cuda")).sum()
               for f in FIELDS)
    loss.backward()
    return out, {**{k: t.grad for k, t in cloud.tensors().items()}, "xi": xi.grad}


def test_auto_picks_gsplat_for_float32_cuda_clouds():
    assert select_backend("auto", "cuda") == "gsplat"
    assert select_backend("auto", "cuda", torch.float64) == "torch"
    assert prepare_backend("auto", "cuda") == "gsplat"  # its kernels built or loaded


def test_gsplat_images_match_the_torch_reference():
    ours, _ = render_with_grads("torch")
    theirs, _ = render_with_grads("gsplat")
    assert ours.alpha.max() > 0.9 and (ours.alpha > 0.5).float().mean() > 0.5  # compositing is exercised
    for field in FIELDS:
        assert getattr(theirs, field).device.type == "cuda", field
        assert (getattr(ours, field) - getattr(theirs, field)).abs().max().item() < 1e-3, field


def test_gsplat_gradients_match_the_torch_reference():
    _, ours = render_with_grads("torch")
    _, theirs = render_with_grads("gsplat")
    assert set(ours) == {"means", "log_radii", "opacity_logits", "colors", "semantics", "xi"}
    for name, grad in ours.items():
        assert grad.abs().max() > 0 and theirs[name].device.type == "cuda", name
        scale = grad.abs().max().clamp_min(1e-6)
        assert ((grad - theirs[name]).abs().max() / scale).item() < 1e-2, name
