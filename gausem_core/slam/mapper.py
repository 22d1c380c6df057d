"""Mapping (paper §III-A, Eq. 3-4): semantic-sampling initialisation, densification, keyframe-window bundle adjustment."""
from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch

from gausem_core.config import MappingConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_exp, transform_points
from gausem_core.render import render
from gausem_core.slam.adam import AdamSteps, ParameterGroup
from gausem_core.slam.losses import mapping_loss
from gausem_core.slam.observation import MAX_COLOR, Observation


@dataclass
class Keyframe:
    frame_id: int
    obs: Observation
    cam_to_world: torch.Tensor  # (4, 4) in the submap frame; refined by bundle adjustment unless fixed
    fixed: bool = False  # the submap's anchor keyframe is never moved by local BA


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


def gaussian_groups(params: GaussianCloud, cfg: MappingConfig,
                    final_fractions: dict[str, float] | None = None) -> list[ParameterGroup]:
    """One Adam group per parameter tensor of ``params`` at its ``mapping.lr_*`` learning rate, decaying to
    ``final_fractions[name]`` of it where given."""
    lrs = {"means": cfg.lr_means, "log_radii": cfg.lr_log_radii, "opacity_logits": cfg.lr_opacity,
           "colors": cfg.lr_colors, "semantics": cfg.lr_semantics}
    fractions = final_fractions or {}
    return [ParameterGroup([t], lrs[name], fractions.get(name, 1.0)) for name, t in params.parameters().items()]


class Mapper:
    def __init__(self, cfg: MappingConfig, backend: str = "auto", seed: int = 0):
        self.cfg = cfg
        self.backend = backend
        self.generator = torch.Generator().manual_seed(seed)
        self.lock = threading.RLock()  # held while keyframe poses change (GauSemSLAM shares it with its tracker)
        self.hurry = threading.Event()  # set: optimisations stop at their next iteration (GauSemSLAM.interrupt)
        self.pressure = threading.Event()  # set (by the mapping worker): a newer keyframe waits, so optimisations
        self.min_iteration_fraction = 1.0  # stop after this fraction of their iterations (1: never cut short)
        self.shortened = 0  # optimisations cut short under pressure

    def initialise(self, obs: Observation, cam_to_world: torch.Tensor, opacity: float | None = None) -> GaussianCloud:
        """A new submap's Gaussians from one frame by semantic sampling, before any optimisation (``opacity``:
        default ``init_opacity``)."""
        n_total = int(self.cfg.init_samples_fraction * obs.depth.numel())
        pixels = semantic_sample(obs.labels, obs.valid_depth, n_total, self.cfg.sampling_gamma, self.generator)
        return gaussians_from_pixels(obs, cam_to_world, pixels, opacity or self.cfg.init_opacity,
                                     self.cfg.init_radius_scale)

    def densify(self, cloud: GaussianCloud, obs: Observation, cam_to_world: torch.Tensor) -> GaussianCloud:
        """Add Gaussians where the map is transparent (silhouette < tau_sil) or a new surface lies in front of it."""
        with torch.no_grad():
            out = render(cloud, invert_pose(cam_to_world), obs.camera, backend=self.backend)
            expected_depth = out.expected_depth
            behind = expected_depth > obs.depth + self.cfg.densify_depth_margin
            grow = obs.valid_depth & ((out.alpha < self.cfg.densify_silhouette_threshold) | behind)
        pixels = torch.nonzero(grow.reshape(-1)).squeeze(1)
        if len(pixels) == 0:
            return cloud
        grown = gaussians_from_pixels(obs, cam_to_world, pixels, self.cfg.init_opacity, self.cfg.init_radius_scale)
        return GaussianCloud.cat([cloud, grown])

    def optimise(self, cloud: GaussianCloud, keyframes: list[Keyframe], iterations: int,
                 optimise_poses: bool | None = None, publish: Callable[[GaussianCloud], None] | None = None,
                 publish_every: int = 0) -> tuple[GaussianCloud, list[float]]:
        """Joint optimisation of Gaussians (and non-fixed keyframe poses) over keyframes sampled each iteration.

        Keyframe poses are updated in place. Returns the optimised cloud (pruned) and the loss per iteration.
        ``publish`` gets a finished copy of the Gaussians every ``publish_every`` iterations (a map to track against
        while the optimisation goes on).
        """
        cfg = self.cfg
        if optimise_poses is None:
            optimise_poses = cfg.optimise_poses
        params = cloud.clone().requires_grad_(True)
        groups = gaussian_groups(params, cfg)
        movable = [kf for kf in keyframes if optimise_poses and not kf.fixed]
        twists = {id(kf): torch.zeros(6, dtype=params.dtype, device=params.device, requires_grad=True) for kf in movable}
        if twists:
            groups.append(ParameterGroup(list(twists.values()), cfg.lr_pose))
        adam = AdamSteps(groups)
        losses = []
        for iteration in range(iterations):
            if self.hurry.is_set():
                break
            if self.pressure.is_set() and iteration >= self.min_iteration_fraction * iterations:
                self.shortened += 1
                break
            kf = keyframes[int(torch.randint(len(keyframes), (1,), generator=self.generator))]
            w2c = invert_pose(kf.cam_to_world.to(params.dtype))
            if id(kf) in twists:
                w2c = se3_exp(twists[id(kf)]) @ w2c
            out = render(params, w2c, kf.obs.camera, backend=self.backend)
            loss = mapping_loss(out, kf.obs, cfg.w_color, cfg.w_depth, cfg.w_semantic, cfg.ssim_lambda)
            adam.step(loss)
            losses.append(loss.detach())
            if publish is not None and publish_every > 0 and (iteration + 1) % publish_every == 0:
                publish(self._finished(params.detach().clone()))
        with torch.no_grad():
            poses = [invert_pose(se3_exp(twists[id(kf)]) @ invert_pose(kf.cam_to_world.to(params.dtype)))
                     for kf in movable]
            with self.lock:  # the tracker reads the poses in one piece
                for kf, pose in zip(movable, poses):
                    kf.cam_to_world = pose
        return self._finished(params.detach()), torch.stack(losses).tolist() if losses else []

    def _finished(self, cloud: GaussianCloud) -> GaussianCloud:
        """Optimised Gaussians as the map keeps them: colours clamped (in place), then pruned."""
        with torch.no_grad():
            cloud.colors.clamp_(0, MAX_COLOR)
            cloud.semantics.clamp_(0, 1)
        return self.prune(cloud)

    def prune(self, cloud: GaussianCloud) -> GaussianCloud:
        """Drop transparent and huge Gaussians."""
        keep = (cloud.opacities > self.cfg.prune_opacity) & (cloud.radii < self.cfg.prune_radius)
        return cloud if bool(keep.all()) else cloud.prune(keep)
