"""``gausem run`` end to end on a few small synthetic frames: the outputs exist and the figures are sane; a strided
run that dropped a frame and a resumed run are evaluated against their own frames."""
import json
import math

import numpy as np
import pytest
import torch

from gausem_core.cli import main
from gausem_core.config import from_flat
from gausem_core.data import SyntheticDataset
from gausem_core.io.ply import read_gaussian_ply
from gausem_core.io.trajectory import read_tum_trajectory
from gausem_core.pipeline import Pipeline
from gausem_core.report import write_outputs
from gausem_core.slam.relocalisation import RelocalisationResult
from gausem_core.slam.front_end import FrontEnd
from gausem_core.slam.system import GauSemSLAM

FAST = ["--set", "mapping.init_iterations=60", "--set", "mapping.iterations=5"]


def test_gausem_run_writes_the_outputs(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--dataset", "synthetic", "--frames", "6", "--size", "80x60", *FAST, "--quiet",
                 "--set", "device=cpu", "--out", str(out)]) == 0
    assert "ATE RMSE" in capsys.readouterr().out
    for name in ("trajectory.txt", "trajectory_gt.txt", "keyframes.txt", "map.ply", "metrics.json", "montage.png",
                 "trajectory.png", "grid.pgm", "grid.yaml"):
        assert (out / name).is_file(), name
    assert len(read_tum_trajectory(out / "trajectory.txt")) == 6
    assert len(read_tum_trajectory(out / "keyframes.txt")) >= 2  # frames 0 and 5 with mapping.every = 5
    cloud, class_ids = read_gaussian_ply(out / "map.ply")
    assert len(cloud) > 0 and class_ids is not None

    document = json.loads((out / "metrics.json").read_text())
    metrics = document["metrics"]
    assert document["parameters"]["mapping.iterations"] == 5 and metrics["frames"] == 6
    # loose bounds: the SLAM core is still being tuned; these only catch a broken run
    assert math.isfinite(metrics["ate"]["rmse"]) and metrics["ate"]["rmse"] < 0.2
    assert metrics["rendering"]["psnr"] > 10 and metrics["rendering"]["frames"] == 2
    assert 0 < metrics["rendering"]["miou"] <= 1
    assert metrics["grid"]["floor"] == "class" and 0 < metrics["grid"]["layout"]["iou"] <= 1
    for phase in ("frame", "tracking", "mapping"):  # a process call, a frame's tracking, a keyframe's mapping
        assert 0 < metrics[f"{phase}_ms_median"] <= metrics[f"{phase}_ms_p95"], phase


@pytest.mark.slow
def test_gausem_run_saves_and_resumes_a_session(tmp_path):
    common = ["--dataset", "synthetic", "--size", "80x60", *FAST, "--quiet", "--eval-every", "10"]
    session = tmp_path / "session"
    assert main(["run", *common, "--frames", "6", "--set", "device=cpu", "--save-session", str(session),
                 "--out", str(tmp_path / "first")]) == 0
    assert (session / "session.json").is_file()
    out = tmp_path / "resumed"
    assert main(["run", *common, "--start", "6", "--frames", "5", "--resume", str(session), "--out", str(out)]) == 0
    first = read_tum_trajectory(tmp_path / "first" / "trajectory.txt")
    resumed = read_tum_trajectory(out / "trajectory.txt")
    assert len(resumed) == 5 and resumed.stamps[0] > first.stamps[-1]  # this run's frames, none dropped
    assert len(read_tum_trajectory(out / "keyframes.txt")) == 3  # the session's (frames 0, 5) and frame 10
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert metrics["frames"] == 5 and metrics["ate"]["rmse"] < 0.2


class DropsFrames(FrontEnd):
    """Drops the frames with the given timestamps as a failed relocalisation does (not recorded, map untouched)."""

    def __init__(self, *args, drop: set[float]):
        super().__init__(*args)
        self.drop = drop

    def _track_or_relocalise(self, obs, motion, *tracked_against):
        if obs.timestamp in self.drop:
            return None, RelocalisationResult(False, torch.eye(4), 0.0, math.nan, 0, "none", 0, 0)
        return super()._track_or_relocalise(obs, motion, *tracked_against)


