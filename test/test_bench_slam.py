"""``gausem bench slam``: suite parsing and validation, the dry run, tables and JSON of a tiny real run, Open3D
baselines (skipped without open3d, a benchmark-only dependency), colour resampling for unregistered depth."""
import dataclasses
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from gausem_bench import results, tables
from gausem_bench.baselines import import_open3d
from gausem_bench.color_registration import ColorCalibration, ColorRegistered
from gausem_bench.data import SHARED_DATA
from gausem_bench.suite import SuiteError, baseline_parameters, gausem_parameters, load_suite, parse_suite, plan
from gausem_bench.cli import main
from gausem_core.data import SyntheticDataset

ROOT = Path(__file__).resolve().parents[1]
SUITES = sorted((ROOT / "benchmarks" / "suites").glob("*.yaml"))
TINY = {"device": "cpu", "mapping.init_iterations": 3, "mapping.iterations": 2,
        "tracking.gauss_newton.level_iterations": 2,
        "health.lost_coverage": 0.0}  # maps of 3 iterations render no silhouette pixel: every frame would be lost


def write_suite(path: Path, document: dict) -> Path:
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def tiny_suite(tmp_path: Path, configurations: list[dict]) -> Path:
    return write_suite(tmp_path / "tiny.yaml", {
        "name": "tiny", "defaults": {"size": "64x48", "frames": 6, "eval_every": 3},
        "sequences": [{"name": "synth", "dataset": "synthetic:default", "open3d": {"depth_max": 6.0}}],
        "configurations": configurations})


# --- suites ---------------------------------------------------------------------------------------------------------
def test_suite_parsing_applies_defaults_flattens_overrides_and_selects():
    suite = parse_suite(yaml.safe_load("""
        defaults: {size: 80x60, frames: 10}
        sequences:
          - {dataset: "synthetic:loop"}
          - {name: other, dataset: "synthetic:default", frames: 4, stride: 2, open3d: {depth_max: 5}}
        configurations:
          - {name: full}
          - {name: no_loop, overrides: {loop: {enabled: false}, submaps.policy: motion}, note: ablation}
          - {name: o3d, method: open3d_slam}
    """), "fallback_name")
    assert suite.name == "fallback_name"
    first, second = suite.sequences
    assert (first.name, first.size, first.frames, first.stride) == ("synthetic_loop", (80, 60), 10, 1)
    assert (second.name, second.frames, second.stride, second.open3d) == ("other", 4, 2, {"depth_max": 5})
    assert suite.configurations[1].overrides == {"loop.enabled": False, "submaps.policy": "motion"}
    assert [c.method for c in suite.configurations] == ["gausem", "gausem", "open3d_slam"]
    picked = suite.select(["other"], ["o3d", "full"])
    assert [s.name for s in picked.sequences] == ["other"]
    assert [c.name for c in picked.configurations] == ["full", "o3d"]  # suite order, not the filter's
    with pytest.raises(SuiteError, match="unknown configuration 'ful'.*did you mean 'full'"):
        suite.select(None, ["ful"])


@pytest.mark.parametrize("document, message", [
    ({"configurations": [{"name": "a", "overides": {}}]}, "unknown key 'overides'.*did you mean 'overrides'"),
    ({"configurations": [{"name": "a", "method": "orbslam"}]}, "unknown method 'orbslam'"),
    ({"configurations": [{"name": "a"}, {"name": "a"}]}, "configuration 'a' appears more than once"),
    ({"sequences": [{"name": "s"}], "configurations": [{"name": "a"}]}, "'dataset' is required"),
    ({"sequences": [{"dataset": "synthetic", "frames": 0}], "configurations": [{"name": "a"}]}, "frames must be"),
    ({"sequences": [{"dataset": "synthetic", "size": "64by48"}], "configurations": [{"name": "a"}]}, "size"),
    ({"sequences": [{"dataset": "synthetic", "open3d": {"voxel": 1}}], "configurations": [{"name": "a"}]},
     "unknown parameter 'voxel'.*did you mean 'voxel_size'"),
    ({"sequences": [{"dataset": "synthetic", "color_calibration": {"intrinsics": [1, 2, 3]}}],
      "configurations": [{"name": "a"}]}, "color_calibration"),
    ({"sequences": []}, "no configurations"),
])
def test_bad_suites_fail_clearly(document, message):
    with pytest.raises(SuiteError, match=message):
        parse_suite(document, "bad")


