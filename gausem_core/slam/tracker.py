"""Frame-to-model tracking (paper Eq. 2): optimise the camera pose through the renderer with the Gaussians frozen."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.config import TrackingConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.render import render
from gausem_core.slam.losses import tracking_loss
from gausem_core.slam.observation import Observation


@dataclass
class TrackingResult:
    cam_to_world: torch.Tensor  # (4, 4), in the frame of the cloud (the submap)
    loss: float
    iterations: int


def constant_velocity(previous: torch.Tensor, before_previous: torch.Tensor | None) -> torch.Tensor:
    """Predict the next cam_to_world by repeating the last relative motion (identity motion with one pose)."""
    if before_previous is None:
        return previous.clone()
    return previous @ (invert_pose(before_previous) @ previous)


class Tracker:
    """Adam on a twist xi applied on the left of world_to_cam: world_to_cam = exp(xi) @ world_to_cam_0.

    The learning rates decay exponentially to ``final_lr_fraction`` of their start over the iterations: the L1 loss
    has a sharp minimum that a constant-rate Adam circles around. The best pose seen is returned.
    """

    def __init__(self, cfg: TrackingConfig, backend: str = "auto"):
        self.cfg = cfg
        self.backend = backend

    def track(self, cloud: GaussianCloud, obs: Observation, init_cam_to_world: torch.Tensor) -> TrackingResult:
        cfg = self.cfg
        frozen = cloud.detach()
        w2c0 = invert_pose(init_cam_to_world.detach()).to(frozen.dtype)
        rho = torch.zeros(3, dtype=w2c0.dtype, device=w2c0.device, requires_grad=True)
        omega = torch.zeros(3, dtype=w2c0.dtype, device=w2c0.device, requires_grad=True)
        optimiser = torch.optim.Adam([{"params": [rho], "lr": cfg.lr_translation},
                                      {"params": [omega], "lr": cfg.lr_rotation}])
        decay = torch.optim.lr_scheduler.ExponentialLR(optimiser, cfg.final_lr_fraction ** (1 / max(cfg.iterations, 1)))
        best_loss, best_w2c, history = float("inf"), w2c0, []
        iterations = 0
        for iterations in range(1, cfg.iterations + 1):
            w2c = se3_exp(torch.cat([rho, omega])) @ w2c0
            out = render(frozen, w2c, obs.camera, backend=self.backend)
            loss = tracking_loss(out, obs, cfg.w_color, cfg.w_depth, cfg.w_semantic, cfg.silhouette_threshold)
            value = loss.item()
            if value < best_loss:
                best_loss, best_w2c = value, w2c.detach()
            history.append(value)
            if self._converged(history):
                break
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            decay.step()
        return TrackingResult(invert_pose(best_w2c), best_loss, iterations)

    def _converged(self, history: list[float]) -> bool:
        p = self.cfg.patience
        if len(history) <= p:
            return False
        old, new = min(history[:-p]), min(history[-p:])
        return old - new <= self.cfg.convergence_tolerance * max(abs(old), 1e-12)
