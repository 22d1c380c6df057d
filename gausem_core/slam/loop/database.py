"""Keyframe descriptor database: exact L2 search over L2-normalised float32 vectors (FAISS or torch)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

BACKENDS = ("auto", "faiss", "torch")


def _import_faiss():
    try:
        import faiss
    except ImportError:
        return None
    return faiss


class DescriptorDatabase:
    """Global image descriptors of keyframes, searched by L2 distance between their unit-norm versions.

    Keyframe ids must be added in strictly increasing order, so "the newest entries" are those with the largest ids.
    ``backend``: ``"faiss"`` (``IndexFlatL2``; sets FAISS to one OpenMP thread, which is fastest for single queries),
    ``"torch"`` (exact search in torch), or ``"auto"`` (FAISS when it imports). Both give the same results.
    """

    def __init__(self, dim: int, backend: str = "auto"):
        if dim <= 0:
            raise ValueError(f"DescriptorDatabase: dim must be positive, got {dim}")
        if backend not in BACKENDS:
            raise ValueError(f"DescriptorDatabase: backend must be one of {BACKENDS}, got {backend!r}")
        faiss = _import_faiss() if backend in ("auto", "faiss") else None
        if backend == "faiss" and faiss is None:
            raise ImportError("DescriptorDatabase backend 'faiss' needs faiss-cpu (pip install 'gausem[faiss]')")
        self.dim = dim
        self.backend = "faiss" if faiss is not None else "torch"
        self._ids: list[int] = []
        self._buffer = np.zeros((16, dim), dtype=np.float32)  # rows [0, len) are used; doubled when full
        self._index = None
        if faiss is not None:
            self._faiss = faiss
            self._index = faiss.IndexFlatL2(dim)

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def ids(self) -> np.ndarray:
        return np.asarray(self._ids, dtype=np.int64)

    @property
    def vectors(self) -> np.ndarray:
        """The stored unit-norm descriptors (len, dim), in insertion order."""
        return self._buffer[:len(self)]

    def add(self, keyframe_id: int, descriptor) -> None:
        """Store the L2-normalised ``descriptor`` (dim,) of keyframe ``keyframe_id``."""
        if self._ids and keyframe_id <= self._ids[-1]:
            raise ValueError(f"DescriptorDatabase.add: keyframe id {keyframe_id} is not larger than the last one "
                             f"({self._ids[-1]}); ids must increase")
        self._append(int(keyframe_id), self._normalised(descriptor, "add"))

    def restore(self, keyframe_ids, unit_vectors) -> None:
        """Store keyframes' unit vectors as saved (a loaded session's: not normalised again, so bit-identical)."""
        for keyframe_id, vector in zip(list(keyframe_ids), np.asarray(unit_vectors, np.float32)):
            self._append(int(keyframe_id), vector)

    def _append(self, keyframe_id: int, unit_vector: np.ndarray) -> None:
        n = len(self)
        if n == self._buffer.shape[0]:
            self._buffer = np.concatenate([self._buffer, np.zeros_like(self._buffer)])
        self._buffer[n] = unit_vector
        self._ids.append(keyframe_id)
        if self._index is not None:
            self._index.add(unit_vector[None])

    def search(self, query, *, k: int | None = None, radius: float | None = None,
               exclude_recent: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Nearest stored keyframes to ``query``, closest first: (ids int64, L2 distances float32).

        ``radius``: keep only distances strictly below it; ``k``: at most this many results; at least one of the two
        must be given. ``exclude_recent``: the newest this many entries are not searched.
        """
        if k is None and radius is None:
            raise ValueError("DescriptorDatabase.search: give k, radius or both")
        if k is not None and k <= 0:
            raise ValueError(f"DescriptorDatabase.search: k must be positive, got {k}")
        if radius is not None and radius <= 0:
            raise ValueError(f"DescriptorDatabase.search: radius must be positive, got {radius}")
        if exclude_recent < 0:
            raise ValueError(f"DescriptorDatabase.search: exclude_recent must be >= 0, got {exclude_recent}")
        q = self._normalised(query, "search")
        searchable = len(self) - exclude_recent
        if searchable <= 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32)
        search = self._search_faiss if self._index is not None else self._search_torch
        rows, squared = search(q, searchable, k, radius)
        return self.ids[rows], np.sqrt(np.maximum(squared, 0)).astype(np.float32)

    def _search_torch(self, q, searchable, k, radius):
        diff = torch.from_numpy(self._buffer[:searchable]) - torch.from_numpy(q)
        squared, rows = torch.sort((diff * diff).sum(1), stable=True)
        if radius is not None:
            keep = squared < radius * radius
            squared, rows = squared[keep], rows[keep]
        if k is not None:
            squared, rows = squared[:k], rows[:k]
        return rows.numpy(), squared.numpy()

    def _search_faiss(self, q, searchable, k, radius):
        params = self._faiss.SearchParameters(sel=self._faiss.IDSelectorRange(0, searchable))
        if radius is None:
            squared, rows = self._index.search(q[None], min(k, searchable), params=params)
            squared, rows = squared[0], rows[0]
            valid = rows >= 0
            return rows[valid], squared[valid]
        _, squared, rows = self._index.range_search(q[None], radius * radius, params=params)
        order = np.lexsort((rows, squared))[:k]
        return rows[order], squared[order]

    def _normalised(self, vec, where: str) -> np.ndarray:
        v = torch.as_tensor(vec).detach().cpu().numpy() if isinstance(vec, torch.Tensor) else np.asarray(vec)
        v = v.astype(np.float32).reshape(-1)
        if v.shape[0] != self.dim:
            raise ValueError(f"DescriptorDatabase.{where}: descriptor has {v.shape[0]} values, expected {self.dim}")
        norm = float(np.linalg.norm(v))
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"DescriptorDatabase.{where}: descriptor must be finite and non-zero")
        return v / norm

    # --- persistence --------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        with open(Path(path), "wb") as f:  # a file object: numpy would otherwise append ".npz" to the name
            np.savez(f, ids=self.ids, vectors=self.vectors)

    @classmethod
    def load(cls, path: str | Path, backend: str = "auto") -> "DescriptorDatabase":
        with np.load(Path(path)) as data:
            if "ids" not in data or "vectors" not in data:
                raise ValueError(f"{path}: not a DescriptorDatabase file (needs 'ids' and 'vectors')")
            ids, vectors = data["ids"], data["vectors"]
        if vectors.ndim != 2 or ids.shape != (vectors.shape[0],) or np.any(np.diff(ids) <= 0):
            raise ValueError(f"{path}: inconsistent DescriptorDatabase file (ids {ids.shape}, vectors {vectors.shape})")
        db = cls(vectors.shape[1], backend)
        db.restore(ids.tolist(), vectors)
        return db
