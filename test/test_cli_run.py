"""``gausem run`` end to end on a few small synthetic frames: the outputs exist and the figures are sane."""
import json
import math

import pytest

from gausem_core.cli import main
from gausem_core.io.ply import read_gaussian_ply
from gausem_core.io.trajectory import read_tum_trajectory

FAST = ["--set", "mapping.init_iterations=60", "--set", "mapping.iterations=5"]


def test_gausem_run_writes_the_outputs(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--dataset", "synthetic", "--frames", "6", "--size", "80x60", *FAST, "--quiet",
                 "--set", "device=cpu", "--out", str(out)]) == 0
    assert "ATE RMSE" in capsys.readouterr().out
    for name in ("trajectory.txt", "trajectory_gt.txt", "keyframes.txt", "map.ply", "metrics.json", "montage.png",
                 "trajectory.png"):
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
