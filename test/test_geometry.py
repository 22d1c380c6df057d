import math

import pytest
import torch

from gausem_core.geometry import (PinholeCamera, invert_pose, make_pose, matrix_to_quaternion, quaternion_to_matrix,
                                  se3_exp, se3_log, so3_exp, so3_log)


def random_twists(n, scale=1.0):
    return torch.randn(n, 6, dtype=torch.float64) * scale


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.5, 2.0])
def test_se3_exp_log_round_trip(scale):
    xi = random_twists(64, scale)
    xi[:, 3:] = xi[:, 3:].clamp(-1.5, 1.5)  # keep angles below pi for a unique log
    assert torch.allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)


def test_so3_log_near_pi():
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    axis = axis / axis.norm()
    for angle in (math.pi - 1e-6, math.pi - 1e-4, math.pi - 1e-2):
        rot = so3_exp(axis * angle)
        assert torch.allclose(so3_exp(so3_log(rot)), rot, atol=1e-6)


def test_exp_is_a_rotation_and_matches_rodrigues_at_90_degrees():
    rot = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(rot, expected, atol=1e-12)


def test_exp_gradient_is_finite_at_zero():
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3_exp, (xi,))


def test_invert_pose():
    pose = se3_exp(random_twists(8))
    assert torch.allclose(pose @ invert_pose(pose), torch.eye(4, dtype=torch.float64).expand(8, 4, 4), atol=1e-12)


def test_quaternion_round_trip():
    rot = so3_exp(random_twists(16)[:, 3:].clamp(-1.5, 1.5))
    assert torch.allclose(quaternion_to_matrix(matrix_to_quaternion(rot)), rot, atol=1e-9)
    identity = matrix_to_quaternion(torch.eye(3, dtype=torch.float64))
    assert torch.allclose(identity, torch.tensor([0, 0, 0, 1.0], dtype=torch.float64))


def test_camera_project_backproject():
    cam = PinholeCamera(100.0, 110.0, 40.0, 30.0, 80, 60)
    depth = torch.rand(60, 80) + 0.5
    pts = cam.backproject(depth)
    uv = cam.project(pts)
    v, u = torch.meshgrid(torch.arange(60.0), torch.arange(80.0), indexing="ij")
    assert torch.allclose(uv, torch.stack([u + 0.5, v + 0.5], -1), atol=1e-4)
    half = cam.scaled(40, 30)
    assert (half.fx, half.cx, half.width) == (50.0, 20.0, 40)
    with pytest.raises(ValueError):
        PinholeCamera(0.0, 1.0, 0, 0, 10, 10)


def test_make_pose_layout():
    pose = make_pose(torch.eye(3), torch.tensor([1.0, 2.0, 3.0]))
    assert pose[3].tolist() == [0, 0, 0, 1] and pose[:3, 3].tolist() == [1, 2, 3]
