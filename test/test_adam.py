"""The shared Adam optimisation: per-group learning rates with exponential decay, and the early-stopping rule."""
import pytest
import torch

from gausem_core.slam.adam import AdamSteps, ParameterGroup, has_stalled


def _quadratic(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return (x - 3.0).pow(2).sum() + (y + 1.0).pow(2).sum()


def test_constant_rates_step_exactly_like_torch_adam():
    x, y = torch.zeros(3, requires_grad=True), torch.ones(2, requires_grad=True)
    rx, ry = x.detach().clone().requires_grad_(True), y.detach().clone().requires_grad_(True)
    adam = AdamSteps([ParameterGroup([x], 0.1), ParameterGroup([y], 0.02)])
    reference = torch.optim.Adam([{"params": [rx], "lr": 0.1}, {"params": [ry], "lr": 0.02}])
    for _ in range(20):
        adam.step(_quadratic(x, y))
        reference.zero_grad()
        _quadratic(rx, ry).backward()
        reference.step()
    assert torch.equal(x, rx) and torch.equal(y, ry) and adam.steps == 20
    assert float(_quadratic(x, y)) < float(_quadratic(torch.zeros(3), torch.ones(2)))


def test_each_group_decays_to_its_final_fraction_at_the_horizon():
    x, y = torch.zeros(1, requires_grad=True), torch.zeros(1, requires_grad=True)
    adam = AdamSteps([ParameterGroup([x], 0.5, 0.01), ParameterGroup([y], 0.2)], horizon=4)
    rates = [[g["lr"] for g in adam.optimiser.param_groups]]
    for _ in range(4):
        adam.step(_quadratic(x, y))
        rates.append([g["lr"] for g in adam.optimiser.param_groups])
    assert [r[1] for r in rates] == [0.2] * 5
    assert rates[0][0] == 0.5 and rates[4][0] == pytest.approx(0.005)
    assert rates[2][0] == pytest.approx(0.05)  # half way: the geometric mean


def test_a_horizon_below_one_step_is_refused():
    with pytest.raises(ValueError, match="horizon"):
        AdamSteps([ParameterGroup([torch.zeros(1, requires_grad=True)], 0.1)], horizon=0)


def test_stalled_when_the_last_losses_improve_too_little():
    assert not has_stalled([5.0, 4.0, 3.0], patience=3, tolerance=0.1)  # too few losses to judge
    assert not has_stalled([5.0, 4.0, 3.0, 2.0], patience=3, tolerance=0.1)  # 5 -> 2: still improving
    assert has_stalled([5.0, 4.9, 4.8, 4.7], patience=3, tolerance=0.1)  # 5 -> 4.7: 6 % < 10 %
    assert has_stalled([5.0, 6.0, 7.0, 8.0], patience=3, tolerance=0.0)  # worse
