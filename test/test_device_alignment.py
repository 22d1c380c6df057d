"""The on-device Gauss-Newton level takes the host level's steps (torch normal equations) and stops where it does."""
import pytest
import torch
from test_direct_alignment import CAMERA, MOTION, WEIGHTS, jitter_edges, ray_cast

from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.slam import direct_alignment
from gausem_core.slam.device_alignment import align_level_on_device


@pytest.fixture(scope="module")
def views() -> tuple[direct_alignment.ModelView, direct_alignment.ObservedImages]:
    """The view at identity (model, float32) and the one at ``MOTION`` (observation)."""
    model_color, model_depth = (t.float() for t in ray_cast(torch.eye(4, dtype=torch.float64)))
    observed_color, observed_depth = (t.float() for t in ray_cast(invert_pose(MOTION)))
    model = direct_alignment.ModelView(model_color, model_color, model_depth, model_depth > 0, CAMERA)
    return model, direct_alignment.ObservedImages.build(observed_color, observed_color, jitter_edges(observed_depth),
                                                        CAMERA)


@pytest.fixture
def host_steps(monkeypatch) -> list[int]:
    """align_level on the torch normal equations; the list grows by one per step it computes."""
    monkeypatch.setattr(direct_alignment, "kernel_available", lambda: False)
    steps, normal_equations = [], direct_alignment.normal_equations
    monkeypatch.setattr(direct_alignment, "normal_equations", lambda *args: steps.append(1) or normal_equations(*args))
    return steps


# (start twist, iterations, check_every, steps align_level takes): all its steps; converged (|xi| < 1e-6) after 4,
# the device level reading that after 6; and the model behind the camera (too few points) from the first step
@pytest.mark.parametrize("twist, iterations, check_every, steps", [
    ([0.0] * 6, 3, 4, 3), ([0.0] * 6, 16, 3, 4), ([0.0, 0.0, -3.0, 0.0, 0.0, 0.0], 8, 4, 1)])
def test_the_device_level_is_the_host_level(views, host_steps, twist, iterations, check_every, steps):
    start = se3_exp(torch.tensor(twist))
    motion, cost = direct_alignment.align_level(*views, start, WEIGHTS, iterations)
    assert len(host_steps) == steps
    on_device, device_cost = align_level_on_device(*views, start, WEIGHTS, iterations, check_every=check_every)
    assert (on_device - motion).abs().max() <= 1e-6
    assert device_cost == pytest.approx(cost, rel=1e-6, nan_ok=True)
