"""One Gauss-Newton alignment level with every step on the points' device (issue 47): the normal equations, the
damped 6x6 solve and the pose update stay there, and the host reads whether the level has converged only every few
iterations."""
from __future__ import annotations

import torch

from gausem_core.geometry import se3_exp
from gausem_core.slam.direct_alignment import (AlignmentWeights, ModelView, ObservedImages, model_samples,
                                               normal_equation_sums)


def align_level_on_device(model: ModelView, observed: ObservedImages, motion: torch.Tensor,
                          weights: AlignmentWeights, iterations: int, damping: float = 1e-4,
                          min_step: float = 1e-6, check_every: int = 4,
                          fused: bool = True) -> tuple[torch.Tensor, float]:
    """:func:`~gausem_core.slam.direct_alignment.align_level` with no host sync per step (the normal equations in one
    Triton kernel on CUDA where it compiles and ``fused``, ``slam.fused_alignment``; in torch otherwise): returns the
    refined ``motion`` (on its device) and the last mean cost (nan when no step had 12 valid points).

    The solve runs in float64 as on the host. Once converged (|xi| < ``min_step``, or a step with fewer than 12 valid
    points, which moves nothing) the steps leave the motion and the cost as they are, so running on changes nothing.
    The host reads the converged flag after every ``check_every`` iterations but the last, stopping when it is set,
    and the cost once at the end: ``ceil(iterations / check_every)`` reads at most."""
    points, ref = model_samples(model, observed)
    device, motion = motion.device, motion.detach()
    sums = normal_equation_sums
    if fused and device.type == "cuda":
        from gausem_core.slam import fused_alignment  # imports Triton: only where it may serve
        sums = fused_alignment.fused_normal_equation_sums if fused_alignment.fused_available(device) else sums
    eye = torch.eye(6, dtype=torch.float64, device=device)
    cost = torch.full((), float("nan"), dtype=torch.float64, device=device)
    done = torch.zeros((), dtype=torch.bool, device=device)
    for i in range(1, iterations + 1):
        h, g, total, count = sums(observed, motion, weights, points, ref)
        h, enough = h.double(), count >= 12
        h = h + damping * torch.diag(h.diagonal()) + 1e-9 * eye
        xi = -torch.linalg.solve_ex(h, g.double())[0].to(motion.dtype)  # solve_ex: no error check, no sync
        moves = enough & ~done
        motion = torch.where(moves, se3_exp(xi) @ motion, motion)
        cost = torch.where(moves, total.double(), cost)
        done = done | ~enough | (xi.norm() < min_step)
        if i % check_every == 0 and i < iterations and bool(done):
            break
    return motion, float(cost) / len(points)
