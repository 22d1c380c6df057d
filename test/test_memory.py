"""release_free_heap returns the freed pages that small live objects keep inside the C heap."""
import sys

import pytest

from gausem_core.memory import release_free_heap


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_freed_buffers_between_live_objects_go_back_to_the_system():
    large, small = [], []
    for _ in range(1500):  # 64 KiB buffers come from the heap (below glibc's mmap threshold), interleaved ...
        large.append(bytearray(64 * 1024))
        small.append(bytearray(1024))  # ... with small objects that stay alive and pin the heap's pages
    del large
    before = _resident_mb()
    if not release_free_heap():
        pytest.skip("the C library has no malloc_trim")
    assert before - _resident_mb() > 50  # of the ~94 MiB freed
    assert len(small) == 1500
