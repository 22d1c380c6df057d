"""Semantic-Guided Registration of two submaps (paper §III-B): the coarse step (Eq. 5) and the fine step (Eq. 6).

Conventions: keyframe poses are cam_to_world in their own submap's frame; the result ``T`` maps source-submap
coordinates to target-submap coordinates, so a source keyframe and a target keyframe that see the place from the
same viewpoint satisfy ``T_t ≈ T @ T_s``. (With world-from-anchor poses A_s, A_t of the two submaps, T = A_t^-1 A_s.)

Fine step (unidirectional, Gaussians frozen), at the keyframe resolution divided by ``downsample``: each selected
source keyframe pose T_s^i is rendered once in the SOURCE submap (colour, semantics, depth: the reference of Eq. 6)
and the TARGET submap is rendered at T T_s^i. The colour + lambda_sem * semantic + lambda_feat * feature
(+ w_depth * depth) residuals between the two are minimised by the tracker's coarse-to-fine IRLS Gauss-Newton
(:func:`~gausem_core.slam.direct_alignment.align_level`), one view at a time; the per-view corrected poses are fused
into one T by Eq. 5's Gauss-Newton on SE(3), and the target is re-rendered at the fused T for the next pyramid level.
The feature residuals are per-pixel channels like colour: the dense features of each rendered semantic image
(DINOv2 patch tokens, or the fallback's), L2-normalised, projected onto the ``feature_channels`` principal directions
of the source views' features and upsampled to the render, at the pyramid levels no finer than the patch grid (finer,
they would move with the grid rather than the content). The Eq. 6 loss reported at the result uses the full
features. There too the overlap (the fraction of source-view pixels the target renders as well) and the fitness
(the fraction of those where the two agree in depth and class) are measured. The spread of the per-view estimates
around the fused T is the registration's uncertainty: with overlap and fitness it decides acceptance, and it sets
the loop edge's standard deviations.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gausem_core.config import RegistrationConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, invert_pose, make_pose, se3_exp, se3_log
from gausem_core.render import render
from gausem_core.semantics.descriptors import DescriptorExtractor
from gausem_core.slam.direct_alignment import AlignmentWeights, ModelView, ObservedImages, align_level
from gausem_core.slam.observation import Observation

_JACOBIAN_STEP = 1e-6  # central-difference step (rad / m) of the numerical Jacobian, in float64


@dataclass(frozen=True)
class CoarseRegistration:
    """Result of :func:`coarse_registration`.

    transform (4, 4) source -> target; pairs (k, 2) matched (source, target) keyframe indices, closest descriptors
    first; rms: sqrt of the mean squared residual norm ||log(T_t^-1 T T_s)|| over the pairs (mixed metres and
    radians, as in Eq. 5); iterations: Gauss-Newton iterations run.
    """

    transform: torch.Tensor
    pairs: torch.Tensor
    rms: float
    iterations: int


def top_k_descriptor_pairs(source: torch.Tensor, target: torch.Tensor, k: int = 10,
                           max_distance: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The k (source, target) index pairs with the smallest L2 distance between L2-normalised descriptors.

    source (S, D), target (T, D) -> pairs (min(k, S*T), 2) long, distances (same length,), closest first.
    ``max_distance``: drop pairs at this distance or more, but always keep the closest pair.
    """
    if source.dim() != 2 or target.dim() != 2 or source.shape[1] != target.shape[1]:
        raise ValueError(f"top_k_descriptor_pairs: need (S, D) and (T, D) descriptors, got {tuple(source.shape)} "
                         f"and {tuple(target.shape)}")
    if source.shape[0] == 0 or target.shape[0] == 0:
        raise ValueError("top_k_descriptor_pairs: both submaps need at least one keyframe descriptor")
    if k <= 0:
        raise ValueError(f"top_k_descriptor_pairs: k must be positive, got {k}")
    s = torch.nn.functional.normalize(source.to(torch.float64), dim=1)
    t = torch.nn.functional.normalize(target.to(torch.float64), dim=1)
    dist = torch.cdist(s, t).flatten()
    distances, flat = torch.sort(dist, stable=True)
    flat, distances = flat[:k], distances[:k]
    if max_distance is not None:
        keep = max(int((distances < max_distance).sum()), 1)
        flat, distances = flat[:keep], distances[:keep]
    return torch.stack([flat // t.shape[0], flat % t.shape[0]], 1), distances


def chordal_mean_alignment(source_poses: torch.Tensor, target_poses: torch.Tensor) -> torch.Tensor:
    """Closed-form estimate of T from pose pairs: the chordal mean of T_t^i (T_s^i)^-1.

    Rotation: the SO(3) projection (SVD) of the summed rotations; translation: the mean translation. (K, 4, 4) each.
    """
    _check_pose_pairs(source_poses, target_poses, "chordal_mean_alignment")
    candidates = target_poses.to(torch.float64) @ invert_pose(source_poses.to(torch.float64))
    u, _, vt = torch.linalg.svd(candidates[:, :3, :3].sum(0))
    fix = torch.diag(torch.cat([torch.ones(2, dtype=u.dtype, device=u.device), torch.sign(torch.det(u @ vt))[None]]))
    return make_pose(u @ fix @ vt, candidates[:, :3, 3].mean(0)).to(source_poses.dtype)


def gauss_newton_alignment(source_poses: torch.Tensor, target_poses: torch.Tensor, init: torch.Tensor | None = None,
                           max_iterations: int = 20, tolerance: float = 1e-10) -> tuple[torch.Tensor, float, int]:
    """Eq. 5: T = argmin sum_i ||log(T_t^i^-1 T T_s^i)||^2 by Gauss-Newton on SE(3), in float64.

    The update is left-multiplied, T <- exp(delta) T; the Jacobian of the residuals w.r.t. delta is taken by central
    differences (accurate to ~1e-9, far below what moves the solution). ``init`` defaults to
    :func:`chordal_mean_alignment`. Stops when |delta| < ``tolerance``. Returns (T, residual RMS, iterations).
    """
    _check_pose_pairs(source_poses, target_poses, "gauss_newton_alignment")
    if init is not None and (init.shape != (4, 4) or not torch.isfinite(init).all()):
        raise ValueError(f"gauss_newton_alignment: init must be a finite 4x4 pose, got shape {tuple(init.shape)}")
    src, tgt = source_poses.to(torch.float64), target_poses.to(torch.float64)
    tgt_inv = invert_pose(tgt)
    transform = (chordal_mean_alignment(src, tgt) if init is None else init).to(torch.float64)
    eye = torch.eye(6, dtype=torch.float64, device=src.device)
    steps = _JACOBIAN_STEP * torch.cat([eye, -eye])

    def residuals(candidates: torch.Tensor) -> torch.Tensor:  # (..., 4, 4) -> (..., K * 6)
        return se3_log(tgt_inv @ candidates[..., None, :, :] @ src).flatten(-2)

    iterations = 0
    for iterations in range(1, max_iterations + 1):
        r = residuals(transform)
        perturbed = residuals(se3_exp(steps) @ transform)  # (12, K * 6)
        jac = ((perturbed[:6] - perturbed[6:]) / (2 * _JACOBIAN_STEP)).T  # (K * 6, 6)
        delta = -torch.linalg.solve(jac.T @ jac, jac.T @ r)
        transform = se3_exp(delta) @ transform
        if float(delta.norm()) < tolerance:
            break
    r = residuals(transform).reshape(-1, 6)
    rms = float(r.pow(2).sum(1).mean().sqrt())
    return transform.to(source_poses.dtype), rms, iterations


def coarse_registration(source_descriptors: torch.Tensor, source_poses: torch.Tensor,
                        target_descriptors: torch.Tensor, target_poses: torch.Tensor, k: int = 10,
                        init: torch.Tensor | None = None, max_iterations: int = 20,
                        max_distance: float | None = None, consensus: tuple[float, float] | None = None,
                        seed: tuple[int, int] | None = None) -> CoarseRegistration:
    """SGR coarse step: match the k closest keyframe descriptor pairs, then solve Eq. 5 on their poses.

    Descriptors (S, D) / (T, D) and cam_to_world poses (S, 4, 4) / (T, 4, 4) of the keyframes of the source and
    target submaps, each pose in its own submap's frame. ``init`` defaults to the chordal mean of the matched pairs;
    ``max_distance`` drops all but the closest pair at that descriptor distance or more (views of other places);
    ``consensus`` (metres, radians) keeps only the pairs that agree on T within these tolerances
    (:func:`consistent_pairs`), so that look-alike views of other places do not bias Eq. 5: those that agree with the
    ``seed`` pair (source index, target index; e.g. the detected loop, always kept first), else the largest such set.
    """
    if source_descriptors.shape[0] != source_poses.shape[0] or target_descriptors.shape[0] != target_poses.shape[0]:
        raise ValueError(f"coarse_registration: descriptor and pose counts differ (source "
                         f"{source_descriptors.shape[0]} vs {source_poses.shape[0]}, target "
                         f"{target_descriptors.shape[0]} vs {target_poses.shape[0]})")
    pairs, _ = top_k_descriptor_pairs(source_descriptors, target_descriptors, k, max_distance)
    if seed is not None:
        seed_pair = torch.tensor([seed], dtype=pairs.dtype, device=pairs.device)
        pairs = torch.cat([seed_pair, pairs[(pairs != seed_pair).any(1)]])
    if consensus is not None:
        keep = consistent_pairs(source_poses[pairs[:, 0]], target_poses[pairs[:, 1]], *consensus,
                                reference=0 if seed is not None else None)
        pairs = pairs[keep]
    transform, rms, iterations = gauss_newton_alignment(source_poses[pairs[:, 0]], target_poses[pairs[:, 1]], init,
                                                        max_iterations)
    return CoarseRegistration(transform, pairs, rms, iterations)


def consistent_pairs(source_poses: torch.Tensor, target_poses: torch.Tensor, max_translation: float,
                     max_rotation: float, reference: int | None = None) -> torch.Tensor:
    """Indices (ascending) of the pose pairs whose single-pair estimates T_t^i (T_s^i)^-1 lie within
    ``max_translation`` (m) and ``max_rotation`` (rad) of pair ``reference``'s; with no reference, of the pair that
    gathers the most (ties go to the earlier, closer pair)."""
    _check_pose_pairs(source_poses, target_poses, "consistent_pairs")
    single = target_poses.to(torch.float64) @ invert_pose(source_poses.to(torch.float64))
    relative = invert_pose(single)[:, None] @ single[None]  # (K, K, 4, 4): hypothesis i vs pair j
    agree = ((relative[..., :3, 3].norm(dim=-1) <= max_translation)
             & (se3_log(relative)[..., 3:].norm(dim=-1) <= max_rotation))
    best = int(torch.argmax(agree.sum(1))) if reference is None else reference  # argmax: the first maximum
    return torch.nonzero(agree[best]).squeeze(1)


def _check_pose_pairs(source: torch.Tensor, target: torch.Tensor, where: str) -> None:
    if source.dim() != 3 or source.shape[1:] != (4, 4) or source.shape != target.shape or source.shape[0] == 0:
        raise ValueError(f"{where}: need two non-empty (K, 4, 4) pose stacks of equal length, got "
                         f"{tuple(source.shape)} and {tuple(target.shape)}")
    if not (torch.isfinite(source).all() and torch.isfinite(target).all()):
        raise ValueError(f"{where}: poses contain non-finite values")


@dataclass(frozen=True)
class FineRegistration:
    """Result of :func:`fine_registration`.

    transform (4, 4) float64 source -> target; overlap: fraction of the source views' rendered pixels that the target
    renders too; fitness: fraction of those overlapping pixels where the depths agree within ``max_depth_residual``
    and the semantic colours within ``max_semantic_residual``; loss: Eq. 6 averaged over the views; spread (rotation
    rad, translation m): RMS disagreement of the per-view estimates with ``transform``; views: views that contributed.
    """

    transform: torch.Tensor
    overlap: float
    fitness: float
    loss: float
    spread: tuple[float, float]
    views: int


@dataclass(frozen=True)
class Registration:
    """Coarse + fine SGR: the transform (float64, source -> target), the fine result, and the acceptance verdict.

    sigmas (rotation rad, translation m): standard deviations for the loop edge, the fine spread floored by the
    configured sigmas. seconds_coarse / seconds_fine: wall-clock split of the two steps.
    """

    transform: torch.Tensor
    coarse: CoarseRegistration
    fine: FineRegistration
    accepted: bool
    sigmas: tuple[float, float]
    seconds_coarse: float
    seconds_fine: float


class FeatureProjection:
    """Dense features (h, w, D) -> pixel-resolution feature channels (H, W, F): L2-normalised, centred and projected
    onto the top F principal directions of the reference features it was built from, then upsampled bilinearly."""

    def __init__(self, reference: torch.Tensor, channels: int):
        flat = F.normalize(reference.reshape(-1, reference.shape[-1]), dim=1)
        self.mean = flat.mean(0)
        self.basis = torch.linalg.svd(flat - self.mean, full_matrices=False)[2][:channels].T

    def __call__(self, dense: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        projected = (F.normalize(dense, dim=-1) - self.mean) @ self.basis
        return F.interpolate(projected.permute(2, 0, 1)[None], size=size, mode="bilinear",
                             align_corners=False)[0].permute(1, 2, 0)


def _source_views(cloud: GaussianCloud, poses: torch.Tensor, camera: PinholeCamera, cfg: RegistrationConfig,
                  features: DescriptorExtractor | None,
                  backend: str) -> tuple[list[list[ObservedImages]], FeatureProjection | None]:
    """Render the source submap at its keyframe poses: one image pyramid (finest first) per view. With ``features``
    and the feature term on, the levels whose pixels are no finer than the feature patch grid carry the features of
    their own semantic image (as the target's renders at those levels will), projected on the principal directions
    of those features; at finer levels the features would move with the grid, not with the content, and bias the fit.
    """
    pyramids = []
    for pose in poses:
        out = render(cloud, _world_to_cam(pose, cloud), camera, backend=backend)
        depth = torch.where(out.alpha > cfg.silhouette_threshold, out.expected_depth, torch.zeros_like(out.depth))
        pyramids.append(ObservedImages.build(out.color, out.semantic, depth, camera).pyramid(
            cfg.pyramid_levels, cfg.coarsest_width // cfg.downsample))
    if features is None or cfg.lambda_feat <= 0 or cfg.feature_channels <= 0:
        return pyramids, None
    dense, grid_rows = {}, None  # (view, level) -> patch features, coarsest level first, while the grid is as fine
    for view, pyramid in enumerate(pyramids):  # as the pixels (its rows do not depend on the input size)
        for level in reversed(range(len(pyramid))):
            rows = pyramid[level].stack.shape[1]
            if grid_rows is not None and grid_rows < rows:
                break
            patches = features.dense_features(pyramid[level].stack[3:6].permute(1, 2, 0))
            grid_rows = patches.shape[0]
            if grid_rows < rows:
                break
            dense[view, level] = patches
    if not dense:
        return pyramids, None
    projection = FeatureProjection(torch.cat([d.reshape(-1, d.shape[-1]) for d in dense.values()]),
                                   cfg.feature_channels)
    for (view, level), patches in dense.items():
        images = pyramids[view][level]
        pyramids[view][level] = images.with_features(projection(patches, images.stack.shape[1:]))
    return pyramids, projection


def _world_to_cam(cam_to_world: torch.Tensor, cloud: GaussianCloud) -> torch.Tensor:
    return invert_pose(cam_to_world).to(device=cloud.device, dtype=cloud.dtype)


def _spread(source_poses: torch.Tensor, corrected: torch.Tensor, transform: torch.Tensor) -> tuple[float, float]:
    """RMS rotation (rad) and translation (m) of corrected_i^-1 T T_s^i over the views."""
    error = invert_pose(corrected) @ transform @ source_poses
    rotation = se3_log(error)[:, 3:].norm(dim=1)
    return float(rotation.pow(2).mean().sqrt()), float(error[:, :3, 3].norm(dim=1).pow(2).mean().sqrt())


def fine_registration(source: GaussianCloud, target: GaussianCloud, source_poses: torch.Tensor,
                      camera: PinholeCamera, init: torch.Tensor, cfg: RegistrationConfig,
                      features: DescriptorExtractor | None = None, backend: str = "auto",
                      alternatives: Sequence[torch.Tensor] = ()) -> FineRegistration:
    """SGR fine step (Eq. 6): refine ``init`` (source -> target, 4x4) with both submaps' Gaussians frozen.

    ``source_poses`` (V, 4, 4): the source keyframe poses to compare the submaps from; ``features``: the dense
    semantic feature extractor of the Eq. 6 feature term (None leaves the term out of the reported loss). Both clouds
    must be on one device; poses and the result are float64 on the CPU. ``alternatives``: other starts (e.g. the
    current estimate from the anchors); the refinement starts from the one of ``init`` and these at which the most
    source pixels agree with the target (overlap x fitness; ``init`` on a tie).
    """
    if source_poses.dim() != 3 or source_poses.shape[1:] != (4, 4) or source_poses.shape[0] == 0:
        raise ValueError(f"fine_registration: need (V, 4, 4) source poses, got {tuple(source_poses.shape)}")
    src = source_poses.to("cpu", torch.float64)
    transform = init.to("cpu", torch.float64)
    camera = camera.scaled(camera.width // cfg.downsample, camera.height // cfg.downsample)
    weights = AlignmentWeights(1.0, cfg.lambda_sem, cfg.w_depth, max_depth_residual=cfg.max_depth_residual,
                               feature=cfg.lambda_feat)
    with torch.no_grad():
        pyramids, projection = _source_views(source, src, camera, cfg, features, backend)
        if alternatives:
            transform = max([transform, *(a.to("cpu", torch.float64) for a in alternatives)],
                            key=lambda t: _agreement(target, t, src, pyramids, cfg, backend))
        used = torch.zeros(0, dtype=torch.long)
        corrected = src[:0]
        for level in [l for l in reversed(range(len(pyramids[0]))) for _ in range(cfg.renders_per_level)]:
            poses, ok = [], []
            for i, pyramid in enumerate(pyramids):
                observed = pyramid[level]
                model_pose = transform @ src[i]
                out = render(target, _world_to_cam(model_pose, target), observed.camera, backend=backend)
                channels = (projection(features.dense_features(out.semantic), out.depth.shape)
                            if observed.feature_channels else None)
                model = ModelView(out.color, out.semantic, out.expected_depth, out.alpha > cfg.silhouette_threshold,
                                  observed.camera, channels)
                eye = torch.eye(4, dtype=out.color.dtype, device=out.color.device)
                motion, cost = align_level(model, observed, eye, weights, cfg.iterations)
                if math.isfinite(cost):
                    poses.append(model_pose @ invert_pose(motion.to("cpu", torch.float64)))
                    ok.append(i)
            if not ok:
                break
            used, corrected = torch.tensor(ok), torch.stack(poses)
            transform, _, _ = gauss_newton_alignment(src[used], corrected, init=transform, max_iterations=5)
        spread = _spread(src[used], corrected, transform) if len(used) else (math.inf, math.inf)
        overlap, fitness, loss = _evaluate(target, transform, src, pyramids, cfg, features, backend)
    return FineRegistration(transform, overlap, fitness, loss, spread, len(used))


def _agreement(target: GaussianCloud, transform: torch.Tensor, source_poses: torch.Tensor,
               pyramids: list[list[ObservedImages]], cfg: RegistrationConfig, backend: str) -> float:
    """Fraction of the source views' pixels that the target at ``transform`` renders and agrees with (overlap x
    fitness): how good a start ``transform`` is."""
    overlap, fitness, _ = _evaluate(target, transform, source_poses, pyramids, cfg, None, backend)
    return overlap * fitness


def _evaluate(target: GaussianCloud, transform: torch.Tensor, source_poses: torch.Tensor,
              pyramids: list[list[ObservedImages]], cfg: RegistrationConfig, features: DescriptorExtractor | None,
              backend: str) -> tuple[float, float, float]:
    """Overlap, fitness and Eq. 6 loss of ``transform`` over the views (finest pyramid level)."""
    agreeing, overlapping, total, losses = 0, 0, 0, []
    for pose, pyramid in zip(source_poses, pyramids):
        observed = pyramid[0]
        out = render(target, _world_to_cam(transform @ pose, target), observed.camera, backend=backend)
        color, semantic, depth = observed.stack[:3], observed.stack[3:6], observed.stack[6]
        seen = depth > 0
        both = seen & (out.alpha > cfg.silhouette_threshold)
        rendered_semantic = out.semantic.permute(2, 0, 1)
        agree = (((out.expected_depth - depth).abs() < cfg.max_depth_residual)
                 & ((rendered_semantic - semantic).abs().sum(0) < cfg.max_semantic_residual))
        agreeing += int((both & agree).sum())
        overlapping += int(both.sum())
        total += int(seen.sum())
        loss = 0.0
        if both.any():
            loss = float(((out.color.permute(2, 0, 1) - color).abs().sum(0)[both]).mean()
                         + cfg.lambda_sem * ((rendered_semantic - semantic).abs().sum(0)[both]).mean())
        if features is not None:
            dense = features.dense_features(torch.stack([rendered_semantic, semantic]).permute(0, 2, 3, 1))
            loss += cfg.lambda_feat * float((dense[0] - dense[1]).pow(2).sum(-1).mean())
        losses.append(loss)
    return overlapping / max(total, 1), agreeing / max(overlapping, 1), sum(losses) / len(losses)


def fine_views(pairs: torch.Tensor, source_poses: torch.Tensor, count: int) -> torch.Tensor:
    """Up to ``count`` source keyframe indices for the fine step: the distinct sources of the descriptor pairs
    (closest first), then the other source keyframes nearest to the first one (camera centres), which see much of
    the same place."""
    seen: list[int] = []
    for s in pairs[:, 0].tolist():
        if s not in seen:
            seen.append(s)
    centres = source_poses[:, :3, 3].to(torch.float64)
    by_distance = torch.argsort((centres - centres[seen[0]]).norm(dim=1), stable=True).tolist()
    seen += [s for s in by_distance if s not in seen]
    return torch.tensor(seen[:count], dtype=torch.long, device=source_poses.device)


def semantic_guided_registration(source_cloud: GaussianCloud, source_poses: torch.Tensor,
                                 source_descriptors: torch.Tensor, target_cloud: GaussianCloud,
                                 target_poses: torch.Tensor, target_descriptors: torch.Tensor,
                                 camera: PinholeCamera, cfg: RegistrationConfig,
                                 features: DescriptorExtractor | None = None, backend: str = "auto",
                                 max_pair_distance: float | None = None,
                                 loop_pair: tuple[int, int] | None = None,
                                 prior: torch.Tensor | None = None,
                                 seeds: Sequence[torch.Tensor] = ()) -> Registration:
    """Coarse (Eq. 5, top-k descriptor pairs closer than ``max_pair_distance`` that agree with each other, or with
    ``loop_pair`` (source index, target index) when given) then fine (Eq. 6) registration of the source submap to
    the target. ``prior``: the current estimate of the transform (from the anchors); the fine step starts from it
    instead of the coarse estimate when more source pixels agree with the target there (look-alike views can mislead
    Eq. 5, and a revisit under little drift is closer to the prior). ``seeds``: more such starts (a transform
    measured by geometric verification of the loop's keyframes).

    Keyframe poses (S, 4, 4) / (T, 4, 4) are cam_to_world in their own submap's frame, descriptors (S, D) / (T, D).
    Accepted by :func:`is_acceptable`.
    """
    start = time.perf_counter()
    coarse = coarse_registration(source_descriptors, source_poses, target_descriptors, target_poses, cfg.top_k,
                                 max_distance=max_pair_distance,
                                 consensus=(cfg.consensus_translation, math.radians(cfg.consensus_rotation_deg)),
                                 seed=loop_pair)
    middle = time.perf_counter()
    views = fine_views(coarse.pairs, source_poses, cfg.views)
    fine = fine_registration(source_cloud, target_cloud, source_poses[views], camera, coarse.transform, cfg,
                             features, backend, (*(() if prior is None else (prior,)), *seeds))
    end = time.perf_counter()
    return Registration(fine.transform, coarse, fine, is_acceptable(fine, cfg), edge_sigmas(fine, cfg),
                        middle - start, end - middle)


def is_acceptable(fine: FineRegistration, cfg: RegistrationConfig) -> bool:
    """Accept a fine registration: overlap and fitness at least ``min_overlap`` and ``min_fitness``, per-view
    estimates within the spread limits."""
    rotation, translation = fine.spread
    return (fine.overlap >= cfg.min_overlap and fine.fitness >= cfg.min_fitness
            and translation <= cfg.max_spread_translation
            and rotation <= math.radians(cfg.max_spread_rotation_deg))


def edge_sigmas(fine: FineRegistration, cfg: RegistrationConfig) -> tuple[float, float]:
    """Loop-edge standard deviations (rotation rad, translation m): the fine spread, floored by the config."""
    rotation, translation = fine.spread
    return max(cfg.sigma_rotation, rotation), max(cfg.sigma_translation, translation)


def align_keyframes(reference: Observation, current: Observation, init: torch.Tensor,
                    cfg: RegistrationConfig) -> tuple[torch.Tensor, tuple[float, float]]:
    """Relative pose of two keyframes from their images (intra-submap loops): the colour + lambda_sem * semantic
    (+ w_depth * depth) residuals of Eq. 6 between the two observations, minimised coarse-to-fine by Gauss-Newton.

    ``init``: current-camera-from-reference-camera (4x4) to start from. Returns that motion refined (float64) and
    :func:`warp_agreement` (overlap, fitness) under it, with ``max_depth_residual``.
    """
    weights = AlignmentWeights(1.0, cfg.lambda_sem, cfg.w_depth, max_depth_residual=cfg.max_depth_residual)
    reference_pyramid = ObservedImages.build(reference.rgb, reference.semantic, reference.depth,
                                             reference.camera).pyramid(cfg.pyramid_levels, cfg.coarsest_width)
    current_pyramid = ObservedImages.build(current.rgb, current.semantic, current.depth,
                                           current.camera).pyramid(cfg.pyramid_levels, cfg.coarsest_width)
    motion = init.to(reference.depth.device, reference.depth.dtype)
    with torch.no_grad():
        for ref, cur in zip(reversed(reference_pyramid), reversed(current_pyramid)):
            stack = ref.stack
            model = ModelView(stack[:3].permute(1, 2, 0), stack[3:6].permute(1, 2, 0), stack[6], stack[6] > 0,
                              ref.camera)
            motion, _ = align_level(model, cur, motion, weights, cfg.iterations)
        agreement = warp_agreement(reference, current, motion, cfg.max_depth_residual)
    return motion.to("cpu", torch.float64), agreement


def warp_agreement(reference: Observation, current: Observation, motion: torch.Tensor,
                   max_residual: float) -> tuple[float, float]:
    """(overlap, fitness) of two depth images under ``motion`` (current-camera-from-reference-camera): the fraction
    of the reference's valid-depth pixels that land in the current image on a depth reading (overlap), and the
    fraction of those whose depth agrees within ``max_residual`` (fitness)."""
    valid = reference.valid_depth
    motion = motion.to(reference.depth.device, reference.depth.dtype)
    points = reference.camera.backproject(reference.depth)[valid] @ motion[:3, :3].T + motion[:3, 3]
    cam = current.camera
    uv = cam.project(points)
    u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (points[:, 2] > 1e-3) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    measured = current.depth.to(points.dtype)[v[inside], u[inside]]
    seen = measured > 0
    hits = seen & ((measured - points[inside, 2]).abs() < max_residual)
    return int(seen.sum()) / max(int(valid.sum()), 1), int(hits.sum()) / max(int(seen.sum()), 1)
