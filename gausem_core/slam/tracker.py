"""Frame-to-model tracking (paper Eq. 2): optimise the camera pose through the renderer with the Gaussians frozen."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from gausem_core.config import TrackingConfig, check_gap_mode
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, project_to_se3, se3_exp, se3_log
from gausem_core.render import render
from gausem_core.slam.adam import AdamSteps, ParameterGroup, has_stalled
from gausem_core.slam.device_alignment import align_level_on_device
from gausem_core.slam.direct_alignment import (AlignmentWeights, ModelView, ObservedImages, align_level,
                                                alignment_cost, compared_costs, model_samples, normal_equations)
from gausem_core.slam.keyframe_view import KeyframeView, fill_from_keyframe
from gausem_core.slam.losses import tracking_loss
from gausem_core.slam.observation import Observation
from gausem_core.slam.photometric import local_contrast

METHODS = ("gauss_newton", "adam")
MODEL_VIEWS = ("per_level", "per_frame")
FULL_RESOLUTION_POINTS = ("all", "checkerboard")


@dataclass
class TrackingResult:
    cam_to_world: torch.Tensor  # (4, 4), in the frame of the cloud (the submap)
    loss: float
    iterations: int
    view: ModelView | None = None  # the full-resolution model view (colour as rendered) the pose was aligned against
    motion: torch.Tensor | None = None  # observed-from-model camera: from where ``view`` was rendered to the pose


def constant_velocity(previous: torch.Tensor, before_previous: torch.Tensor | None) -> torch.Tensor:
    """Predict the next cam_to_world by repeating the last relative motion (identity motion with one pose)."""
    if before_previous is None:
        return previous.clone()
    return repeat_motion(previous, invert_pose(before_previous) @ previous)


def repeat_motion(pose: torch.Tensor, relative: torch.Tensor, steps: float = 1) -> torch.Tensor:
    """``pose`` moved on by the relative motion ``relative`` (pose-from-next) ``steps`` times, projected onto SE(3):
    a whole number of steps as repeated products, a fractional one along the screw motion, ``exp(steps log
    relative)``."""
    if not steps > 0:
        raise ValueError(f"repeat_motion: steps must be > 0, got {steps}")
    if steps != int(steps):
        return project_to_se3(pose @ se3_exp(se3_log(relative.double()) * steps).to(pose.dtype))
    for _ in range(int(steps)):
        pose = pose @ relative
    return project_to_se3(pose)


def alignment_weights(cfg: TrackingConfig) -> AlignmentWeights:
    """The Gauss-Newton alignment's weights and tolerances from the tracking config."""
    return AlignmentWeights(cfg.w_color, cfg.w_semantic, cfg.w_depth, cfg.huber_delta, cfg.max_depth_residual,
                            cfg.max_depth_slope)


def model_view(cloud: GaussianCloud, cam_to_world: torch.Tensor, camera, cfg: TrackingConfig,
               backend: str, keyframe: KeyframeView | None = None) -> ModelView:
    """The map rendered at ``cam_to_world``, masked to its silhouette (alpha above ``silhouette_threshold``); with a
    ``keyframe``, its own images fill the pixels outside the silhouette (frame-to-keyframe, ``slam.keyframe_view``)."""
    out = render(cloud, invert_pose(cam_to_world), camera, backend=backend)
    view = ModelView(out.color, out.semantic, out.expected_depth, out.alpha > cfg.silhouette_threshold, camera)
    return view if keyframe is None else fill_from_keyframe(view, cam_to_world, keyframe)


