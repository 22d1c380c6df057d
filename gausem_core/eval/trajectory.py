"""Trajectory evaluation: timestamp association, Umeyama alignment, ATE and RPE (numbers as evo_ape / evo_rpe) of
:class:`~gausem_core.io.trajectory.Trajectory` objects (cam_to_world poses).

ATE is evo_ape's ``translation_part`` after optional alignment of the estimate onto the reference
(``evo_ape tum ref est -a`` for SE(3), ``-as`` for Sim(3)); RPE is evo_rpe's (delta in frames, non-overlapping pairs).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gausem_core.data.tum import associate
from gausem_core.io.trajectory import Trajectory


def associate_trajectories(estimate: Trajectory, reference: Trajectory,
                           max_diff: float = 0.02) -> tuple[Trajectory, Trajectory]:
    """Pair poses whose stamps differ by less than ``max_diff`` s, one-to-one, closest first (TUM associate.py).

    Returns the matched sub-trajectories in the estimate's time order; raises ValueError when nothing matches.
    """
    pairs = associate(estimate.stamps, reference.stamps, max_diff)
    if not pairs:
        raise ValueError(f"no timestamps of the estimate ({len(estimate)} poses) and the reference "
                         f"({len(reference)} poses) lie within max_diff={max_diff} s of each other")
    est_idx, ref_idx = zip(*pairs)
    return estimate.subset(est_idx), reference.subset(ref_idx)


def umeyama_alignment(source: np.ndarray, target: np.ndarray,
                      with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``R, t, s`` with ``target ~ s R source + t`` for (N, 3) point sets (Umeyama 1991).

    ``s`` is 1 unless ``with_scale``. Raises ValueError for fewer than 3 points or (near-)collinear points,
    where the rotation is not determined.
    """
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"umeyama_alignment needs two (N, 3) arrays, got {source.shape} and {target.shape}")
    if len(source) < 3:
        raise ValueError(f"umeyama_alignment needs at least 3 points, got {len(source)}")
    mean_s, mean_t = source.mean(0), target.mean(0)
    cov = (target - mean_t).T @ (source - mean_s) / len(source)
    u, d, vt = np.linalg.svd(cov)
    if np.linalg.matrix_rank(cov) < 2:
        raise ValueError("umeyama_alignment: the points are degenerate (collinear or coincident); "
                         "the alignment is not determined (evaluate without alignment)")
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / ((source - mean_s) ** 2).sum(1).mean()) if with_scale else 1.0
    return rot, mean_t - scale * rot @ mean_s, scale


def error_statistics(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std, min, max of an error vector (as evo reports them)."""
    errors = np.asarray(errors, np.float64)
    if errors.size == 0:
        raise ValueError("error_statistics: no errors to summarise")
    return {"rmse": float(np.sqrt(np.mean(errors**2))), "mean": float(errors.mean()),
            "median": float(np.median(errors)), "std": float(errors.std()), "min": float(errors.min()),
            "max": float(errors.max())}


@dataclass(frozen=True)
class AteResult:
    """Per-pose position errors (m), their statistics, and the alignment applied to the estimate."""

    errors: np.ndarray
    stats: dict[str, float]
    transform: np.ndarray  # 4x4 rigid part of the alignment (identity without alignment)
    scale: float

    @property
    def rmse(self) -> float:
        return self.stats["rmse"]


def _require_paired(estimate: Trajectory, reference: Trajectory, what: str) -> None:
    if len(estimate) != len(reference) or len(estimate) == 0:
        raise ValueError(f"{what} needs paired non-empty trajectories (use associate_trajectories first); "
                         f"got {len(estimate)} and {len(reference)} poses")


def absolute_trajectory_error(estimate: Trajectory, reference: Trajectory, *, align: bool = True,
                              with_scale: bool = False) -> AteResult:
    """ATE of paired trajectories: ``|| p_est_aligned(i) - p_ref(i) ||`` after SE(3) (or Sim(3)) alignment."""
    _require_paired(estimate, reference, "absolute_trajectory_error")
    transform, scale = np.eye(4), 1.0
    if align:
        transform[:3, :3], transform[:3, 3], scale = umeyama_alignment(estimate.positions, reference.positions,
                                                                       with_scale)
    aligned = estimate.transformed(transform, scale)
    errors = np.linalg.norm(aligned.positions - reference.positions, axis=1)
    return AteResult(errors, error_statistics(errors), transform, scale)


def relative_pose_error(estimate: Trajectory, reference: Trajectory, delta: int = 1) -> dict[str, dict[str, float]]:
    """RPE over pose pairs ``(i, i + delta)``, ``i = 0, delta, 2 delta, ...`` (evo_rpe, delta in frames).

    Per pair E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q the reference, P the estimate. Returns the statistics of
    ``"translation"`` (m, ||t(E)||) and ``"rotation"`` (degrees, angle of R(E)).
    """
    _require_paired(estimate, reference, "relative_pose_error")
    if delta < 1 or delta >= len(estimate):
        raise ValueError(f"relative_pose_error: delta must lie in [1, {len(estimate) - 1}], got {delta}")
    first = np.arange(0, len(estimate) - delta, delta)
    ref_rel = np.linalg.inv(reference.poses[first]) @ reference.poses[first + delta]
    est_rel = np.linalg.inv(estimate.poses[first]) @ estimate.poses[first + delta]
    error = np.linalg.inv(ref_rel) @ est_rel
    cos = np.clip((np.trace(error[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return {"translation": error_statistics(np.linalg.norm(error[:, :3, 3], axis=1)),
            "rotation": error_statistics(np.degrees(np.arccos(cos)))}
