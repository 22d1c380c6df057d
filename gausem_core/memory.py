"""Handing freed heap memory back to the operating system during long runs."""
from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none (macOS, musl)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return getattr(libc, "malloc_trim", None)


def release_free_heap() -> bool:
    """Return the C heap's free pages to the system; whether the C library could.

    Mapping a keyframe allocates and frees many image-sized buffers among small long-lived objects (poses, records);
    glibc keeps the freed pages between them, so without this a run's resident memory grows with its length
    (`benchmarks/submaps.py memory`: 500 frames 1,050 -> 705 MB peak, no measurable time cost at one call per keyframe).
    """
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
