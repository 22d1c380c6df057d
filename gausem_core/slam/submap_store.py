"""Bounded memory for inactive submaps: named tensor dicts kept on the CPU, spilled to disk past a byte budget.

A :class:`SubmapStore` holds ``dict[str, Tensor]`` entries (a submap's ``GaussianCloud.tensors()``, its keyframe
images, ...) under hashable keys. Entries live in CPU memory until the in-memory total exceeds ``max_bytes``; then the
least recently used ones (stored or loaded longest ago) are written to the cache directory with ``torch.save`` and
dropped from memory. :meth:`SubmapStore.load` returns copies on the requested device, reading a spilled entry back
(it becomes the most recently used in-memory entry again); :meth:`SubmapStore.read` returns copies and moves nothing
(a spilled entry is read from its file and stays there: a reader of the whole map does not churn the store). Round
trips are bit-identical (same dtypes, shapes and
values). The store owns a fresh temporary directory (inside ``cache_dir`` when given) and deletes it on
:meth:`SubmapStore.close` or on leaving a ``with`` block. It is safe to use from several threads (the mapping worker
spills while a node's map publisher loads): each call holds the store's own lock.
"""
from __future__ import annotations

import functools
import shutil
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Hashable
from pathlib import Path

import torch


def _locked(method):
    """``method`` run under the store's lock."""
    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return run


def tensor_bytes(tensors: dict[str, torch.Tensor]) -> int:
    """Bytes of the tensors' elements (what the store accounts for an entry)."""
    return sum(t.numel() * t.element_size() for t in tensors.values())


class SubmapStore:
    """LRU tensor-dict store: CPU memory up to ``max_bytes``, disk beyond (a private folder, deleted on close)."""

    def __init__(self, max_bytes: int, cache_dir: str | Path | None = None):
        if max_bytes < 0:
            raise ValueError(f"SubmapStore: max_bytes must be >= 0, got {max_bytes}")
        if cache_dir is not None:
            Path(cache_dir).mkdir(parents=True, exist_ok=True)
        self.max_bytes = max_bytes
        self.directory: Path | None = Path(tempfile.mkdtemp(prefix="gausem-submaps-", dir=cache_dir))
        self._memory: OrderedDict[Hashable, dict[str, torch.Tensor]] = OrderedDict()  # oldest use first
        self._disk: dict[Hashable, tuple[Path, int]] = {}  # key -> (file, tensor bytes)
        self._files = 0
        self._lock = threading.RLock()

    # --- queries ----------------------------------------------------------------------------------------------------
    @property
    @_locked
    def nbytes(self) -> int:
        """Tensor bytes held in CPU memory."""
        return sum(tensor_bytes(t) for t in self._memory.values())

    @property
    @_locked
    def disk_bytes(self) -> int:
        """Tensor bytes of the entries spilled to disk."""
        return sum(size for _, size in self._disk.values())

    @_locked
    def __contains__(self, key: Hashable) -> bool:
        return key in self._memory or key in self._disk

    @_locked
    def __len__(self) -> int:
        return len(self._memory) + len(self._disk)

    @_locked
    def keys(self) -> list[Hashable]:
        return [*self._memory, *self._disk]

    @_locked
    def on_disk(self, key: Hashable) -> bool:
        """Whether ``key``'s entry is currently spilled to disk (KeyError when absent)."""
        self._check_key(key)
        return key in self._disk

    # --- operations -------------------------------------------------------------------------------------------------
    @_locked
    def store(self, key: Hashable, tensors: dict[str, torch.Tensor]) -> None:
        """Keep detached CPU copies of ``tensors`` under ``key`` (replacing an entry of that key), then enforce the
        budget."""
        self._check_open()
        if not isinstance(tensors, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                    for k, v in tensors.items()):
            raise ValueError(f"SubmapStore.store({key!r}): expected a dict[str, Tensor]")
        copies = {name: t.detach().to("cpu", copy=True) for name, t in tensors.items()}
        self.evict(key, missing_ok=True)
        self._memory[key] = copies
        self._spill()

    @_locked
    def load(self, key: Hashable, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """Copies of ``key``'s tensors on ``device``; marks the entry as used. A spilled entry is read back into memory
        and stays there (even past the budget) until a later store or load spills it again."""
        self._check_open()
        self._check_key(key)
        if key in self._disk:
            path, _ = self._disk.pop(key)
            self._memory[key] = torch.load(path, map_location="cpu", weights_only=True)
            path.unlink()
            self._spill(keep=key)
        self._memory.move_to_end(key)
        return {name: t.to(device, copy=True) for name, t in self._memory[key].items()}

    @_locked
    def read(self, key: Hashable, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """Copies of ``key``'s tensors on ``device``; nothing moves (a spilled entry stays on disk, no entry becomes
        more recently used)."""
        self._check_open()
        self._check_key(key)
        if key in self._disk:
            return torch.load(self._disk[key][0], map_location=device, weights_only=True)
        return {name: t.to(device, copy=True) for name, t in self._memory[key].items()}

    @_locked
    def evict(self, key: Hashable, missing_ok: bool = False) -> None:
        """Forget ``key``'s entry (memory and disk)."""
        self._check_open()
        if key in self._memory:
            del self._memory[key]
        elif key in self._disk:
            self._disk.pop(key)[0].unlink()
        elif not missing_ok:
            raise KeyError(f"SubmapStore: no entry {key!r}")

    @_locked
    def close(self) -> None:
        """Drop every entry and delete the cache directory (idempotent)."""
        if self.directory is not None:
            shutil.rmtree(self.directory, ignore_errors=True)
            self.directory = None
        self._memory.clear()
        self._disk.clear()

    def __enter__(self) -> "SubmapStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- internals --------------------------------------------------------------------------------------------------
    def _spill(self, keep: Hashable | None = None) -> None:
        """Write least recently used entries to disk until the in-memory bytes fit the budget (``keep`` stays)."""
        used = self.nbytes
        for key in list(self._memory):
            if used <= self.max_bytes:
                break
            if key == keep:
                continue
            tensors = self._memory.pop(key)
            path = self.directory / f"{self._files}.pt"
            self._files += 1
            torch.save(tensors, path)
            size = tensor_bytes(tensors)
            self._disk[key] = (path, size)
            used -= size

    def _check_open(self) -> None:
        if self.directory is None:
            raise ValueError("SubmapStore is closed")

    def _check_key(self, key: Hashable) -> None:
        if key not in self:
            raise KeyError(f"SubmapStore: no entry {key!r}")
