"""The compiled CPU back-end: the torch back-end's exact model in C++ loops (``cpu_kernel.cpp``), built on first use.

Gaussians are ordered front to back by a radix sort of their depths (the order of ``pairs.depth_order``), pairs are
bucketed by pixel with a counting sort (the Gaussians are visited front to back, so each pixel's list is already in
compositing order) and every pixel is composited, and differentiated, in one pass; the torch back-end
needs a comparison sort and a dozen gathers/scatters over all pairs instead. Memory: about 8 bytes per (Gaussian,
pixel) pair plus one float64 gradient buffer of (5 + C) values per Gaussian with a footprint in the image, and
thread.

The extension is compiled with ``torch.utils.cpp_extension`` (needs a C++ compiler with OpenMP, and ninja: the
``ninja`` wheel of ``requirements.txt`` is found next to the running Python) into torch's extension cache
(``TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``): tens of seconds once per machine, a fraction of a
second afterwards. Rows run in parallel on torch's intra-op threads. When it cannot be built,
:func:`cpu_kernel_error` says why and ``backend="auto"`` uses the torch back-end.
"""
from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import torch

from gausem_core.render.pairs import footprint_boxes
from gausem_core.render.projection import ScreenGaussians

_SOURCE = Path(__file__).with_name("cpu_kernel.cpp")
_lock = threading.Lock()
_kernel = None
_error: str | None = None


def _ninja_on_path() -> None:
    """torch looks for ``ninja`` on PATH; the ninja wheel puts it beside the interpreter (a venv's bin)."""
    bin_dir = str(Path(sys.executable).parent)
    if bin_dir not in os.environ.get("PATH", "").split(os.pathsep):
        os.environ["PATH"] = os.pathsep.join([bin_dir, os.environ.get("PATH", "")])


def _load():
    """The compiled module, or None (with the reason kept for :func:`cpu_kernel_error`)."""
    global _kernel, _error
    if _kernel is not None:  # every render asks: no lock once loaded
        return _kernel
    with _lock:
        if _kernel is None and _error is None:
            try:
                from torch.utils.cpp_extension import load

                _ninja_on_path()
                _kernel = load(name="gausem_cpu_raster", sources=[str(_SOURCE)], extra_cflags=["-O3", "-fopenmp"],
                               extra_ldflags=["-fopenmp"], verbose=False)
            except Exception as exc:  # noqa: BLE001 -- a missing compiler shows up as many different errors
                _error = f"{type(exc).__name__}: {exc}".strip()
        return _kernel


def cpu_kernel_available() -> bool:
    """True when the compiled CPU kernel builds (or is cached) and loads."""
    return _load() is not None


def cpu_kernel_error() -> str | None:
    """Why the kernel is unavailable (None when it loads)."""
    _load()
    return _error


def require_cpu_kernel():
    """The compiled module; a ValueError saying why when it is unavailable."""
    if _load() is None:
        raise ValueError(f"render backend 'cpu' is unavailable ({_error}); use backend='torch'")
    return _kernel


class _RasterizeCpu(torch.autograd.Function):
    """``apply(u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height)`` ->
    ``(height * width, C + 1)``."""

    @staticmethod
    def forward(ctx, u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height):
        image, offsets, slots, alpha = _load().rasterize_forward(
            u, v, inv_var_x, inv_var_y, opacity, features, order, x0, x1, y0, y1, width, height)
        ctx.save_for_backward(u, v, inv_var_x, inv_var_y, opacity, features, order, offsets, slots, alpha)
        ctx.width = width
        return image

    @staticmethod
    def backward(ctx, grad_image):
        grads = _load().rasterize_backward(*ctx.saved_tensors, grad_image, ctx.width)
        return (*grads, None, None, None, None, None, None, None)


def rasterize_cpu(screen: ScreenGaussians, width: int, height: int) -> torch.Tensor:
    """Composite ``screen`` (CPU tensors) into an (height, width, C + 1) image: the feature channels, then alpha."""
    kernel = require_cpu_kernel()
    if screen.u.device.type != "cpu":
        raise ValueError(f"render backend 'cpu' needs CPU tensors, got {screen.u.device}")
    boxes = footprint_boxes(screen, width, height)
    order = kernel.depth_order(screen.depth.detach(), boxes.nonempty())  # pairs.depth_order, by a radix sort
    image = _RasterizeCpu.apply(screen.u, screen.v, screen.inv_var_x, screen.inv_var_y, screen.opacity,
                                screen.features, order, boxes.x0, boxes.x1, boxes.y0, boxes.y1, width, height)
    return image.reshape(height, width, -1)

