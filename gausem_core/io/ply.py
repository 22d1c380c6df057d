"""The Gaussian map as a 3DGS-style binary PLY that splat viewers open, plus class ids and semantic colours.

One ``vertex`` element, little-endian, with the properties 3DGS writes for SH degree 0 (no ``f_rest_*``):
``x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3`` (float32), then GauSem's ``sem_r sem_g sem_b`` (float32,
semantic colour in [0, 1]) and, when class ids are given, ``class_id`` (int32). Conventions as in 3DGS:
``f_dc = (rgb - 0.5) / SH_C0``, opacity as a logit, scales as the log of the standard deviation (the isotropic radius
repeated three times), rotation the identity quaternion with w first (``rot_0 = 1``); normals are zero.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gausem_core.gaussians import GaussianCloud

SH_C0 = 0.28209479177387814
_SPLAT_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                 "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "sem_r", "sem_g", "sem_b")
_REQUIRED_FIELDS = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                   "sem_r", "sem_g", "sem_b")
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def write_gaussian_ply(path: str | Path, cloud: GaussianCloud,
                       class_ids: torch.Tensor | np.ndarray | None = None) -> None:
    """Write ``cloud`` (and optional per-Gaussian ``class_ids`` (N,)) as a 3DGS-style binary PLY."""
    n = len(cloud)
    c = {k: v.detach().cpu().double().numpy() for k, v in cloud.tensors().items()}
    columns = {"x": c["means"][:, 0], "y": c["means"][:, 1], "z": c["means"][:, 2],
               "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n),
               **{f"f_dc_{i}": (c["colors"][:, i] - 0.5) / SH_C0 for i in range(3)},
               "opacity": c["opacity_logits"], **{f"scale_{i}": c["log_radii"] for i in range(3)},
               "rot_0": np.ones(n), "rot_1": np.zeros(n), "rot_2": np.zeros(n), "rot_3": np.zeros(n),
               "sem_r": c["semantics"][:, 0], "sem_g": c["semantics"][:, 1], "sem_b": c["semantics"][:, 2]}
    dtype = [(name, "<f4") for name in _SPLAT_FIELDS]
    if class_ids is not None:
        ids = class_ids.detach().cpu().numpy() if isinstance(class_ids, torch.Tensor) else np.asarray(class_ids)
        if ids.shape != (n,):
            raise ValueError(f"write_gaussian_ply: class_ids has shape {ids.shape}, expected ({n},)")
        columns["class_id"] = ids
        dtype.append(("class_id", "<i4"))
    table = np.empty(n, dtype=dtype)
    for name in table.dtype.names:
        table[name] = columns[name]
    types = {"<f4": "float", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0",
              "comment GauSem isotropic semantic Gaussians (3DGS layout, SH degree 0)", f"element vertex {n}",
              *(f"property {types[t]} {name}" for name, t in dtype), "end_header"]
    with Path(path).open("wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.tobytes())


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """The ``vertex`` properties of a binary little-endian PLY whose first element is ``vertex`` (name -> (N,))."""
    data = Path(path).read_bytes()
    end = data.find(b"\nend_header\n") + 1
    if not data.startswith(b"ply\n") or end == 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary_little_endian 1.0 PLY files are supported")
    count, dtype, elements_seen = 0, [], 0
    for line in lines:
        words = line.split()
        if words[:1] == ["element"]:
            if elements_seen == 0 and words[1:2] != ["vertex"]:
                raise ValueError(f"{path}: the first PLY element must be 'vertex', got {line!r}")
            count = int(words[2]) if elements_seen == 0 else count
            elements_seen += 1
        elif words[:1] == ["property"] and elements_seen == 1:
            if words[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported vertex property {line!r} (list properties are not supported)")
            dtype.append((words[2], "<" + _PLY_TYPES[words[1]]))
    if elements_seen == 0:
        raise ValueError(f"{path}: no 'vertex' element")
    offset, dtype = end + len(b"end_header\n"), np.dtype(dtype)
    if len(data) - offset < count * dtype.itemsize:
        raise ValueError(f"{path}: truncated ({len(data) - offset} data bytes for {count} vertices of "
                         f"{dtype.itemsize} bytes)")
    table = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return {name: table[name].copy() for name in table.dtype.names}


def read_gaussian_ply(path: str | Path) -> tuple[GaussianCloud, torch.Tensor | None]:
    """Read a PLY written by :func:`write_gaussian_ply` -> (GaussianCloud float32, class ids (N,) int64 or None).

    ``f_rest_*`` in other 3DGS files is ignored (view-independent colour only); anisotropic scales are an error.
    """
    v = read_ply_vertices(path)
    missing = [name for name in _REQUIRED_FIELDS if name not in v]
    if missing:
        raise ValueError(f"{path}: missing vertex properties {missing}")
    scales = np.stack([v[f"scale_{i}"] for i in range(3)], 1)
    if np.ptp(scales, axis=1).max(initial=0) > 1e-6:
        raise ValueError(f"{path}: anisotropic scales; GauSem Gaussians are isotropic (scale_0 = scale_1 = scale_2)")
    col = lambda *names: torch.from_numpy(np.stack([v[k] for k in names], -1).astype(np.float32))  # noqa: E731
    cloud = GaussianCloud(means=col("x", "y", "z"), log_radii=col("scale_0")[:, 0],
                          opacity_logits=col("opacity")[:, 0],
                          colors=col("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5,
                          semantics=col("sem_r", "sem_g", "sem_b"))
    class_ids = torch.from_numpy(v["class_id"].astype(np.int64)) if "class_id" in v else None
    return cloud, class_ids
