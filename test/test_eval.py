"""Evaluation metrics against hand-computed values: trajectories, images, semantics, loops."""
import math

import numpy as np
import pytest
import torch

from gausem_core.eval.image import LPIPS_NOT_AVAILABLE, depth_l1, image_metrics, lpips, psnr, ssim
from gausem_core.eval.loops import ground_truth_loops, loop_scores
from gausem_core.eval.semantic import confusion_matrix, mean_iou, per_class_iou, pixel_accuracy, semantic_scores
from gausem_core.eval.trajectory import (absolute_trajectory_error, associate_trajectories, relative_pose_error,
                                         umeyama_alignment)
from gausem_core.geometry import se3_exp, so3_exp
from gausem_core.io.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory


# --- trajectories ---------------------------------------------------------------------------------------------------
def random_trajectory(n: int, seed: int = 0) -> Trajectory:
    g = torch.Generator().manual_seed(seed)
    twists = torch.randn(n, 6, generator=g, dtype=torch.float64)
    return Trajectory(np.arange(n) * 0.1 + 1305031102.0, se3_exp(twists).numpy())


def rigid(rotvec, translation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = so3_exp(torch.tensor(rotvec, dtype=torch.float64)).numpy()
    t[:3, 3] = translation
    return t


def test_tum_trajectory_round_trip(tmp_path):
    traj = random_trajectory(20)
    write_tum_trajectory(tmp_path / "traj.txt", traj)
    lines = (tmp_path / "traj.txt").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 21 and len(lines[1].split()) == 8
    back = read_tum_trajectory(tmp_path / "traj.txt")
    np.testing.assert_allclose(back.stamps, traj.stamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8)


def test_read_tum_trajectory_rejects_bad_lines(tmp_path):
    (tmp_path / "zero.txt").write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="zero quaternion"):
        read_tum_trajectory(tmp_path / "zero.txt")
    (tmp_path / "short.txt").write_text("1.0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="expected 8 fields"):
        read_tum_trajectory(tmp_path / "short.txt")


def test_association_with_jitter_and_missing_stamps():
    est = Trajectory([0.0, 0.1, 0.2, 0.3, 0.4, 1.0, 1.005], np.tile(np.eye(4), (7, 1, 1)))
    ref_stamps = [0.003, 0.098, 0.25, 0.302, 0.401, 0.402, 1.004]
    ref_poses = np.tile(np.eye(4), (7, 1, 1))
    ref_poses[:, 0, 3] = np.arange(7)  # x identifies the reference pose
    est_m, ref_m = associate_trajectories(est, Trajectory(ref_stamps, ref_poses), max_diff=0.02)
    # 0.2 has no partner (0.25 is too far); 1.0 loses 1.004 to the closer 1.005; 0.4 takes the closer 0.401.
    np.testing.assert_allclose(est_m.stamps, [0.0, 0.1, 0.3, 0.4, 1.005])
    np.testing.assert_allclose(ref_m.positions[:, 0], [0, 1, 3, 4, 6])
    with pytest.raises(ValueError, match="max_diff"):
        associate_trajectories(est, Trajectory([50.0], np.eye(4)[None]))


def test_ate_of_rigidly_moved_trajectory_is_zero_and_recovers_the_motion():
    ref = random_trajectory(30)
    motion = rigid([0.3, -0.5, 1.2], [2.0, -1.0, 0.5])
    est = ref.transformed(motion)
    result = absolute_trajectory_error(est, ref)
    assert result.rmse < 1e-9 and result.stats["max"] < 1e-9
    np.testing.assert_allclose(result.transform, np.linalg.inv(motion), atol=1e-9)
    unaligned = absolute_trajectory_error(ref.transformed(rigid([0, 0, 0], [1.0, 2.0, 2.0])), ref, align=False)
    np.testing.assert_allclose(unaligned.errors, 3.0)


def test_ate_of_known_noise_after_rigid_motion():
    ref = random_trajectory(40, seed=1)
    # Noise orthogonal to the constant and to the positions leaves the optimal alignment the identity, so the
    # ATE errors are exactly the noise norms, whatever rigid motion is applied afterwards.
    basis = np.column_stack([np.ones(40), ref.positions])
    noise = np.random.default_rng(2).normal(scale=0.05, size=(40, 3))
    noise -= basis @ np.linalg.lstsq(basis, noise, rcond=None)[0]
    noisy = ref.poses.copy()
    noisy[:, :3, 3] += noise
    est = Trajectory(ref.stamps, noisy).transformed(rigid([-0.7, 0.2, 0.4], [0.3, 5.0, -2.0]))
    result = absolute_trajectory_error(est, ref)
    norms = np.linalg.norm(noise, axis=1)
    np.testing.assert_allclose(result.errors, norms, atol=1e-9)
    assert result.rmse == pytest.approx(math.sqrt(np.mean(norms**2)), abs=1e-12)
    assert result.stats["median"] == pytest.approx(np.median(norms), abs=1e-12)
    assert result.stats["max"] == pytest.approx(norms.max(), abs=1e-12)


def test_sim3_alignment_recovers_scale():
    ref = random_trajectory(25, seed=3)
    est = ref.transformed(rigid([0.1, 0.2, 0.3], [1.0, 0.0, 0.0]), scale=2.5)
    sim3 = absolute_trajectory_error(est, ref, with_scale=True)
    assert sim3.rmse < 1e-9 and sim3.scale == pytest.approx(1 / 2.5)
    assert absolute_trajectory_error(est, ref).rmse > 0.1


def test_umeyama_rejects_degenerate_input():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="degenerate"):
        umeyama_alignment(line, line)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama_alignment(line[:2], line[:2])
    with pytest.raises(ValueError, match="paired"):
        absolute_trajectory_error(random_trajectory(5), random_trajectory(4))


