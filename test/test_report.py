"""gausem_core.report: the outputs of an offline run, on hand-built run results (no SLAM is run)."""
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gausem_core.config import SlamConfig
from gausem_core.data import SyntheticDataset
from gausem_core.eval.loops import DEFAULT_PROTOCOL
from gausem_core.gaussians import GaussianCloud
from gausem_core.io.ply import read_gaussian_ply
from gausem_core.io.trajectory import read_tum_trajectory
from gausem_core.pipeline import Pipeline, RunResult
from gausem_core.report import format_summary, loop_metrics, nearest_palette_class, write_outputs
from gausem_core.slam.loop_closure import LoopRecord
from gausem_core.slam.densification import gaussians_from_pixels
from gausem_core.slam.mapper import Keyframe
from gausem_core.slam.submap import Submap
from gausem_core.slam.system import GauSemSLAM

ANCHOR = torch.tensor([[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.1], [0.0, 0.0, 0.0, 1.0]])


class UnlabelledSynthetic(SyntheticDataset):
    """The synthetic frames without labels, ground truth or class table (like a raw RGB-D recording)."""

    class_table = None

    def _load(self, index):
        frame = super()._load(index)
        frame.labels, frame.gt_pose = None, None
        return frame


def small_dataset(cls=SyntheticDataset):
    # stride 3: frame ids (0, 3, 6, 9) differ from dataset positions (0, 1, 2, 3)
    return cls("default", resolution=(64, 48), stride=3, max_frames=4)


def config():
    cfg = SlamConfig()
    cfg.device, cfg.backend = "cpu", "torch"
    return cfg


def fake_result(dataset, poses=None):
    """A run whose map is frame 0 back-projected densely at its ground-truth pose, with keyframes 0 (submap 0) and
    2 (submap 1, anchored at ANCHOR); the estimates are the ground-truth poses unless ``poses`` is given."""
    cfg = config()
    pipeline = Pipeline(dataset, cfg, progress=False)
    frames = [dataset[i] for i in range(len(dataset))]
    gt = [torch.from_numpy(f.gt_pose).float() if f.gt_pose is not None else torch.eye(4) for f in frames]
    obs = [pipeline.observation(f) for f in frames]
    pixels = torch.nonzero(obs[0].valid_depth.reshape(-1)).squeeze(1)
    cloud = gaussians_from_pixels(obs[0], gt[0], pixels, opacity=0.99)
    slam = GauSemSLAM(cfg, "cpu")
    slam.submaps[:] = [Submap(0, torch.eye(4), cloud, [Keyframe(0, obs[0], gt[0], fixed=True)]),
                       Submap(1, ANCHOR, GaussianCloud.empty(), [Keyframe(2, obs[2], torch.linalg.inv(ANCHOR) @ gt[2])])]
    poses = np.stack([g.double().numpy() for g in gt]) if poses is None else poses
    return RunResult(slam, [f.timestamp for f in frames], poses, [f.gt_pose for f in frames],
                     [f.index for f in frames], list(range(len(frames))), seconds=2.0), cloud


