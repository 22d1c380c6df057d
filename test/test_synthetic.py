"""The procedural synthetic scene: determinism, classes, geometric consistency of depth and poses, loops, export."""
import numpy as np
import pytest
import torch

from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset, TumDataset, write_tum_folder
from gausem_core.data.synthetic import SEQUENCES, Scene


@pytest.fixture(scope="module")
def default():
    return SyntheticDataset()


def test_same_seed_same_frames_other_seed_other_texture():
    a, b, c = SyntheticDataset(seed=3), SyntheticDataset(seed=3), SyntheticDataset(seed=4)
    for i in (0, 57):
        fa, fb = a[i], b[i]
        assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth, fb.depth)
        assert np.array_equal(fa.labels, fb.labels) and np.array_equal(fa.gt_pose, fb.gt_pose)
    assert not np.array_equal(a[0].rgb, c[0].rgb)


def test_frame_format_camera_and_lengths(default):
    f = default[0]
    assert f.rgb.shape == (120, 160, 3) and f.depth.dtype == np.float32 and f.labels.dtype == np.int64
    assert f.camera.fx == f.camera.fy == pytest.approx(80 / np.tan(np.radians(30)))  # 60 deg horizontal fov
    assert (f.camera.cx, f.camera.cy) == (80, 60)
    assert np.all(f.depth > 0.3)  # a closed room: every pixel sees a surface, never too close
    assert len(default) == SEQUENCES["default"].frames and 120 <= len(default) <= 200
    assert len(SyntheticDataset("loop")) > len(default)
    assert SyntheticDataset(resolution=(320, 240))[0].camera.fx == pytest.approx(2 * f.camera.fx)


def test_at_least_eight_classes_and_changing_class_content(default):
    histograms = np.stack([np.bincount(default[i].labels.ravel(), minlength=len(SYNTHETIC_CLASSES))
                           for i in range(0, len(default), 15)])
    assert (histograms.sum(0) > 0).sum() >= 8
    p = (histograms + 1) / (histograms + 1).sum(1, keepdims=True)
    kl = (p[:, None] * np.log(p[:, None] / p[None])).sum(-1)
    assert kl.max() > 1.0  # some views share little class content


def test_textures_have_gradients(default):
    grey = default[10].rgb.astype(np.float32).mean(-1)
    assert np.abs(np.diff(grey, axis=1)).mean() > 2.0


def test_depth_consistent_with_poses_between_frames():
    ds = SyntheticDataset(resolution=(320, 240))
    a, b = ds[20], ds[24]
    cam = a.camera
    points_a = cam.backproject(torch.from_numpy(a.depth).double()).reshape(-1, 3).numpy()
    a_to_b = np.linalg.inv(b.gt_pose) @ a.gt_pose
    points_b = points_a @ a_to_b[:3, :3].T + a_to_b[:3, 3]
    uv = cam.project(torch.from_numpy(points_b)).numpy()
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (points_b[:, 2] > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    assert inside.mean() > 0.7
    error = np.abs(points_b[inside, 2] - b.depth[v[inside], u[inside]])
    assert (error < 0.01).mean() > 0.9


def test_ray_casting_matches_a_hand_computed_hit():
    scene = Scene()
    # looking straight down from the room centre at 1 m height: the floor, 1 m away, normal up
    t, normals, points, material = scene.cast(np.array([0.0, 0.0, 1.0]), np.array([[0.0, 0.0, -1.0]]))
    assert t[0] == pytest.approx(1.0) and normals[0].tolist() == [0, 0, 1]
    assert SYNTHETIC_CLASSES.names[scene.material_class[material[0]]] == "floor"
    # towards the east wall (x = 3.5) at sofa-back height 1.6 m above the sofa: the picture at x = 3.46
    t, _, _, material = scene.cast(np.array([0.0, 0.0, 1.55]), np.array([[1.0, 0.0, 0.0]]))
    assert t[0] == pytest.approx(3.46, abs=1e-5)
    assert SYNTHETIC_CLASSES.names[scene.material_class[material[0]]] == "picture"


@pytest.mark.parametrize("name", ["default", "loop"])
def test_trajectory_is_smooth_and_returns_to_start(name):
    ds = SyntheticDataset(name)
    poses = np.stack([ds.trajectory.pose(i) for i in range(len(ds))] + [ds.trajectory.pose(0)])
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=-1)
    rotations = poses[:, :3, :3]
    cosines = [(np.trace(p.T @ q) - 1) / 2 for p, q in zip(rotations, rotations[1:])]
    angles = np.degrees(np.arccos(np.clip(cosines, -1, 1)))
    assert steps.max() < 0.06 and 0.5 < max(angles) < 5.0  # the last frame is one smooth step away from the first
    assert np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=-1).max() > 1.5  # it does travel
    assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_write_tum_folder_round_trip(tmp_path):
    ds = SyntheticDataset(max_frames=4, stride=3)
    back = TumDataset(write_tum_folder(ds, tmp_path / "synthetic_tum"))
    assert len(back) == 4 and back.class_table.names == SYNTHETIC_CLASSES.names
    for i in range(4):
        original, read = ds[i], back[i]
        assert np.array_equal(original.rgb, read.rgb) and np.array_equal(original.labels, read.labels)
        assert np.abs(original.depth - read.depth).max() <= 0.5 / 5000 + 1e-6
        assert read.timestamp == pytest.approx(original.timestamp, abs=1e-6)
        np.testing.assert_allclose(read.gt_pose, original.gt_pose, atol=1e-6)
        assert read.camera.fx == pytest.approx(original.camera.fx) and read.camera.cx == pytest.approx(80)