def steps(n: int, step: np.ndarray) -> Trajectory:
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ step)
    return Trajectory(np.arange(n, dtype=float), np.array(poses))


def test_relative_pose_error_of_known_step_errors():
    ref = steps(6, rigid([0, 0, np.radians(10)], [0.1, 0, 0]))
    est = steps(6, rigid([0, 0, np.radians(12)], [0.1, 0, 0]))
    rpe = relative_pose_error(est, ref)
    np.testing.assert_allclose([rpe["rotation"]["min"], rpe["rotation"]["max"]], [2.0, 2.0], atol=1e-9)
    assert rpe["translation"]["max"] < 1e-12
    longer = relative_pose_error(steps(7, rigid([0, 0, 0], [0.11, 0, 0])), steps(7, rigid([0, 0, 0], [0.1, 0, 0])), 3)
    assert longer["translation"]["rmse"] == pytest.approx(0.03)  # pairs (0, 3) and (3, 6)
    moved = relative_pose_error(ref.transformed(rigid([1.0, 0.0, 0.0], [3.0, 0.0, 0.0])), ref)
    assert moved["translation"]["max"] < 1e-12 and moved["rotation"]["max"] < 1e-5


# --- images ---------------------------------------------------------------------------------------------------------
def test_psnr_of_known_mse_and_mask():
    img = torch.rand(8, 9, 3, dtype=torch.float64) * 0.8
    assert psnr(img + 0.1, img) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    other = img.clone()
    mask = torch.zeros(8, 9, dtype=torch.bool)
    mask[2:5, 3:7] = True
    other[mask] += 0.01
    other[~mask] = 1 - img[~mask]
    assert psnr(other, img, mask) == pytest.approx(40.0, abs=1e-6)  # MSE 1e-4 inside the mask
    assert psnr(img, img) == math.inf
    with pytest.raises(ValueError, match="no pixels"):
        psnr(img, img, torch.zeros(8, 9, dtype=torch.bool))