def test_unknown_parameters_fail_before_anything_runs(tmp_path, capsys):
    code = main(["slam", "--dataset", "synthetic", "--set", "mapping.iteratons=3", "--dry-run",
                 "--out", str(tmp_path / "res")])
    err = capsys.readouterr().err
    assert code == 2 and "unknown parameter 'mapping.iteratons'" in err and "did you mean 'mapping.iterations'" in err
    suite = tiny_suite(tmp_path, [{"name": "old", "overrides": {"tracking.iterations": 3}}])
    assert main(["slam", "--suite", str(suite), "--dry-run"]) == 2
    assert ("configuration 'old': renamed parameter: 'tracking.iterations' is now 'tracking.adam.iterations'"
            in capsys.readouterr().err)
    suite = tiny_suite(tmp_path, [{"name": "abl", "overrides": {"submap.policy": "motion"}}])
    assert main(["slam", "--suite", str(suite), "--dry-run"]) == 2
    assert "configuration 'abl': unknown parameter 'submap.policy'" in capsys.readouterr().err
    suite = tiny_suite(tmp_path, [{"name": "o3d", "method": "open3d_odometry", "overrides": {"depth_maximum": 4}}])
    assert main(["slam", "--suite", str(suite), "--dry-run"]) == 2
    assert "unknown parameter 'depth_maximum'" in capsys.readouterr().err
    suite = tiny_suite(tmp_path, [{"name": "typed", "overrides": {"loop.enabled": "no"}}])
    assert main(["slam", "--suite", str(suite), "--dry-run"]) == 2
    assert "loop.enabled" in capsys.readouterr().err
    assert not (tmp_path / "res").exists()


def test_a_suite_runs_the_sequences_of_another(tmp_path):
    """``sequences_of``: the other file's sequences and defaults, the suite's own defaults on top; with sequences of
    its own, or a missing file, a clear error."""
    write_suite(tmp_path / "base.yaml", {"defaults": {"size": "80x60", "frames": 10},
                                         "sequences": [{"dataset": "synthetic:loop"}, {"dataset": "synthetic"}],
                                         "configurations": [{"name": "g"}]})
    suite = load_suite(write_suite(tmp_path / "cmp.yaml", {"sequences_of": "base.yaml", "defaults": {"frames": 4},
                                                           "configurations": [{"name": "a"}, {"name": "b"}]}))
    assert [(s.name, s.size, s.frames) for s in suite.sequences] == [("synthetic_loop", (80, 60), 4),
                                                                     ("synthetic_default", (80, 60), 4)]
    assert (suite.name, [c.name for c in suite.configurations]) == ("cmp", ["a", "b"])
    for document, message in (({"sequences_of": "none.yaml"}, "does not exist"),
                              ({"sequences_of": "base.yaml", "sequences": []}, "not both")):
        with pytest.raises(SuiteError, match=message):
            load_suite(write_suite(tmp_path / "bad.yaml", {**document, "configurations": [{"name": "a"}]}))


@pytest.mark.parametrize("path", SUITES, ids=[p.stem for p in SUITES])
def test_committed_suites_name_only_known_parameters(path):
    suite = load_suite(path)
    assert suite.configurations
    for sequence in suite.sequences:
        for configuration in suite.configurations:
            if configuration.method == "gausem":
                _, _, parameters = gausem_parameters(sequence, configuration, {})
                assert all(parameters[name] == value for name, value in configuration.overrides.items())
            else:
                _, parameters = baseline_parameters(sequence, configuration)
                assert all(parameters[name] == value for name, value in sequence.open3d.items())


