"""Where a submap gains and loses Gaussians: the densification strategy (gsplat's ``DefaultStrategy`` is the model).

The mapper asks a :class:`DensificationStrategy` for a new submap's first Gaussians (semantic sampling, paper
§III-A), for the Gaussians a keyframe adds where the map lacks them (silhouette or depth error), for one-pixel detail
once the keyframe is optimised (where its colour is off finer than the lattice), and to prune the optimised ones.
New Gaussians are spawned ``spacing`` pixels apart (radius ``spacing`` pixels' footprint), where ``spacing = max(1,
width / mapping.density_width)``: the map's density, and so its size, does not grow with the image.
"""
from __future__ import annotations

import math

import torch

from gausem_core.config import MappingConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, invert_pose, transform_points
from gausem_core.render import RenderOutput, render
from gausem_core.slam.observation import Observation


def semantic_sample(labels: torch.Tensor, valid: torch.Tensor, n_total: int, gamma: float,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """Pixel indices (flat) sampled per class: n_c = floor(N_tot * A_c^gamma / sum_k A_k^gamma), at most A_c each."""
    flat_labels, flat_valid = labels.reshape(-1), valid.reshape(-1)
    classes, areas = torch.unique(flat_labels[flat_valid], return_counts=True)
    if len(classes) == 0:
        return torch.zeros(0, dtype=torch.long, device=labels.device)
    weights = areas.double() ** gamma
    counts = torch.minimum(torch.floor(n_total * weights / weights.sum()).long(), areas)
    picked = []
    for c, n in zip(classes.tolist(), counts.tolist()):
        pixels = torch.nonzero(flat_valid & (flat_labels == c)).squeeze(1)
        order = torch.randperm(len(pixels), generator=generator, device="cpu")[:n].to(pixels.device)
        picked.append(pixels[order])
    return torch.cat(picked)


def gaussians_from_pixels(obs: Observation, cam_to_world: torch.Tensor, pixels: torch.Tensor,
                          opacity: float, radius_scale: float = 1.0) -> GaussianCloud:
    """Back-project flat pixel indices into Gaussians: colour and semantics from the pixel, radius scale * d / f."""
    depth = obs.depth.reshape(-1)[pixels]
    rays = obs.camera.pixel_rays(obs.depth.dtype, obs.depth.device).reshape(-1, 3)[pixels]
    means = transform_points(cam_to_world.to(depth.dtype), rays * depth[:, None])
    radii = radius_scale * depth / obs.camera.focal
    return GaussianCloud.from_points(means, obs.rgb.reshape(-1, 3)[pixels].clone(),
                                     obs.semantic.reshape(-1, 3)[pixels].clone(), radii, opacity)


def fine_residual(residual: torch.Tensor, spacing: float) -> torch.Tensor:
    """(H, W, C) the part of an image residual finer than ``spacing`` pixels: the residual less its mean over the
    (2 * round(spacing) + 1)^2 pixels around (what Gaussians that far apart cannot fit, not a region still off)."""
    size = 2 * round(spacing) + 1
    image = residual.permute(2, 0, 1)[None]
    local = torch.nn.functional.avg_pool2d(image, size, stride=1, padding=size // 2, count_include_pad=False)
    return (image - local)[0].permute(1, 2, 0)


def pixel_lattice(height: int, width: int, spacing: float, device: torch.device | str) -> torch.Tensor:
    """(H, W) bool: the pixels ``spacing`` (>= 1, not necessarily whole) apart in both directions, the centre of each
    spacing x spacing block."""
    def axis(size: int) -> torch.Tensor:
        picked = torch.zeros(size, dtype=torch.bool, device=device)
        picked[(torch.arange(math.ceil(size / spacing), device=device) * spacing + spacing / 2).floor().long()
               .clamp_max(size - 1)] = True
        return picked

    return axis(height)[:, None] & axis(width)[None, :]


class DensificationStrategy:
    """Initial sampling, growth and pruning of a submap's Gaussians (``mapping.*`` parameters)."""

    def __init__(self, cfg: MappingConfig, backend: str = "auto", generator: torch.Generator | None = None):
        self.cfg = cfg
        self.backend = backend
        self.generator = generator

    def spacing(self, obs: Observation) -> float:
        """Pixels between new Gaussians in ``obs``'s image (at least 1)."""
        if self.cfg.density_width <= 0:
            return 1.0
        return max(1.0, obs.camera.width / self.cfg.density_width)

    def initial(self, obs: Observation, cam_to_world: torch.Tensor, opacity: float | None = None) -> GaussianCloud:
        """A new submap's Gaussians from one frame by semantic sampling, before any optimisation (``opacity``:
        default ``init_opacity``)."""
        spacing = self.spacing(obs)
        n_total = int(self.cfg.init_samples_fraction * obs.depth.numel() / spacing ** 2)
        pixels = semantic_sample(obs.labels, obs.valid_depth, n_total, self.cfg.sampling_gamma, self.generator)
        return gaussians_from_pixels(obs, cam_to_world, pixels, opacity or self.cfg.init_opacity,
                                     self.cfg.init_radius_scale * spacing)

    def grow(self, cloud: GaussianCloud, obs: Observation, cam_to_world: torch.Tensor) -> GaussianCloud:
        """``cloud`` and :meth:`new_gaussians` for the keyframe ``obs``."""
        return _joined(cloud, self.new_gaussians(cloud, obs, cam_to_world))

    def new_gaussians(self, cloud: GaussianCloud, obs: Observation, cam_to_world: torch.Tensor,
                      opacity: float | None = None) -> GaussianCloud:
        """Gaussians on the lattice where the map ``cloud`` is transparent (silhouette < tau_sil) or a new surface
        lies in front of it (a new keyframe, before its optimisation); ``opacity``: default ``init_opacity``."""
        spacing = self.spacing(obs)
        with torch.no_grad():
            out = render(cloud, invert_pose(cam_to_world), obs.camera, backend=self.backend)
            lacking = obs.valid_depth & self._lacking(out, obs)
            if spacing > 1:
                lacking &= pixel_lattice(*lacking.shape, spacing, lacking.device)
        return self._spawned(obs, cam_to_world, lacking, spacing, cloud, opacity)

    def add_detail(self, cloud: GaussianCloud, obs: Observation, cam_to_world: torch.Tensor) -> GaussianCloud:
        """Beside a lattice coarser than one pixel, add one-pixel Gaussians where the map, optimised over this view,
        covers it but still misses its colour by more than ``densify_color_error``: detail the lattice is too coarse
        for (not the error of a view the map has not been fitted to yet)."""
        spacing = self.spacing(obs)
        if spacing <= 1 or self.cfg.densify_color_error <= 0:
            return cloud
        with torch.no_grad():
            out = render(cloud, invert_pose(cam_to_world), obs.camera, backend=self.backend)
            error = fine_residual(out.color - obs.rgb * out.alpha[..., None], spacing).abs().mean(-1)
            missed = obs.valid_depth & ~self._lacking(out, obs) & (error > self.cfg.densify_color_error)
        return _joined(cloud, self._spawned(obs, cam_to_world, missed, 1.0, cloud))

    def _lacking(self, out: RenderOutput, obs: Observation) -> torch.Tensor:
        """(H, W) bool: where the render ``out`` is transparent or lies behind the measured depth."""
        behind = out.expected_depth > obs.depth + self.cfg.densify_depth_margin
        return (out.alpha < self.cfg.densify_silhouette_threshold) | behind

    def _spawned(self, obs: Observation, cam_to_world: torch.Tensor, pixels: torch.Tensor, footprint: float,
                 like: GaussianCloud, opacity: float | None = None) -> GaussianCloud:
        """A Gaussian at each pixel of the mask ``pixels``, ``footprint`` pixels wide, ``opacity`` (default
        ``init_opacity``) opaque (dtype and device of ``like``)."""
        flat = torch.nonzero(pixels.reshape(-1)).squeeze(1)
        if len(flat) == 0:
            return GaussianCloud.empty(like.dtype, like.device)
        return gaussians_from_pixels(obs, cam_to_world, flat, opacity or self.cfg.init_opacity,
                                     self.cfg.init_radius_scale * footprint).to(like.device, like.dtype)

    def prune(self, cloud: GaussianCloud) -> GaussianCloud:
        """Drop transparent and huge Gaussians (after every optimisation)."""
        keep = (cloud.opacities > self.cfg.prune_opacity) & (cloud.radii < self.cfg.prune_radius)
        return cloud if bool(keep.all()) else cloud.prune(keep)

    def prune_hidden(self, cloud: GaussianCloud, views: list[tuple[torch.Tensor, PinholeCamera]]) -> GaussianCloud:
        """Drop the Gaussians that add less than ``prune_weight`` pixels to all of ``views`` (world-to-camera, camera)
        together: hidden behind others or outside them (a closed submap's, seen from its keyframes)."""
        if self.cfg.prune_weight <= 0 or not views or len(cloud) == 0:
            return cloud
        weights = blend_weights(cloud, views, self.backend)
        keep = weights >= self.cfg.prune_weight
        return cloud if bool(keep.all()) else cloud.prune(keep)


def _joined(cloud: GaussianCloud, added: GaussianCloud) -> GaussianCloud:
    """``cloud`` followed by ``added`` (``cloud`` itself when nothing was added)."""
    return GaussianCloud.cat([cloud, added]) if len(added) else cloud


def blend_weights(cloud: GaussianCloud, views: list[tuple[torch.Tensor, PinholeCamera]],
                  backend: str = "auto") -> torch.Tensor:
    """(N,) each Gaussian's blending weight summed over the pixels of ``views``: the gradient of the rendered image's
    sum with respect to a colour of one, which every pixel's colour holds with that Gaussian's weight."""
    ones = torch.ones(len(cloud), dtype=cloud.dtype, device=cloud.device, requires_grad=True)
    probe = GaussianCloud(cloud.means.detach(), cloud.log_radii.detach(), cloud.opacity_logits.detach(),
                          ones[:, None].expand(-1, 3), cloud.semantics.detach())
    total = torch.zeros_like(ones)
    for world_to_cam, camera in views:
        image = render(probe, world_to_cam, camera, backend=backend).color[..., 0]
        total += torch.autograd.grad(image.sum(), ones)[0]
    return total
