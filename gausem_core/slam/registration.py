"""Semantic-Guided Registration of two submaps (paper §III-B): the coarse step (Eq. 5).

Conventions: keyframe poses are cam_to_world in their own submap's frame; the result ``T`` maps source-submap
coordinates to target-submap coordinates, so a source keyframe and a target keyframe that see the place from the
same viewpoint satisfy ``T_t ≈ T @ T_s``. (With world-from-anchor poses A_s, A_t of the two submaps, T = A_t^-1 A_s.)
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gausem_core.geometry import invert_pose, make_pose, se3_exp, se3_log

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


def top_k_descriptor_pairs(source: torch.Tensor, target: torch.Tensor,
                           k: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
    """The k (source, target) index pairs with the smallest L2 distance between L2-normalised descriptors.

    source (S, D), target (T, D) -> pairs (min(k, S*T), 2) long, distances (same length,), closest first.
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
    return torch.stack([flat // t.shape[0], flat % t.shape[0]], 1), distances


def chordal_mean_alignment(source_poses: torch.Tensor, target_poses: torch.Tensor) -> torch.Tensor:
    """Closed-form estimate of T from pose pairs: the chordal mean of T_t^i (T_s^i)^-1.

    Rotation: the SO(3) projection (SVD) of the summed rotations; translation: the mean translation. (K, 4, 4) each.
    """
    _check_pose_pairs(source_poses, target_poses, "chordal_mean_alignment")
    candidates = target_poses.to(torch.float64) @ invert_pose(source_poses.to(torch.float64))
    u, _, vt = torch.linalg.svd(candidates[:, :3, :3].sum(0))
    fix = torch.diag(torch.tensor([1.0, 1.0, torch.sign(torch.det(u @ vt)).item()], dtype=torch.float64))
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
    steps = _JACOBIAN_STEP * torch.cat([torch.eye(6), -torch.eye(6)]).to(torch.float64)

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
                        init: torch.Tensor | None = None, max_iterations: int = 20) -> CoarseRegistration:
    """SGR coarse step: match the k closest keyframe descriptor pairs, then solve Eq. 5 on their poses.

    Descriptors (S, D) / (T, D) and cam_to_world poses (S, 4, 4) / (T, 4, 4) of the keyframes of the source and
    target submaps, each pose in its own submap's frame. ``init`` defaults to the chordal mean of the matched pairs.
    """
    if source_descriptors.shape[0] != source_poses.shape[0] or target_descriptors.shape[0] != target_poses.shape[0]:
        raise ValueError(f"coarse_registration: descriptor and pose counts differ (source "
                         f"{source_descriptors.shape[0]} vs {source_poses.shape[0]}, target "
                         f"{target_descriptors.shape[0]} vs {target_poses.shape[0]})")
    pairs, _ = top_k_descriptor_pairs(source_descriptors, target_descriptors, k)
    transform, rms, iterations = gauss_newton_alignment(source_poses[pairs[:, 0]], target_poses[pairs[:, 1]], init,
                                                        max_iterations)
    return CoarseRegistration(transform, pairs, rms, iterations)


def _check_pose_pairs(source: torch.Tensor, target: torch.Tensor, where: str) -> None:
    if source.dim() != 3 or source.shape[1:] != (4, 4) or source.shape != target.shape or source.shape[0] == 0:
        raise ValueError(f"{where}: need two non-empty (K, 4, 4) pose stacks of equal length, got "
                         f"{tuple(source.shape)} and {tuple(target.shape)}")
    if not (torch.isfinite(source).all() and torch.isfinite(target).all()):
        raise ValueError(f"{where}: poses contain non-finite values")
