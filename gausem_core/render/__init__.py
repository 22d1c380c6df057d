"""Differentiable rendering of isotropic semantic Gaussians: ``render(cloud, world_to_cam, camera) -> RenderOutput``.

Model (paper Eq. 1): each Gaussian in front of the near plane becomes a screen Gaussian of standard deviation
``radius * f / z`` pixels (fx and fy separately); at a pixel centre at distance d its alpha is
``min(0.99, opacity * exp(-d^2 / 2 sigma^2))``; Gaussians are composited front to back by the camera-space depth of
their centres with weights ``w_i = alpha_i prod_{j<i} (1 - alpha_j)``. Alphas below 1/255 are ignored (as in 3DGS
and gsplat), which bounds every footprint to ``sqrt(2 ln(255 opacity)) <= 3.33`` sigma. Colour, semantic colour and
depth are ``sum_i w_i x_i`` over a black background; ``alpha`` is ``sum_i w_i``. Differentiable w.r.t. every cloud
tensor and ``world_to_cam``.

Back-ends: ``"torch"`` (reference, CPU and CUDA, exact, memory-bounded by row bands), ``"cpu"`` (the same model in a
C++ kernel compiled on first use, CPU only; see :mod:`gausem_core.render.cpu_backend`) and ``"gsplat"`` (CUDA, float32,
needs the gsplat package). ``"auto"`` takes gsplat for float32 CUDA clouds when it imports, the compiled kernel for
CPU clouds when it builds, torch otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera
from gausem_core.native import kernel_available, kernel_error
from gausem_core.render.cpu_backend import rasterize_cpu
from gausem_core.render.gsplat_backend import gsplat_available, rasterize_gsplat
from gausem_core.render.projection import check_render_inputs, project
from gausem_core.render.torch_backend import rasterize_torch

BACKENDS = ("auto", "torch", "cpu", "gsplat")


@dataclass
class RenderOutput:
    """Rendered images of one view (black background)."""

    color: torch.Tensor  # (H, W, 3)
    depth: torch.Tensor  # (H, W) sum_i w_i z_i; divide by alpha for the expected depth of the covered part
    semantic: torch.Tensor  # (H, W, 3)
    alpha: torch.Tensor  # (H, W) silhouette sum_i w_i

    @property
    def expected_depth(self) -> torch.Tensor:
        """Depth of the covered part of each pixel (``depth / alpha``; 0 where nothing is rendered)."""
        return self.depth / self.alpha.clamp_min(1e-6)


def select_backend(backend: str, device: torch.device | str, dtype: torch.dtype = torch.float32) -> str:
    """The back-end ``render`` uses for clouds of ``dtype`` on ``device`` (``"auto"`` resolved).

    On the CPU this builds or loads the compiled kernel (tens of seconds on a machine's first run, then a fraction of
    one): call it before serving or timing frames to keep that out of the first one. ``"cpu"`` raises here when the
    kernel is unavailable."""
    if backend not in BACKENDS:
        raise ValueError(f"render: unknown backend {backend!r}; choose one of {BACKENDS}")
    device = torch.device(device)
    if backend == "cpu" and not kernel_available():
        raise ValueError(f"render backend 'cpu' is unavailable ({kernel_error()}); use backend='torch'")
    if backend != "auto":
        return backend
    if device.type == "cpu":
        return "cpu" if kernel_available() else "torch"
    on_gpu = device.type == "cuda" and dtype == torch.float32
    return "gsplat" if on_gpu and gsplat_available() else "torch"


def prepare_backend(backend: str, device: torch.device | str, dtype: torch.dtype = torch.float32) -> str:
    """:func:`select_backend`, and for gsplat one render of a single Gaussian: gsplat compiles its CUDA kernels on a
    machine's first use (one to two minutes, measured on an H100), which would otherwise fall in the first frame
    (a live node's first frame then took 73 s). Call it before serving or timing frames."""
    chosen = select_backend(backend, device, dtype)
    if chosen == "gsplat":
        ones = torch.ones(1, 3, dtype=dtype, device=device)
        one = GaussianCloud.from_points(torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype, device=device), ones, ones,
                                        torch.full((1,), 0.05, dtype=dtype, device=device))
        render(one, torch.eye(4, dtype=dtype, device=device), PinholeCamera(16.0, 16.0, 8.0, 8.0, 16, 16),
               backend=chosen)
    return chosen


def render(cloud: GaussianCloud, world_to_cam: torch.Tensor, camera: PinholeCamera, *, backend: str = "auto",
           near: float = 0.01) -> RenderOutput:
    """Render ``cloud`` seen from ``world_to_cam`` (4x4, world -> camera optical frame) through ``camera``."""
    check_render_inputs(cloud, world_to_cam, camera, near)
    screen = project(cloud, world_to_cam, camera, near)
    chosen = select_backend(backend, cloud.device, cloud.dtype)
    if chosen == "gsplat":
        image = rasterize_gsplat(screen, camera.width, camera.height)
    elif chosen == "cpu":
        image = rasterize_cpu(screen, camera.width, camera.height)
    else:
        image = rasterize_torch(screen, camera.width, camera.height)
    return RenderOutput(color=image[..., 0:3], semantic=image[..., 3:6], depth=image[..., 6], alpha=image[..., 7])


__all__ = ["BACKENDS", "RenderOutput", "render", "select_backend"]
