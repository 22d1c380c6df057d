"""Isotropic semantic Gaussians (paper §III-A): centre, radius, opacity, RGB colour and semantic colour."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import torch

_FIELDS = ("means", "log_radii", "opacity_logits", "colors", "semantics")
CLASS_ID_CHUNK = 1 << 18  # Gaussians per chunk of GaussianCloud.class_ids


@dataclass
class GaussianCloud:
    """A set of N isotropic Gaussians, stored in the parameterisation that is optimised.

    means (N, 3) centres; log_radii (N,) log of the world-space standard deviation; opacity_logits (N,) logits of
    the opacity; colors (N, 3) RGB in [0, 1]; semantics (N, 3) semantic colour in [0, 1] (the class palette colour).
    """

    means: torch.Tensor
    log_radii: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    semantics: torch.Tensor

    def __post_init__(self):
        n = self.means.shape[0]
        shapes = {"means": (n, 3), "log_radii": (n,), "opacity_logits": (n,), "colors": (n, 3), "semantics": (n, 3)}
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"GaussianCloud.{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")

    # --- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_points(cls, means: torch.Tensor, colors: torch.Tensor, semantics: torch.Tensor,
                    radii: torch.Tensor, opacity: float | torch.Tensor = 0.5) -> "GaussianCloud":
        """Gaussians at ``means`` with given radii (metres) and opacity in (0, 1)."""
        n = means.shape[0]
        opacity = torch.as_tensor(opacity, dtype=means.dtype, device=means.device).clamp(1e-4, 1 - 1e-4).expand(n)
        return cls(means, radii.clamp_min(1e-8).log(), torch.logit(opacity).clone(), colors, semantics)

    @classmethod
    def empty(cls, dtype=torch.float32, device=None) -> "GaussianCloud":
        z = lambda *s: torch.zeros(s, dtype=dtype, device=device)  # noqa: E731
        return cls(z(0, 3), z(0), z(0), z(0, 3), z(0, 3))

    # --- activations --------------------------------------------------------------------------------------------
    @property
    def radii(self) -> torch.Tensor:
        return self.log_radii.exp()

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    # --- whole-cloud operations ---------------------------------------------------------------------------------
    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def _map(self, fn) -> "GaussianCloud":
        return GaussianCloud(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "GaussianCloud":
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "GaussianCloud":
        return self._map(lambda t: t.detach())

    def clone(self) -> "GaussianCloud":
        return self._map(lambda t: t.detach().clone())

    def requires_grad_(self, flag: bool = True) -> "GaussianCloud":
        for t in self.tensors().values():
            t.requires_grad_(flag)
        return self

    def parameters(self) -> dict[str, torch.Tensor]:
        """The optimisable leaf tensors by name (for per-group learning rates)."""
        return self.tensors()

    def prune(self, keep: torch.Tensor) -> "GaussianCloud":
        """Keep the Gaussians where the boolean mask ``keep`` (N,) is true."""
        return self._map(lambda t: t[keep].detach().clone())

    def transformed(self, pose: torch.Tensor) -> "GaussianCloud":
        """Rigidly move the centres by a 4x4 transform (isotropic kernels need no rotation)."""
        out = self.clone()
        pose = pose.to(self.means)
        out.means = self.means.detach() @ pose[:3, :3].T + pose[:3, 3]
        return out

    @staticmethod
    def cat(clouds: list["GaussianCloud"]) -> "GaussianCloud":
        """Concatenate clouds (detached copies)."""
        if not clouds:
            raise ValueError("GaussianCloud.cat needs at least one cloud")
        return GaussianCloud(**{k: torch.cat([getattr(c, k).detach() for c in clouds]) for k in _FIELDS})

    def class_ids(self, palette: torch.Tensor) -> torch.Tensor:
        """Per-Gaussian class id: index of the nearest palette colour (C, 3) to the semantic colour (in chunks of
        :data:`CLASS_ID_CHUNK` Gaussians: the distances held are a chunk's, not the whole map's)."""
        if len(self) == 0:
            return torch.zeros(0, dtype=torch.long, device=self.device)
        palette = palette.to(self.device, self.dtype)
        return torch.cat([torch.cdist(part, palette).argmin(-1)
                          for part in self.semantics.detach().split(CLASS_ID_CHUNK)])

    # --- persistence --------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        torch.save({k: v.detach().cpu() for k, v in self.tensors().items()}, Path(path))

    @classmethod
    def load(cls, path: str | Path, device=None) -> "GaussianCloud":
        state = torch.load(Path(path), map_location=device or "cpu", weights_only=True)
        missing = set(_FIELDS) - set(state)
        if missing:
            raise ValueError(f"{path}: not a GaussianCloud file (missing {sorted(missing)})")
        return cls(**{k: state[k] for k in _FIELDS})
