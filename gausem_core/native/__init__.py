"""GauSem's compiled CPU kernels, one C++ extension module built on first use: the renderer's compositing
(``raster.cpp``, :mod:`gausem_core.render.cpu_backend`) and the Gauss-Newton normal equations of direct alignment
(``alignment.cpp``, :mod:`gausem_core.slam.direct_alignment`).

The extension is compiled with ``torch.utils.cpp_extension`` (needs a C++ compiler with OpenMP, and ninja: the
``ninja`` wheel of ``requirements.txt`` is found next to the running Python) into torch's extension cache
(``TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``) under a name keyed by this checkout's folder
(:data:`KERNEL_NAME`), so two checkouts on one machine do not rebuild each other's build: tens of seconds once per
checkout, a fraction of a second afterwards. Loops run in parallel on torch's intra-op threads. When it cannot be built, :func:`kernel_error`
says why and every caller falls back to its torch implementation.
"""
from __future__ import annotations

import hashlib
import os
import sys
import threading
import time
from pathlib import Path

_HERE = Path(__file__).parent
_SOURCES = [str(_HERE / name) for name in ("bindings.cpp", "raster.cpp", "alignment.cpp")]
# keyed by the checkout and the environment (two virtualenvs on one checkout build against different torch headers
# and would otherwise rebuild each other's kernel, each waiting on the other's lock)
_KEY = f"{_HERE.resolve()}\0{Path(sys.prefix).resolve()}"
KERNEL_NAME = f"gausem_cpu_kernels_{hashlib.sha1(_KEY.encode()).hexdigest()[:10]}"
_lock = threading.Lock()
_kernel = None
_error: str | None = None
STALE_LOCK_SECONDS = 600  # a build takes under two minutes; an older lock was left by a process killed mid-build


def _remove_stale_lock() -> None:
    """torch waits forever on a build lock whose owner died; drop one older than :data:`STALE_LOCK_SECONDS`."""
    from torch.utils.cpp_extension import _get_build_directory

    lock = Path(_get_build_directory(KERNEL_NAME, verbose=False)) / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return
    if age > STALE_LOCK_SECONDS:
        print(f"gausem: removing {lock}, left {age:.0f} s ago by an interrupted build", file=sys.stderr)
        lock.unlink(missing_ok=True)


def _ninja_on_path() -> None:
    """torch looks for ``ninja`` on PATH; the ninja wheel puts it beside the interpreter (a venv's bin)."""
    bin_dir = str(Path(sys.executable).parent)
    if bin_dir not in os.environ.get("PATH", "").split(os.pathsep):
        os.environ["PATH"] = os.pathsep.join([bin_dir, os.environ.get("PATH", "")])


def _load():
    """The compiled module, or None (with the reason kept for :func:`kernel_error`)."""
    global _kernel, _error
    if _kernel is not None:  # every render asks: no lock once loaded
        return _kernel
    with _lock:
        if _kernel is None and _error is None:
            try:
                from torch.utils.cpp_extension import load

                _ninja_on_path()
                _remove_stale_lock()
                _kernel = load(name=KERNEL_NAME, sources=_SOURCES, extra_cflags=["-O3", "-fopenmp"],
                               extra_ldflags=["-fopenmp"], verbose=False)  # kernels.h: beside the sources
            except Exception as exc:  # noqa: BLE001 -- a missing compiler shows up as many different errors
                _error = f"{type(exc).__name__}: {exc}".strip()
        return _kernel


def kernel_available() -> bool:
    """True when the compiled kernels build (or are cached) and load."""
    return _load() is not None


def kernel_error() -> str | None:
    """Why the kernels are unavailable (None when they load)."""
    _load()
    return _error


def require_kernel():
    """The compiled module; a ValueError saying why when it is unavailable."""
    if _load() is None:
        raise ValueError(f"the compiled CPU kernels are unavailable ({_error})")
    return _kernel