def test_plan_resolves_every_parameter_and_the_seed(tmp_path):
    suite = parse_suite({"sequences": [{"dataset": "synthetic", "frames": 7, "stride": 2}],
                         "configurations": [{"name": "g", "overrides": {"seed": 3, "loop.enabled": False}},
                                            {"name": "o", "method": "open3d_slam"}]}, "s")
    gausem, baseline = plan(suite, tmp_path, overrides={"mapping.iterations": 4})
    assert gausem.frames == 7 and gausem.dataset_name == "synthetic_default" and gausem.depth_registered
    assert gausem.seed == 3 and gausem.parameters["loop.enabled"] is False
    assert gausem.parameters["mapping.iterations"] == 4
    assert gausem.overrides == {"seed": 3, "loop.enabled": False, "mapping.iterations": 4}
    assert gausem.params_file.endswith("synthetic.yaml") and gausem.out_dir == tmp_path / "synthetic_default" / "g"
    assert baseline.parameters["method"] == "point_to_plane" and "mapping.iterations" not in baseline.parameters
    with pytest.raises(SuiteError, match="sequence 'nowhere'.*does not exist"):
        plan(parse_suite({"sequences": [{"name": "nowhere", "dataset": f"tum:{tmp_path / 'none'}"}],
                          "configurations": [{"name": "g"}]}, "s"), tmp_path)


def test_dry_run_lists_the_runs_and_runs_nothing(tmp_path, capsys):
    code = main(["slam", "--suite", str(ROOT / "benchmarks/suites/smoke.yaml"), "--dry-run",
                 "--out", str(tmp_path / "res"), "--work", str(tmp_path / "work")])
    out = capsys.readouterr().out
    suite = load_suite(ROOT / "benchmarks/suites/smoke.yaml")
    assert code == 0 and f"{len(suite.configurations)} runs planned" in out
    assert all(f"synthetic_default / {c.name}" in out for c in suite.configurations)
    assert not (tmp_path / "res").exists() and not (tmp_path / "work").exists()


# --- tables ---------------------------------------------------------------------------------------------------------
def record(sequence, configuration, metrics, method="gausem", status="ok", **extra):
    return {"sequence": sequence, "configuration": configuration, "method": method, "status": status,
            "metrics": metrics, "overrides": {}, "frames": 10, "size": [160, 120], "seed": 0, "out_dir": "x",
            **extra}


def test_tables_average_only_complete_rows_and_show_loops_when_reported():
    runs = [record("a", "full", {"ate_rmse_cm": 2.0, "loops": {"precision": 0.5, "recall": 1.0, "f1": 2 / 3},
                                 "rendering": {"psnr": 20.0}}),
            record("b", "full", {"ate_rmse_cm": 4.0, "rendering": {"psnr": 30.0}}, depth_registered=False),
            record("a", "o3d", {"ate_rmse_cm": 3.0}, method="open3d_odometry"),
            record("b", "o3d", {}, method="open3d_odometry", status="failed", error="boom | bang")]
    grid = tables.Grid(runs)
    assert grid.headers == ["a", "b" + tables.UNREGISTERED]
    assert grid.row("full", tables.ATE) == ["3.00", "2.00", "4.00"]
    assert grid.row("o3d", tables.ATE) == ["–", "3.00", "–"]  # no average over an incomplete row
    report = tables.markdown_report(runs, "t")
    assert "| a | full | 0.50 | 1.00 | 0.67 | 20.00 | 2.00 |" in report  # Tab. VII shape
    assert "| full | PSNR [dB] ↑ | 25.00 | 20.00 | 30.00 |" in report
    assert "failed: boom \\| bang" in report and "Ablations" not in report  # one GauSem configuration only
    assert tables.UNREGISTERED + " depth not registered" in report
    assert "Loop detection" not in tables.markdown_report(runs[1:], "t")