def test_a_strided_run_with_a_dropped_frame_is_evaluated_on_its_own_frames(tmp_path):
    dataset = SyntheticDataset("default", resolution=(80, 60), stride=3, max_frames=5)  # frame ids 0, 3, ..., 12
    cfg = from_flat({"device": "cpu", "mapping.init_iterations": 60, "mapping.iterations": 5})
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, pipeline.device, len(pipeline.palette))
    slam.front_end = DropsFrames(cfg, slam.device, slam.back_end, drop={dataset[1].timestamp})
    result = pipeline.run(slam)
    assert result.frame_ids == [0, 6, 9, 12] and result.dataset_positions == [0, 2, 3, 4]

    metrics = write_outputs(result, dataset, cfg, tmp_path, eval_every=1)
    assert metrics["rendering"]["frames"] == 4 and metrics["rendering"]["psnr"] > 10
    estimate, truth = (read_tum_trajectory(tmp_path / name) for name in ("trajectory.txt", "trajectory_gt.txt"))
    kept = [dataset[i] for i in result.dataset_positions]
    np.testing.assert_allclose(truth.stamps, [f.timestamp for f in kept], atol=1e-6)
    np.testing.assert_allclose(estimate.stamps, truth.stamps, atol=1e-6)  # ATE pairs each frame with its own pose
    np.testing.assert_allclose(truth.poses, np.stack([f.gt_pose for f in kept]), atol=1e-6)
    # a sanity bound, not tracking accuracy: frame 6 follows a six-frame gap at 80x60 and lands some 0.45 m off
    assert metrics["ate"]["pairs"] == 4 and metrics["ate"]["rmse"] < 0.25


def test_a_resumed_run_scores_only_the_loops_among_its_own_frames(tmp_path):
    """Every loop keyframe detects a loop (none accepted). The session (frames 0-2) holds the loop (2, 0); resumed on
    source frames 3-9 (system ids 3-9), the run's loops back into frames 0-2 are counted, not scored, and those among
    ids 3-9 are scored as this run's frames 0-6."""
    cfg = from_flat({"device": "cpu", "mapping.init_iterations": 60, "mapping.iterations": 5, "mapping.every": 2,
                     "refinement.enabled": False, "submaps.min_keyframes": 100, "loop.keyframe_every": 2,
                     "loop.check_every": 1, "loop.exclude_recent": 0, "loop.place_recognition": "descriptor",
                     "loop.max_fallback_descriptor_distance": 2.0, "loop.registration.min_fitness": 2.0})
    Pipeline(SyntheticDataset("default", resolution=(80, 60), max_frames=3), cfg, progress=False).run(
        save_session=tmp_path / "session")
    dataset = SyntheticDataset("default", resolution=(80, 60), start=3, max_frames=7)
    pipeline = Pipeline(dataset, cfg, progress=False)
    result = pipeline.run(GauSemSLAM.load(tmp_path / "session", pipeline.device, cfg))
    loops = write_outputs(result, dataset, cfg, tmp_path / "out", eval_every=10)["loops"]
    assert result.first_frame == 3 and len(result.frame_ids) == 7
    records = result.slam.loop_closure.records
    own = [r for r in records if r.match_frame >= 3]
    assert loops["loaded_session"] == 1 and loops["into_loaded_map"] >= 1 and len(own) >= 1
    assert loops["detected"] == len(records) == loops["loaded_session"] + loops["into_loaded_map"] + len(own)
    assert loops["detections"] == len(own)
    assert loops["detection"]["pairs"] >= len(own)  # every registered loop was first a detected candidate
    stamps = {kf.frame_id: kf.obs.timestamp for submap in result.slam.submaps for kf in submap.keyframes}
    for r in own:  # system id - first_frame is the frame's place in this run
        for frame_id in (r.query_frame, r.match_frame):
            assert stamps[frame_id] == result.timestamps[frame_id - result.first_frame]
