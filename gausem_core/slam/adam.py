"""The Adam optimisation shared by mapping, the global refinement and Adam tracking: parameter groups with their own
learning rates, each decaying exponentially over a horizon of steps, one step per loss, and the early-stopping rule."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass
class ParameterGroup:
    """Tensors optimised at learning rate ``lr``, which decays exponentially to ``final_fraction`` of it at the
    horizon (1: constant)."""

    tensors: list[torch.Tensor]
    lr: float
    final_fraction: float = 1.0


class AdamSteps:
    """Adam over ``groups``: step k (counted from 0) runs at each group's ``lr * final_fraction ** (k / horizon)``."""

    def __init__(self, groups: Sequence[ParameterGroup], horizon: int = 1):
        if horizon < 1:
            raise ValueError(f"the learning-rate horizon must be at least 1 step, got {horizon}")
        self.groups = list(groups)
        self.horizon = horizon
        self.steps = 0
        self.optimiser = torch.optim.Adam([{"params": g.tensors, "lr": g.lr} for g in self.groups])

    def step(self, loss: torch.Tensor) -> None:
        """Back-propagate ``loss``, step every group at its current learning rate, then decay the rates."""
        self.optimiser.zero_grad(set_to_none=True)
        loss.backward()
        self.optimiser.step()
        self.steps += 1
        for group, spec in zip(self.optimiser.param_groups, self.groups):
            group["lr"] = spec.lr * spec.final_fraction ** (self.steps / self.horizon)


def has_stalled(losses: Sequence[float], patience: int, tolerance: float) -> bool:
    """Early stopping: whether the best of the last ``patience`` losses improves on the best before them by at most
    ``tolerance`` of it (False until there are more than ``patience`` losses)."""
    if len(losses) <= patience:
        return False
    old, new = min(losses[:-patience]), min(losses[-patience:])
    return old - new <= tolerance * max(abs(old), 1e-12)
