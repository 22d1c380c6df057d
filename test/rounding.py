"""What floating-point arithmetic allows a parity test, whatever the CPU.

Two implementations of one sum (a kernel and torch, float32 and float64, two devices) add the same terms in different
orders, with or without fused multiply-adds and in vector lanes of different widths: their results differ by rounding,
and by how much depends on the machine. What does not depend on it is the classical worst case (Higham, *Accuracy and
Stability of Numerical Algorithms*, ch. 3-4): a sum of terms each produced by rounded operations, with ``n`` rounded
operations on the longest path from an input to the result, lies within ``gamma(n) * sum(|term|)`` of the exact sum,
``gamma(n) = n u / (1 - n u)`` with ``u`` the unit roundoff. The tests compare each entry with a float64 reference of
the same terms and bound it by its own magnitude, not by the largest entry's.
"""
from __future__ import annotations

import torch


def unit_roundoff(dtype: torch.dtype) -> float:
    """Half the machine epsilon: the largest relative error of one rounded operation."""
    return torch.finfo(dtype).eps / 2


def gamma(operations: int, dtype: torch.dtype) -> float:
    """The relative worst case of ``operations`` rounded operations in a row in ``dtype``."""
    nu = operations * unit_roundoff(dtype)
    assert nu < 0.5, f"{operations} operations in {dtype}: no useful bound"
    return nu / (1 - nu)


def assert_within_rounding(got, exact, magnitude, operations: int, dtype: torch.dtype, what: str = "") -> None:
    """Every entry of ``got`` (computed in ``dtype``) within ``gamma(operations) * magnitude`` of ``exact`` (float64),
    ``magnitude`` being the entry's sum of the absolute values of its terms (same shape as ``exact``)."""
    got, exact, magnitude = (torch.as_tensor(t, dtype=torch.float64, device="cpu") for t in (got, exact, magnitude))
    assert got.shape == exact.shape == magnitude.shape, (what, got.shape, exact.shape, magnitude.shape)
    assert torch.isfinite(got).all(), f"{what}: non-finite entries {got}"
    bound = gamma(operations, dtype) * magnitude
    excess = (got - exact).abs() - bound
    worst = int(excess.argmax())
    assert float(excess.reshape(-1)[worst]) <= 0, (
        f"{what}: entry {worst} is {float(got.reshape(-1)[worst])!r}, the float64 reference "
        f"{float(exact.reshape(-1)[worst])!r}; rounding in {dtype} over {operations} operations allows "
        f"{float(bound.reshape(-1)[worst]):.3g}")
