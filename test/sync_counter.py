"""Counting gausem_core's device-to-host reads without a GPU (issue 47).

``with HostReads() as reads:`` wraps the torch.Tensor methods that hand a tensor's values to the host (``item``,
``tolist``, ``__bool__``, ``__float__``, ``__int__``, ``__index__``, ``__array__``, ``cpu``, ``numpy``, and ``to``
a CPU device or a CPU tensor's) and records every call made directly from gausem_core code, by the calling function.
Every tensor's device is counted, CPU ones included: on a GPU each such call is a wait for the device, and here it is
where one would be. Implicit syncs (boolean-mask indexing, ``nonzero``, ``repeat_interleave`` without a size) are not
seen.
"""
from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import torch

import gausem_core

ROOT = Path(gausem_core.__file__).resolve().parents[1]
PACKAGE = str(ROOT / "gausem_core")
READS = ("item", "tolist", "__bool__", "__float__", "__int__", "__index__", "__array__", "cpu", "numpy")


def _targets_cpu(args: tuple, kwargs: dict) -> bool:
    """Whether ``Tensor.to(*args, **kwargs)`` moves to the CPU (a device, a device name or a CPU tensor)."""
    for target in (*args, kwargs.get("device"), kwargs.get("other")):
        if isinstance(target, torch.Tensor):
            target = target.device
        if isinstance(target, (str, torch.device)) and torch.device(target).type == "cpu":
            return True
    return False


class HostReads:
    """Context manager: ``sites`` counts the reads per calling function, ``"gausem_core/path.py:Qualified.name"``."""

    def __init__(self):
        self.sites: Counter[str] = Counter()
        self._saved: dict[str, object] = {}

    def count(self, *exempt: str) -> int:
        """All reads, less those at sites that start with one of ``exempt``."""
        return sum(n for site, n in self.sites.items() if not site.startswith(exempt))

    def _record(self, frame) -> None:
        code = frame.f_code
        if code.co_filename.startswith(PACKAGE):
            self.sites[f"{Path(code.co_filename).relative_to(ROOT).as_posix()}:{code.co_qualname}"] += 1

    def _wrap(self, name: str):
        original = getattr(torch.Tensor, name)

        def read(tensor, *args, **kwargs):
            if name != "to" or _targets_cpu(args, kwargs):
                self._record(sys._getframe(1))
            return original(tensor, *args, **kwargs)
        return read

    def __enter__(self) -> "HostReads":
        for name in (*READS, "to"):
            self._saved[name] = vars(torch.Tensor).get(name)
            setattr(torch.Tensor, name, self._wrap(name))
        return self

    def __exit__(self, *exc) -> None:
        for name, saved in self._saved.items():
            if saved is None:
                delattr(torch.Tensor, name)
            else:
                setattr(torch.Tensor, name, saved)
