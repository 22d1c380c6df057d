"""The three-cornered hat of benchmarks/reference_error.py: each trajectory's own error from the pairwise ATEs."""
import numpy as np
import pytest

from gausem_core.io.trajectory import Trajectory
from reference_error import own_errors, pairwise_rmse


def noisy_copy(truth: Trajectory, sigma: float, rng: np.random.Generator) -> Trajectory:
    poses = truth.poses.copy()
    poses[:, :3, 3] += rng.normal(0.0, sigma / np.sqrt(3), (len(poses), 3))
    return Trajectory(truth.stamps, poses)


def test_independent_errors_are_recovered_including_the_reference_own():
    rng = np.random.default_rng(0)
    n = 2000
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(0.0, 0.02, (n, 3)), axis=0)
    truth = Trajectory(np.arange(n) / 30.0, poses)
    sigmas = [0.01, 0.02, 0.015]  # two estimates and a reference that is itself off by 1.5 cm
    d = pairwise_rmse([noisy_copy(truth, s, rng) for s in sigmas])
    assert d[0, 2] == pytest.approx(np.hypot(0.01, 0.015), rel=0.05)  # what ATE against the reference reports
    assert own_errors(d) == pytest.approx(sigmas, abs=0.0015)  # sampling noise in d, amplified by the solve


def test_two_trajectories_are_not_enough():
    with pytest.raises(ValueError, match="three"):
        own_errors(np.array([[0.0, 0.01], [0.01, 0.0]]))