# --- a tiny real run ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_tiny_run_writes_json_and_paper_shaped_tables(tmp_path):
    suite = tiny_suite(tmp_path, [{"name": "full", "overrides": TINY},
                                  {"name": "no_loop", "overrides": {**TINY, "loop.enabled": False}}])
    res = tmp_path / "res"
    assert main(["slam", "--suite", str(suite), "--out", str(res), "--work", str(tmp_path / "work"),
                 "--quiet", "--threads", "1"]) == 0
    record = results.read(res / "slam_tiny.json")
    document = record["data"]
    assert document["suite"] == "tiny" and "--suite" in record["command"] and record["date"]
    assert not list(res.glob("*.md"))
    full, ablated = document["runs"]
    for run in (full, ablated):
        assert run["status"] == "ok" and run["frames"] == 6 and run["seed"] == 0 and run["threads"] == 1
        assert run["git_commit"] and run["device"].startswith("cpu")
        assert run["parameters"]["mapping.iterations"] == 2 and run["metrics"]["frames"] == 6
        assert run["metrics"]["fps"] > 0 and run["metrics"]["peak_rss_mb"] > 0
        assert run["metrics"]["rendering"]["frames"] == 2  # frames 0 and 3 with eval_every 3
        assert all((Path(run["out_dir"]) / name).is_file() for name in ("metrics.json", "trajectory.txt"))
    assert full["parameters"]["loop.enabled"] is True and ablated["parameters"]["loop.enabled"] is False
    tables = [record["table"], *record.get("tables", [])]
    for heading in ("Tracking", "Rendering", "Ablations", "Runtime and memory"):
        assert any(t["title"].startswith(heading) for t in tables)
    markdown = "\n".join(results.markdown_table(t) for t in tables)
    psnr, miou = full["metrics"]["rendering"]["psnr"], full["metrics"]["rendering"]["miou"]
    assert f"| full | PSNR [dB] ↑ | {psnr:.2f} |" in markdown
    assert f"| full | mIoU [%] ↑ | {100 * miou:.1f} |" in markdown
    assert "loop.enabled=False" in markdown
    ate = full["metrics"]["ate_rmse_cm"]
    assert f"| full | {'–' if ate is None else f'{ate:.2f}'} |" in markdown