def test_outputs_of_an_exact_run(tmp_path):
    dataset = small_dataset()
    result, cloud = fake_result(dataset)
    metrics = write_outputs(result, dataset, config(), tmp_path, eval_every=2)

    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"trajectory.txt", "trajectory_gt.txt", "keyframes.txt", "map.ply", "metrics.json",
                     "tracking_status.csv", "loops.csv", "montage.png", "trajectory.png", "grid.pgm", "grid.yaml"}
    loops = (tmp_path / "loops.csv").read_text().splitlines()
    assert loops[0].split(",")[:6] == ["query_frame", "match_frame", "query_submap", "match_submap", "intra",
                                       "accepted"] and len(loops) == 1 + metrics["loops"]["detected"]
    gt = np.stack([dataset[i].gt_pose for i in range(4)])
    estimate = read_tum_trajectory(tmp_path / "trajectory.txt")
    np.testing.assert_allclose(estimate.stamps, [0, 0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(estimate.poses, gt, atol=1e-6)
    keyframes = read_tum_trajectory(tmp_path / "keyframes.txt")  # submap 1's anchor applied
    np.testing.assert_allclose(keyframes.poses, gt[[0, 2]], atol=1e-5)

    ply_cloud, ply_ids = read_gaussian_ply(tmp_path / "map.ply")
    assert len(ply_cloud) == len(cloud) == metrics["num_gaussians"] == sum(metrics["gaussians_per_submap"])
    assert len(metrics["gaussians_per_submap"]) == metrics["num_submaps"] == 2
    torch.testing.assert_close(ply_cloud.means, cloud.means, atol=1e-6, rtol=0)
    assert torch.equal(ply_ids, cloud.class_ids(dataset.class_table.palette))

    assert metrics["ate"]["rmse"] < 1e-6 and metrics["ate"]["pairs"] == 4 and metrics["ate_rmse_cm"] < 1e-4
    rendering = metrics["rendering"]
    assert rendering["frames"] == 2  # positions 0 and 2
    assert metrics["frames"] == 4 and metrics["fps"] == pytest.approx(2.0)
    assert metrics["seconds_per_frame"] == pytest.approx(0.5) and metrics["peak_rss_mb"] > 0
    assert metrics["num_submaps"] == 2 and metrics["num_keyframes"] == 2

    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["metrics"]["ate_rmse_cm"] == pytest.approx(metrics["ate_rmse_cm"], abs=1e-12)
    assert written["parameters"]["backend"] == "torch" and written["parameters"]["eval_every"] == 2
    assert written["parameters"]["dataset"] == "synthetic_default"


def test_rendering_metrics_on_the_frame_the_map_was_built_from(tmp_path):
    dataset = small_dataset()
    result, _ = fake_result(dataset)
    exact = write_outputs(result, dataset, config(), tmp_path / "exact", eval_every=4)["rendering"]
    assert exact["frames"] == 1  # frame 0 only: the map is that frame's own back-projection
    assert exact["psnr"] > 24 and exact["ssim"] > 0.7  # isotropic 1-pixel blobs blur a little
    assert exact["depth_l1_m"] < 0.05
    assert exact["miou"] > 0.8 and exact["pixel_accuracy"] > 0.9

    right = np.eye(4)
    right[0, 3] = 0.1  # an estimate 10 cm to the camera's right must score worse
    result.poses = result.poses.copy()
    result.poses[0] = result.poses[0] @ right
    moved = write_outputs(result, dataset, config(), tmp_path / "moved", eval_every=4)["rendering"]
    assert moved["psnr"] < exact["psnr"] - 3 and moved["ssim"] < exact["ssim"] - 0.1
    assert moved["miou"] < exact["miou"] - 0.05 and moved["depth_l1_m"] > exact["depth_l1_m"] + 0.03


def test_run_without_labels_or_ground_truth(tmp_path):
    dataset = small_dataset(UnlabelledSynthetic)
    result, _ = fake_result(dataset)
    metrics = write_outputs(result, dataset, config(), tmp_path, eval_every=1)
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"trajectory.txt", "keyframes.txt", "map.ply", "metrics.json", "montage.png",
                     "tracking_status.csv", "loops.csv", "grid.pgm", "grid.yaml"}
    assert "ate" not in metrics and math.isnan(metrics["rendering"]["miou"])
    assert metrics["rendering"]["frames"] == 4
    assert read_gaussian_ply(tmp_path / "map.ply")[1] is None  # no class table: no class ids
    assert json.loads((tmp_path / "metrics.json").read_text())["metrics"]["rendering"]["miou"] is None
    assert format_summary(metrics).splitlines()[0].split() == ["ATE", "RMSE", "n/a"]


def test_inconsistent_results_are_rejected(tmp_path):
    dataset = small_dataset()
    result, _ = fake_result(dataset)
    result.frame_ids = [0, 1, 2, 3]  # positions, not this dataset's frame ids
    with pytest.raises(ValueError, match="does not belong to this dataset"):
        write_outputs(result, dataset, config(), tmp_path, eval_every=1)
    result, _ = fake_result(dataset)
    result.poses[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match="frame 6 .* not finite"):
        write_outputs(result, dataset, config(), tmp_path, eval_every=1)
    with pytest.raises(ValueError, match="eval_every"):
        write_outputs(fake_result(dataset)[0], dataset, config(), tmp_path, eval_every=0)


def test_nearest_palette_class():
    palette = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    colors = torch.tensor([[[0.9, 0.1, 0.0], [0.1, 0.1, 0.1]], [[0.2, 0.0, 0.7], [0.6, 0.0, 0.0]]])
    assert nearest_palette_class(colors, palette).tolist() == [[1, 0], [2, 1]]


def test_summary_puts_headline_figures_first():
    metrics = {"ate": {"rmse": 0.0123}, "ate_rmse_cm": 1.23,
               "rendering": {"psnr": 31.5, "ssim": 0.91, "miou": 0.875}, "fps": 2.5}
    lines = format_summary(metrics).splitlines()
    assert lines[:5] == ["ATE RMSE  1.23 cm", "PSNR      31.5 dB", "SSIM      0.91", "mIoU      87.5 %",
                         "fps       2.5"]
    assert lines[-4].split() == ["rendering.psnr", "31.5"] and lines[-1].split() == ["fps", "2.5"]


def test_loop_metrics_score_the_detections_against_ground_truth_loops():
    # 60 frames: out along x to 3 m by frame 30 and back to the start by frame 50, then still: frames 0-9 and 50-59
    # lie within 1 m of each other (a ground-truth loop), frame 40 (1.5 m out) is no loop with frame 5
    x = np.interp(np.arange(60), [0, 10, 30, 50, 59], [0.0, 0.3, 3.0, 0.3, 0.0])
    gt_poses = []
    for value in x:
        pose = np.eye(4)
        pose[0, 3] = value
        gt_poses.append(pose)
    records = [LoopRecord(55, 3, 1, 0, False, True, 0.9, 0.5), LoopRecord(40, 5, 1, 0, False, False, 0.2, 0.25)]
    phases = {"describe": 0.05, "detect": 0.1, "verify": 0.1, "register": 0.7, "correct": 0.05}
    detector = SimpleNamespace(detections=[(55, 3), (55, 4), (40, 5)])  # the checks' candidates: 2 true, 1 false
    slam = SimpleNamespace(loop_closure=SimpleNamespace(records=records, place_recognition="bow", detector=detector,
                                                        rejected_candidates=3, seconds=phases))
    result = RunResult(slam, list(range(60)), np.stack(gt_poses), gt_poses, list(range(60)), list(range(60)),
                       seconds=4.0)
    metrics = loop_metrics(result)
    assert metrics["detected"] == 2 and metrics["accepted"] == 1 and metrics["seconds"] == pytest.approx(0.75)
    assert metrics["place_recognition"] == "bow" and metrics["rejected_by_verification"] == 3
    assert metrics["seconds_by_phase"] == phases and metrics["fraction_of_run_time"] == pytest.approx(0.25)
    assert metrics["precision"] == pytest.approx(0.5)
    assert metrics["ground_truth_loops"] >= 1 and metrics["true_positives"] == 1
    assert metrics["protocol"] == DEFAULT_PROTOCOL
    detection = metrics["detection"]
    assert detection["pairs"] == detection["detections"] == 3 and detection["true_positives"] == 2
    assert detection["precision"] == pytest.approx(2 / 3) and detection["ground_truth_loops_detected"] == 2
