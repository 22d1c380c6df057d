"""Mapping (paper §III-A, Eq. 3-4): keyframe-window bundle adjustment of a submap's Gaussians and keyframe poses;
where Gaussians are added and dropped is the densification strategy's (``slam.densification``)."""
from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch

from gausem_core.config import MappingConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.render import render
from gausem_core.slam.adam import AdamSteps, ParameterGroup
from gausem_core.slam.densification import DensificationStrategy
from gausem_core.slam.losses import mapping_loss, valid_depth_pixels
from gausem_core.slam.observation import MAX_COLOR, Observation


@dataclass
class Keyframe:
    frame_id: int
    obs: Observation
    cam_to_world: torch.Tensor  # (4, 4) in the submap frame; refined by bundle adjustment unless fixed
    fixed: bool = False  # the submap's anchor keyframe is never moved by local BA


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
        self.strategy = DensificationStrategy(cfg, backend, self.generator)  # where Gaussians are added and dropped
        # The map's lock (re-entrant), shared as ``BackEnd.lock`` and ``GauSemSLAM.lock``. It guards what the
        # tracking thread and the mapping worker (``worker.mode: async``) share besides the Gaussians (those are
        # swapped whole under each submap's own lock, ``slam.submap``): keyframe poses, submap anchors, the lists of
        # submaps and of their keyframes, and the frame records (appended, re-anchored). Writers hold it for each
        # change: this mapper (bundle adjustment's poses), the back end (a new submap or keyframe, records
        # re-anchored) and the loop closure (a correction's anchors and keyframe poses). Readers hold it for poses
        # that must agree: the front end (the submap it tracks against, the motion model's poses, recording a frame),
        # the occupancy grid's rays and the tracking node's TF. No optimisation or re-mapping runs under it.
        self.lock = threading.RLock()
        self.hurry = threading.Event()  # set: optimisations stop at their next iteration (GauSemSLAM.interrupt)
        self.pressure = threading.Event()  # set (by the mapping worker): a newer keyframe waits, so optimisations
        self.min_iteration_fraction = 1.0  # stop after this fraction of their iterations (1: never cut short)
        self.shortened = 0  # optimisations cut short under pressure

    def optimise(self, cloud: GaussianCloud, keyframes: list[Keyframe], iterations: int,
                 optimise_poses: bool | None = None, publish: Callable[[GaussianCloud], None] | None = None,
                 publish_every: int = 0) -> tuple[GaussianCloud, list[float]]:
        """Joint optimisation of Gaussians (and non-fixed keyframe poses) over keyframes sampled each iteration.

        Keyframe poses are updated in place. Returns the optimised cloud (pruned) and the loss per iteration.
        ``publish`` gets a finished copy of the Gaussians every ``publish_every`` iterations (a map to track against
        while the optimisation goes on). On a GPU the iterations make no host sync of their own (the rasteriser may):
        the keyframes' valid pixels are listed before them and the losses read back after them.
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
        valid_pixels = {id(kf): valid_depth_pixels(kf.obs) for kf in keyframes}
        losses = []
        for iteration in range(iterations):
            if self.hurry.is_set():
                break
            if self.pressure.is_set() and iteration >= self.min_iteration_fraction * iterations:
                self.shortened += 1
                break
            kf = keyframes[self._keyframe_index(len(keyframes))]
            w2c = invert_pose(kf.cam_to_world.to(params.dtype))
            if id(kf) in twists:
                w2c = se3_exp(twists[id(kf)]) @ w2c
            out = render(params, w2c, kf.obs.camera, backend=self.backend)
            loss = mapping_loss(out, kf.obs, cfg.w_color, cfg.w_depth, cfg.w_semantic, cfg.ssim_lambda,
                                valid_pixels[id(kf)])
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

    def state_dict(self) -> dict:
        """The random generator's state (keyframe draws, densification); :meth:`load_state_dict` restores it."""
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`: the draws go on as the saved mapper's would have."""
        self.generator.set_state(state["generator"])

    def _keyframe_index(self, count: int) -> int:
        """A uniform draw below ``count`` from the mapper's generator: a CPU one, so no device read."""
        return int(torch.randint(count, (1,), generator=self.generator))

    def _finished(self, cloud: GaussianCloud) -> GaussianCloud:
        """Optimised Gaussians as the map keeps them: colours clamped (in place), then pruned."""
        with torch.no_grad():
            cloud.colors.clamp_(0, MAX_COLOR)
            cloud.semantics.clamp_(0, 1)
        return self.strategy.prune(cloud)