def _spawned_children(pid: int) -> list[int]:
    """Children of ``pid`` started by multiprocessing's spawn (Linux /proc)."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [int(c) for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_sigterm_stops_the_running_case_too(tmp_path):
    """SIGTERM to `gausem bench slam` while a run's process works: both end (the run's process is not orphaned)."""
    suite = tiny_suite(tmp_path, [{"name": "full", "overrides": TINY}])
    command = [sys.executable, str(ROOT / "benchmarks" / "bench.py"), "slam", "--suite", str(suite), "--frames", "180", "--out", str(tmp_path / "res"), "--work",
               str(tmp_path / "work"), "--quiet", "--threads", "1"]
    harness = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (children := _spawned_children(harness.pid)) and time.monotonic() < deadline:
            assert harness.poll() is None, "the harness ended before starting its run"
            time.sleep(0.2)
        assert children, "no run process appeared"
        time.sleep(1.0)
        harness.send_signal(signal.SIGTERM)
        assert harness.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if harness.poll() is None:
            harness.kill()
    for child in children:
        assert not Path(f"/proc/{child}").exists()


# --- Open3D baselines -----------------------------------------------------------------------------------------------
def test_missing_open3d_gives_an_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    with pytest.raises(ImportError, match="requirements-bench.txt"):
        import_open3d()


def test_the_harness_does_not_import_open3d_until_a_baseline_runs():
    code = ("import sys, gausem_bench.cli as cli, argparse; cli.add_arguments(argparse.ArgumentParser()); "
            "import gausem_bench.slam, gausem_bench.worker, gausem_bench.tables; assert 'open3d' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT / "benchmarks")


def test_the_library_does_not_know_the_harness():
    """No arrow up the layers: every `gausem` command's parser builds without importing gausem_bench."""
    code = ("import sys, gausem_core.cli as cli; [cli.build_parser(name) for name in cli.COMMANDS]; "
            "assert 'bench' not in cli.COMMANDS and not any(m.startswith('gausem_bench') for m in sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.mark.parametrize("method", ["open3d_odometry", "open3d_slam"])
def test_open3d_baselines_track_the_synthetic_frames(tmp_path, method):
    pytest.importorskip("open3d")
    from gausem_bench.worker import run_case

    suite = parse_suite({"sequences": [{"dataset": "synthetic", "frames": 8, "open3d": {"depth_max": 6.0}}],
                         "configurations": [{"name": "b", "method": method}]}, "s")
    (case,) = plan(suite, tmp_path, progress=False)
    result = run_case(case)
    assert result["status"] == "ok", result.get("error")
    metrics = result["metrics"]
    assert metrics["frames"] == 8 and metrics["tracking_failures"] == 0 and metrics["ate"]["pairs"] == 8
    estimate = np.loadtxt(tmp_path / "synthetic_default" / "b" / "trajectory.txt")[:, 1:4]
    truth = np.stack([SyntheticDataset(max_frames=8)[i].gt_pose[:3, 3] for i in range(8)])
    # the camera moves about 4 cm per frame: the estimate follows it (path length) and stays close (ATE)
    path = lambda p: np.linalg.norm(np.diff(p, axis=0), axis=1).sum()  # noqa: E731
    assert path(estimate) == pytest.approx(path(truth), rel=0.3)
    assert metrics["ate"]["rmse"] < 0.25 * path(truth)


# --- colour resampled into the depth camera -------------------------------------------------------------------------
def test_color_resampling_undoes_a_known_colour_camera():
    frame = SyntheticDataset(max_frames=1)[0]  # colour and depth registered: a depth-camera view
    cam = frame.camera
    scale = 0.9  # a colour camera with a wider field of view, as in 7-Scenes (525 vs 585 px)
    color_camera = dataclasses.replace(cam, fx=cam.fx * scale, fy=cam.fy * scale)
    calibration = ColorCalibration((color_camera.fx, color_camera.fy, cam.cx - 0.5, cam.cy - 0.5), frame.size)
    # what that colour camera would see: the frame's image shrunk about the principal point
    matrix = np.array([[scale, 0, (1 - scale) * (cam.cx - 0.5)], [0, scale, (1 - scale) * (cam.cy - 0.5)]])
    seen = cv2.warpAffine(frame.rgb, matrix, frame.size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    unaligned = dataclasses.replace(frame, rgb=seen)

    class One:
        name, class_table = "one", None

        def __len__(self):
            return 1

        def __getitem__(self, i):
            return unaligned

    resampled = ColorRegistered(One(), calibration)[0]
    inner = (slice(10, -10), slice(10, -10))
    error_before = np.abs(seen.astype(float) - frame.rgb)[inner].mean()
    error_after = np.abs(resampled.rgb.astype(float) - frame.rgb)[inner].mean()
    assert error_after < 0.5 * error_before and resampled.camera == frame.camera
    assert np.array_equal(resampled.depth, frame.depth) and math.isclose(resampled.timestamp, frame.timestamp)


# --- the shared data setting ----------------------------------------------------------------------------------------
def test_suites_name_the_shared_sequences_through_the_one_setting():
    suite = parse_suite({"sequences": [{"dataset": "tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy"}],
                         "configurations": [{"name": "g"}]}, "s")
    assert [s.dataset for s in suite.sequences] == [f"tum:{SHARED_DATA / 'tum_fr1_rpy'}"]
    assert all("$GAUSEM_SHARED_DATA/" in path.read_text() for path in SUITES if "tum:" in path.read_text())
