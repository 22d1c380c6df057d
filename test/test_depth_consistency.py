"""benchmarks/depth_consistency.py: the relative pose that aligns two frames' depth best is the true one."""
import numpy as np
import pytest

from depth_consistency import compare, summary, surface
from gausem_core.data import open_dataset
from gausem_core.geometry import PinholeCamera
from gausem_core.io.trajectory import Trajectory


def test_a_plane_has_its_normal_and_an_occluding_edge_has_none():
    camera = PinholeCamera(50.0, 50.0, 20.0, 15.0, 40, 30)
    depth = np.full((30, 40), 2.0)
    depth[:, 30:] = 1.0  # a step: an occluding edge between columns 29 and 30
    points, normals = surface(depth, camera)
    assert points[15, 10] == pytest.approx([(10.5 - 20) / 50 * 2, (15.5 - 15) / 50 * 2, 2.0])
    assert np.abs(normals[10, 10]) == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)
    assert not normals[10, 29].any() and not normals[10, 30].any()
    assert not normals[0].any()  # the border has no central difference


def test_the_true_poses_align_the_depth_better_than_drifted_ones():
    dataset = open_dataset("synthetic", size=(160, 120), max_frames=21)
    truth = Trajectory([f.timestamp for f in dataset], [f.gt_pose for f in dataset])
    drifted = truth.poses.copy()
    drifted[:, :3, 3] += np.arange(len(drifted))[:, None] * np.array([0.001, 0.0, 0.0005])  # 1.1 mm per frame
    trajectories = {"drifted": Trajectory(truth.stamps, drifted), "reference": truth}
    pairs = compare(dataset, trajectories, "reference", gaps=[10], every=5)
    assert len(pairs) == 3 and all(p["second"] - p["first"] == 10 for p in pairs)
    for p in pairs:
        assert p["median_distance_m"]["reference"] < 1e-3  # exact depth, exact poses: only discretisation is left
        assert p["median_distance_m"]["drifted"] > 3e-3
    (row,) = summary(pairs, ["drifted", "reference"])
    assert row["best_in"] == {"drifted": 0, "reference": 3} and row["pairs"] == 3