def slow_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Per-pixel SSIM with an explicit 2-D window and zero padding (H, W, C), averaged."""
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    h, wd, c = x.shape
    xp, yp = (np.pad(a, ((5, 5), (5, 5), (0, 0))) for a in (x, y))
    values = []
    for i in range(h):
        for j in range(wd):
            for k in range(c):
                px, py = xp[i:i + 11, j:j + 11, k], yp[i:i + 11, j:j + 11, k]
                mx, my = (w * px).sum(), (w * py).sum()
                vx, vy, cxy = (w * px * px).sum() - mx**2, (w * py * py).sum() - my**2, (w * px * py).sum() - mx * my
                values.append((2 * mx * my + 1e-4) * (2 * cxy + 9e-4) / ((mx**2 + my**2 + 1e-4) * (vx + vy + 9e-4)))
    return float(np.mean(values))


def test_ssim_matches_a_slow_reference_and_is_one_for_identical_images():
    x = torch.rand(13, 10, 2, dtype=torch.float64)
    y = (x + 0.2 * torch.rand(13, 10, 2, dtype=torch.float64)).clamp(0, 1)
    assert ssim(x, y).item() == pytest.approx(slow_ssim(x.numpy(), y.numpy()), abs=1e-10)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-12)
    batch = torch.rand(2, 3, 16, 12)
    assert ssim(batch, batch).item() == pytest.approx(1.0, abs=1e-6)
    assert ssim(x, y).item() == pytest.approx(ssim(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None]).item())
    with pytest.raises(ValueError, match="shape"):
        ssim(x, y[:-1])


def test_ssim_is_differentiable():
    x = torch.rand(7, 6, 3, dtype=torch.float64, requires_grad=True)
    y = torch.rand(7, 6, 3, dtype=torch.float64)
    (grad,) = torch.autograd.grad(ssim(x, y), x)
    direction, eps = torch.randn(7, 6, 3, dtype=torch.float64), 1e-6
    with torch.no_grad():
        numeric = (ssim(x + eps * direction, y) - ssim(x - eps * direction, y)) / (2 * eps)
    assert (grad * direction).sum().item() == pytest.approx(numeric.item(), rel=1e-6)


def test_depth_l1_over_valid_pixels():
    target = torch.tensor([[1.0, 2.0], [0.0, 4.0]])
    rendered = torch.tensor([[1.5, 1.0], [9.0, 4.0]])
    assert depth_l1(rendered, target) == pytest.approx((0.5 + 1.0 + 0.0) / 3)
    assert depth_l1(rendered, target, torch.tensor([[True, False], [True, False]])) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="no pixel"):
        depth_l1(rendered, torch.zeros(2, 2))


def test_lpips_needs_local_weights(tmp_path):
    img = torch.rand(8, 8, 3)
    with pytest.raises(FileNotFoundError, match="lpips_weights"):
        lpips(img, img, tmp_path / "missing.pt2")
    assert image_metrics(img, img)["lpips"] == LPIPS_NOT_AVAILABLE


def test_lpips_runs_an_exported_program(tmp_path):
    class MeanAbs(torch.nn.Module):  # stands in for an exported LPIPS network: (B,3,H,W) pairs in [-1, 1]
        def forward(self, a, b):
            return (a - b).abs().mean(dim=(1, 2, 3))

    h, w = torch.export.Dim("h", min=2), torch.export.Dim("w", min=2)
    example = (torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8))
    program = torch.export.export(MeanAbs(), example, dynamic_shapes=({2: h, 3: w}, {2: h, 3: w}))
    torch.export.save(program, tmp_path / "lpips.pt2")
    a, b = torch.rand(6, 5, 3), torch.rand(6, 5, 3)
    expected = 2 * (a - b).abs().mean().item()  # inputs are scaled from [0, 1] to [-1, 1]
    assert lpips(a, b, tmp_path / "lpips.pt2") == pytest.approx(expected, rel=1e-5)
    assert image_metrics(a, b, lpips_weights=tmp_path / "lpips.pt2")["lpips"] == pytest.approx(expected, rel=1e-5)


# --- semantics ------------------------------------------------------------------------------------------------------
def test_miou_of_a_tiny_confusion():
    gt = np.array([0, 0, 1, 1, 2, 255])
    pred = np.array([0, 1, 1, 1, 0, 2])
    conf = confusion_matrix(pred, gt, 3, ignore_index=255)
    np.testing.assert_array_equal(conf, [[1, 1, 0], [0, 2, 0], [1, 0, 0]])
    np.testing.assert_allclose(per_class_iou(conf), [1 / 3, 2 / 3, 0.0])
    assert mean_iou(conf) == pytest.approx(1 / 3)
    assert pixel_accuracy(conf) == pytest.approx(3 / 5)
    assert semantic_scores(conf)["miou"] == pytest.approx(1 / 3)


def test_miou_averages_only_classes_present_in_ground_truth():
    conf = confusion_matrix(torch.tensor([[0, 1]]), torch.tensor([[0, 0]]), 3, ignore_index=-1)
    iou = per_class_iou(conf)
    assert iou[0] == pytest.approx(0.5) and iou[1] == 0.0 and math.isnan(iou[2])
    assert mean_iou(conf) == pytest.approx(0.5)
    assert math.isnan(mean_iou(np.zeros((3, 3))))


def test_confusion_matrix_rejects_bad_labels():
    with pytest.raises(ValueError, match=r"\[7\]"):
        confusion_matrix(np.array([0, 7]), np.array([0, 1]), 3)
    with pytest.raises(ValueError, match="ground truth labels"):
        confusion_matrix(np.array([0, 1]), np.array([0, 255]), 3)
    with pytest.raises(ValueError, match="shape"):
        confusion_matrix(np.array([0, 1]), np.array([0]), 3)


# --- loops ----------------------------------------------------------------------------------------------------------
def loop_track() -> np.ndarray:
    """40 frames, intervals of 10: 0-19 at the origin, 20-29 five metres away, 30-38 back, frame 39 one metre off."""
    positions = np.zeros((40, 3))
    positions[20:30, 0] = 5.0
    positions[39, 0] = 1.0
    return positions + np.random.default_rng(0).uniform(-0.05, 0.05, (40, 3))


def test_ground_truth_loops_follow_the_interval_protocol():
    track = loop_track()
    # Gap 15: intervals 0 and 1 have admissible pairs (|i - j| up to 19) -> a loop. Interval 3 pairs with 0 and 1
    # only for tau_loop > 1 m: the max over P includes frame 39 (1 m off).
    assert ground_truth_loops(track, min_frame_gap=15, tau_loop=0.5) == {(0, 1)}
    assert ground_truth_loops(track, min_frame_gap=15, tau_loop=1.5) == {(0, 1), (0, 3), (1, 3)}
    # Gap 25: intervals 0 and 1 have no admissible pair; 1 and 3 still do (|i - j| up to 29).
    assert ground_truth_loops(track, min_frame_gap=25, tau_loop=1.5) == {(0, 3), (1, 3)}
    track[39, 0] = 0.0
    assert ground_truth_loops(track, min_frame_gap=25, tau_loop=0.5) == {(0, 3), (1, 3)}


def test_loop_protocol_counts_the_cameras_frames():
    """A run that processed every 3rd frame of a 30 Hz camera is judged on the camera's intervals, as a run that
    processed them all; numbered by index, its intervals would span three times the motion."""
    positions = np.zeros((120, 3))
    positions[30:90, 0] = 5.0  # away for two seconds, then back where it started
    positions += np.random.default_rng(0).uniform(-0.05, 0.05, positions.shape)
    stamps = np.arange(120) / 30.0
    protocol = {"min_frame_gap": 30, "tau_loop": 0.5, "interval": 10}
    full = ground_truth_loops(positions, timestamps=stamps, **protocol)
    returns = {(a, b) for a in range(3) for b in range(9, 12)}
    assert full == returns | {(a, b) for a in range(3, 9) for b in range(a + 3, 9)}  # and while away
    assert full == ground_truth_loops(positions, **protocol)  # 30 Hz stamps: numbered as by index
    assert ground_truth_loops(positions[::3], timestamps=stamps[::3], **protocol) == full
    assert ground_truth_loops(positions[::3], **protocol) == {(0, 3)}
    assert loop_scores([(33, 3), (35, 25)], positions[::3], timestamps=stamps[::3], **protocol).precision == 0.5
    with pytest.raises(ValueError, match="non-decreasing"):
        loop_scores([], positions[:3], timestamps=[0.0, 0.2, 0.1], **protocol)


def test_loop_precision_recall_f1():
    track = loop_track()
    detections = [(35, 2), (33, 15), (25, 5), (36, 4)]  # (0,3) hit, (1,3) hit, (0,2) false, (0,3) again
    scores = loop_scores(detections, track, min_frame_gap=25, tau_loop=1.5)
    assert (scores.true_positives, scores.detections, scores.ground_truth_loops) == (3, 4, 2)
    assert scores.precision == pytest.approx(0.75) and scores.recall == pytest.approx(1.0)
    assert scores.f1 == pytest.approx(6 / 7)
    half = loop_scores([(35, 2), (12, 14)], track, min_frame_gap=25, tau_loop=1.5)  # same interval: never a loop
    assert (half.precision, half.recall, half.f1) == pytest.approx((0.5, 0.5, 0.5))
    none = loop_scores([], track, min_frame_gap=25, tau_loop=1.5)
    assert math.isnan(none.precision) and none.recall == 0.0 and math.isnan(none.f1)
    with pytest.raises(ValueError, match="outside"):
        loop_scores([(0, 40)], track, min_frame_gap=25, tau_loop=1.5)


def test_real_tum_ground_truth(shared_data, tmp_path):
    gt = read_tum_trajectory(shared_data / "tum_fr1_rpy" / "groundtruth.txt")
    rgb_stamps = [float(line.split()[0]) for line in (shared_data / "tum_fr1_rpy" / "rgb.txt").read_text().splitlines()
                  if not line.startswith("#")]
    camera = Trajectory(rgb_stamps, np.tile(np.eye(4), (len(rgb_stamps), 1, 1)))
    matched_camera, matched_gt = associate_trajectories(camera, gt)
    assert len(matched_camera) == len(rgb_stamps) == 200  # the folder holds frames of the associated sequence
    assert np.abs(matched_camera.stamps - matched_gt.stamps).max() < 0.02
    write_tum_trajectory(tmp_path / "gt.txt", matched_gt)
    estimate = read_tum_trajectory(tmp_path / "gt.txt").transformed(rigid([0.0, 0.0, 2.0], [1.0, -3.0, 0.2]))
    assert absolute_trajectory_error(estimate, matched_gt).rmse < 1e-5
    assert relative_pose_error(estimate, matched_gt)["rotation"]["max"] < 1e-3