def motion_size(motion: torch.Tensor, view: ModelView) -> float:
    """How far ``motion`` moves ``view``'s camera: translation over the view's median depth plus rotation in
    radians (inf for an empty view)."""
    if math.isinf(view.median_depth):
        return math.inf
    cos = ((motion[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return float(motion[:3, 3].norm() / view.median_depth + torch.arccos(cos))


def inspect_pose(cloud: GaussianCloud, obs: Observation, cam_to_world: torch.Tensor, cfg: TrackingConfig,
                 backend: str, tracked: TrackingResult | None = None, keyframe: KeyframeView | None = None
                 ) -> tuple[ModelView, torch.Tensor, torch.Tensor | None]:
    """What tracking health is judged from: a model view, the motion (observed-from-model camera) that brings it to
    ``cam_to_world``, and the Gauss-Newton Hessian (6, 6) of the full-resolution alignment there (None when the views
    barely overlap). The view that ``tracked`` (the result at ``cam_to_world``) was aligned against serves when the
    pose moved at most ``rerender_motion`` from it, as it would in tracking; else the model is rendered at the pose
    (identity motion), ``keyframe`` filling it as tracking's views are filled."""
    with torch.no_grad():
        if (tracked is not None and tracked.view is not None
                and motion_size(tracked.motion, tracked.view) <= cfg.gauss_newton.rerender_motion):
            view, motion = tracked.view, tracked.motion
        else:
            cloud = cloud.detach()
            view = model_view(cloud, cam_to_world.detach().to(cloud.dtype), obs.camera, cfg, backend, keyframe)
            motion = torch.eye(4, dtype=cloud.dtype, device=cloud.means.device)
        observed = ObservedImages.build(obs.rgb, obs.semantic, obs.depth, obs.camera)
        step = normal_equations(observed, motion, alignment_weights(cfg), *model_samples(view, observed))
    return view, motion, None if step is None else step[0]


class Tracker:
    """Estimate a frame's pose against the frozen Gaussians of a submap by minimising Eq. 2.

    ``method="gauss_newton"`` (default): coarse-to-fine IRLS Gauss-Newton on the Eq. 2 residuals, linearised through
    the observed images against model views rendered at the current estimate (see ``direct_alignment``).
    ``method="adam"``: the paper's optimiser, Adam on a twist xi applied on the left of world_to_cam
    (world_to_cam = exp(xi) @ world_to_cam_0) with gradients through the renderer; learning rates decay
    exponentially to ``adam.final_lr_fraction`` over the iterations and the best pose seen is returned.
    """

    def __init__(self, cfg: TrackingConfig, backend: str = "auto"):
        if cfg.method not in METHODS:
            raise ValueError(f"tracking.method must be one of {METHODS}, got {cfg.method!r}")
        if cfg.gauss_newton.model_views not in MODEL_VIEWS:
            raise ValueError(f"tracking.gauss_newton.model_views must be one of {MODEL_VIEWS}, got "
                             f"{cfg.gauss_newton.model_views!r}")
        if cfg.gauss_newton.full_resolution_points not in FULL_RESOLUTION_POINTS:
            raise ValueError(f"tracking.gauss_newton.full_resolution_points must be one of {FULL_RESOLUTION_POINTS}, "
                             f"got {cfg.gauss_newton.full_resolution_points!r}")
        if not cfg.gauss_newton.keep_start_margin >= 0:
            raise ValueError(f"tracking.gauss_newton.keep_start_margin must be >= 0, got "
                             f"{cfg.gauss_newton.keep_start_margin!r}")
        check_gap_mode("tracking.gauss_newton.search", cfg.gauss_newton.search)
        self.cfg = cfg
        self.backend = backend

    def track(self, cloud: GaussianCloud, obs: Observation, init_cam_to_world: torch.Tensor,
              alternatives: Sequence[torch.Tensor] = (), search: bool = False,
              keyframe: KeyframeView | None = None) -> TrackingResult:
        """Optimise the pose from ``init_cam_to_world``; Gauss-Newton also tries ``alternatives`` (e.g. the previous
        pose when the motion model overshoots a sudden stop) on the coarsest level and goes on from the best, with
        ``search`` the starts around ``init_cam_to_world`` that ``gauss_newton.search_*`` describe, and with a
        ``keyframe`` its own images where the map renders no silhouette (see :func:`model_view`)."""
        if self.cfg.method == "gauss_newton":
            init = init_cam_to_world.detach()
            starts = [init, *alternatives, *(self._search_starts(init) if search else [])]
            return self._track_gauss_newton(cloud.detach(), obs, starts, keyframe)
        return self._track_adam(cloud, obs, init_cam_to_world)

    def _search_starts(self, pose: torch.Tensor) -> list[torch.Tensor]:
        """``pose`` moved by ``search_translation`` along, and turned by ``search_rotation_deg`` about, each camera
        axis, both ways."""
        cfg = self.cfg.gauss_newton
        steps = ((cfg.search_translation, range(3)), (math.radians(cfg.search_rotation_deg), range(3, 6)))
        offsets = [step * sign * torch.eye(6, dtype=torch.float64)[axis]
                   for step, axes in steps if step > 0 for axis in axes for sign in (1, -1)]
        return [pose @ se3_exp(offset).to(pose) for offset in offsets]

    def _track_gauss_newton(self, cloud: GaussianCloud, obs: Observation, starts: list[torch.Tensor],
                            keyframe: KeyframeView | None) -> TrackingResult:
        """Coarse-to-fine Gauss-Newton from the start whose coarsest-level alignment costs least; keeps that start if
        the result explains the full-resolution frame worse (coarse levels can leave the basin of convergence when
        the map covers little of the view)."""
        cfg, weights = self.cfg.gauss_newton, alignment_weights(self.cfg)
        rgb = local_contrast(obs.rgb, cfg.color_normalisation_width)  # compared with the model views' colour
        pyramid = ObservedImages.build(rgb, obs.semantic, obs.depth, obs.camera).pyramid(cfg.pyramid_levels,
                                                                                         cfg.coarsest_width)
        if cfg.model_views == "per_frame":
            with torch.no_grad():
                return self._track_per_frame(cloud, [start.to(cloud.dtype) for start in starts], pyramid, weights,
                                             keyframe)
        eye = torch.eye(4, dtype=cloud.dtype, device=cloud.means.device)
        with torch.no_grad():
            coarse = [self._align(cloud, start.to(cloud.dtype), pyramid[-1], weights, eye, keyframe)
                      for start in starts]
            best = min(range(len(starts)), key=lambda i: alignment_cost(
                self._model_view(cloud, coarse[i], pyramid[-1].camera, keyframe), pyramid[-1], eye, weights))
            initial, pose = starts[best].to(cloud.dtype), coarse[best]
            for level in reversed(pyramid[:-1]):
                pose = self._align(cloud, pose, level, weights, eye, keyframe)
            iterations = cfg.renders_per_level * (len(pyramid) - 1 + len(starts))
            full = pyramid[0]
            cost = alignment_cost(self._model_view(cloud, pose, full.camera, keyframe), full, eye, weights)
            initial_cost = alignment_cost(self._model_view(cloud, initial, full.camera, keyframe), full, eye,
                                          weights)
        if initial_cost < cost:
            return TrackingResult(initial, initial_cost, iterations)
        return TrackingResult(project_to_se3(pose), cost, iterations)

    def _track_per_frame(self, cloud: GaussianCloud, starts: list[torch.Tensor], pyramid: list[ObservedImages],
                         weights: AlignmentWeights, keyframe: KeyframeView | None) -> TrackingResult:
        """Coarse-to-fine Gauss-Newton, ``renders_per_level`` rounds of ``level_iterations`` per level, against one
        model view rendered at the first start and downsampled for the coarser levels; the estimate is the view's
        pose moved by ``motion`` (observed-from-model camera), and a round renders the view again at the estimate
        only when that moved ``rerender_motion`` from it. The start whose coarsest rounds cost least goes on
        (:meth:`_best_start`); a start is kept instead if it explains the full-resolution frame better than the result
        by more than ``keep_start_margin`` (:func:`compared_costs` on the last view: the view's border that leaves the
        image under any of the poses left out), all costs from the views already rendered; the pose kept carries its
        cost."""
        cfg = self.cfg.gauss_newton
        base = starts[0]
        rendered, views = self._view_pyramid(cloud, base, pyramid, keyframe)
        begun = [invert_pose(start) @ base for start in starts]
        best, motion = self._best_start(views[-1], pyramid[-1], begun)
        renders = 1
        rounds = [index for index in reversed(range(len(pyramid) - 1)) for _ in range(cfg.renders_per_level)]
        for index in rounds:
            if motion_size(motion, views[0]) > cfg.rerender_motion:
                base, motion = base @ invert_pose(motion), torch.eye(4, dtype=motion.dtype, device=motion.device)
                (rendered, views), renders = self._view_pyramid(cloud, base, pyramid, keyframe), renders + 1
            motion = self._align_level(views[index], pyramid[index], motion)
        poses = [project_to_se3(base @ invert_pose(motion)), *starts]
        costs = compared_costs(views[0], pyramid[0], [invert_pose(pose) @ base for pose in poses], weights)
        start = min(range(1, len(poses)), key=costs.__getitem__)
        kept = start if costs[start] * (1 + cfg.keep_start_margin) < costs[0] else 0
        return TrackingResult(poses[kept], costs[kept], renders, rendered, invert_pose(poses[kept]) @ base)

    def _best_start(self, view: ModelView, level: ObservedImages,
                    motions: list[torch.Tensor]) -> tuple[int, torch.Tensor]:
        """Which of the start ``motions`` costs least after ``renders_per_level`` rounds on ``level`` against
        ``view`` (:func:`compared_costs`: the view's border that leaves the image under any of them left out), and
        its motion."""
        weights, rounds = alignment_weights(self.cfg), self.cfg.gauss_newton.renders_per_level
        aligned = [self._align_level(view, level, motion, rounds) for motion in motions]
        if len(aligned) == 1:
            return 0, aligned[0]
        costs = compared_costs(view, level, aligned, weights)
        best = min(range(len(motions)), key=costs.__getitem__)
        return best, aligned[best]

    def _view_pyramid(self, cloud: GaussianCloud, cam_to_world: torch.Tensor, pyramid: list[ObservedImages],
                      keyframe: KeyframeView | None) -> tuple[ModelView, list[ModelView]]:
        """The model rendered once at ``cam_to_world`` at full resolution (returned as rendered too), its colour
        compared as the observation's is, and halved to match ``pyramid``'s levels (as the observation's pyramid is
        made); the full-resolution view keeps ``full_resolution_points``."""
        rendered = model_view(cloud, cam_to_world, pyramid[0].camera, self.cfg, self.backend, keyframe)
        views = [self._compared(rendered)]
        while len(views) < len(pyramid):
            views.append(views[-1].downsampled())
        if self.cfg.gauss_newton.full_resolution_points == "checkerboard":
            views[0] = views[0].checkerboard()
        return rendered, views

    def _align(self, cloud: GaussianCloud, pose: torch.Tensor, level: ObservedImages, weights: AlignmentWeights,
               eye: torch.Tensor, keyframe: KeyframeView | None) -> torch.Tensor:
        """``renders_per_level`` rounds of render-at-the-estimate + Gauss-Newton on one pyramid level."""
        for _ in range(self.cfg.gauss_newton.renders_per_level):
            view = self._model_view(cloud, pose, level.camera, keyframe)
            pose = pose @ invert_pose(self._align_level(view, level, eye))
        return pose

    def _align_level(self, view: ModelView, level: ObservedImages, motion: torch.Tensor,
                     rounds: int = 1) -> torch.Tensor:
        """``motion`` after ``rounds`` rounds of ``level_iterations`` Gauss-Newton steps (fewer once a step is below
        ``min_step``)."""
        cfg = self.cfg.gauss_newton
        iterations, weights = cfg.level_iterations * rounds, alignment_weights(self.cfg)
        if view.depth.device.type == "cpu":
            return align_level(view, level, motion, weights, iterations, min_step=cfg.min_step)[0]
        return align_level_on_device(view, level, motion, weights, iterations, min_step=cfg.min_step,
                                     fused=cfg.fused)[0]  # no host sync per step

    def _model_view(self, cloud: GaussianCloud, cam_to_world: torch.Tensor, camera,
                    keyframe: KeyframeView | None) -> ModelView:
        """The model view with the colour that is compared with the observation's (``slam.photometric``)."""
        return self._compared(model_view(cloud, cam_to_world, camera, self.cfg, self.backend, keyframe))

    def _compared(self, view: ModelView) -> ModelView:
        """``view`` with its colour as it is compared with the observation's (``slam.photometric``)."""
        return replace(view, color=local_contrast(view.color, self.cfg.gauss_newton.color_normalisation_width,
                                                  view.mask))

    def _track_adam(self, cloud: GaussianCloud, obs: Observation, init_cam_to_world: torch.Tensor) -> TrackingResult:
        cfg = self.cfg.adam
        frozen = cloud.detach()
        w2c0 = invert_pose(init_cam_to_world.detach()).to(frozen.dtype)
        rho = torch.zeros(3, dtype=w2c0.dtype, device=w2c0.device, requires_grad=True)
        omega = torch.zeros(3, dtype=w2c0.dtype, device=w2c0.device, requires_grad=True)
        adam = AdamSteps([ParameterGroup([rho], cfg.lr_translation, cfg.final_lr_fraction),
                          ParameterGroup([omega], cfg.lr_rotation, cfg.final_lr_fraction)],
                         horizon=max(cfg.iterations, 1))
        best_loss, best_w2c, history = float("inf"), w2c0, []
        iterations = 0
        for iterations in range(1, cfg.iterations + 1):
            w2c = se3_exp(torch.cat([rho, omega])) @ w2c0
            out = render(frozen, w2c, obs.camera, backend=self.backend)
            loss = tracking_loss(out, obs, self.cfg.w_color, self.cfg.w_depth, self.cfg.w_semantic,
                                 self.cfg.silhouette_threshold)
            value = loss.item()
            if value < best_loss:
                best_loss, best_w2c = value, w2c.detach()
            history.append(value)
            if has_stalled(history, cfg.patience, cfg.convergence_tolerance):
                break
            adam.step(loss)
        return TrackingResult(invert_pose(best_w2c), best_loss, iterations)
