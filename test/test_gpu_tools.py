"""The tools for GPU sessions: the stack sampler (benchmarks/stack_sampler.py), the bundle of what the GPU machine
lacks (benchmarks/gpu/bundle.py), the acceptance record (benchmarks/gpu/acceptance.py) and the small TUM copy
(benchmarks/gpu/pack_tum.py)."""
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np

from gausem_core.data import SyntheticDataset, open_dataset, write_tum_folder
from gpu import acceptance, bundle, pack_tum

ROOT = Path(__file__).resolve().parents[1]

BUSY_MODULE = '''
import os, threading, time

def spin_here(seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sum(range(1000))

worker = threading.Thread(target=spin_here, args=(1.5,), name="busy")
worker.start()
worker.join()
print("module output")
os._exit(3)  # as GauSem's commands end: no interpreter teardown, no finally
'''


def test_the_stack_sampler_reports_each_thread_and_its_cpu_also_after_os_exit(tmp_path):
    (tmp_path / "busymod.py").write_text(BUSY_MODULE)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "stack_sampler.py"), "--interval", "0.005",
                             "-m", "busymod"], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 3  # the module's own exit code
    assert "module output" in result.stdout
    report = result.stderr
    assert "[stack-sampler] thread busy:" in report
    busy = report.split("[stack-sampler] thread busy:")[1].split("[stack-sampler]")[0]
    assert "spin_here (busymod.py:" in busy
    cpu_rows = [line for line in report.splitlines() if line.startswith("[stack-sampler] cpu") and "busy [" in line]
    assert len(cpu_rows) == 1 and float(cpu_rows[0].split()[2]) > 0.5  # 1.5 s of spinning, mostly on a core


def test_the_sampler_needs_a_module():
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "stack_sampler.py")], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode != 0 and "usage" in result.stderr


def test_a_wheel_unpacks_as_a_prefix_install(tmp_path):
    wheel = tmp_path / "ros_demo-1.0-cp312-cp312-manylinux_2_28_x86_64.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        archive.writestr("demo/__init__.py", "X = 1\n")
        library = zipfile.ZipInfo("ros_demo-1.0.data/data/lib/libdemo.so")
        library.external_attr = 0o755 << 16
        archive.writestr(library, b"\x7fELF")
        archive.writestr("ros_demo-1.0.data/data/lib/python3.12/site-packages/demo_msgs/__init__.py", "")
        archive.writestr("ros_demo-1.0.data/data/include/demo.h", "")
        archive.writestr("ros_demo-1.0.data/data/share/demo/cmake/demoConfig.cmake", "")
        archive.writestr("ros_demo-1.0.data/purelib/demo_extra.py", "")
        archive.writestr("ros_demo-1.0.data/scripts/demo-tool", "")
    prefix = tmp_path / "prefix"
    bundle.unpack(wheel, prefix)
    assert (prefix / "site" / "demo" / "__init__.py").read_text() == "X = 1\n"
    assert (prefix / "site" / "demo_extra.py").exists()
    assert (prefix / "lib" / "python3.12" / "site-packages" / "demo_msgs" / "__init__.py").exists()
    assert os.access(prefix / "lib" / "libdemo.so", os.X_OK)
    assert (prefix / "scripts" / "demo-tool").exists()
    bundle.prune(prefix)
    assert not (prefix / "include").exists()
    assert not (prefix / "share" / "demo" / "cmake" / "demoConfig.cmake").exists()
    assert (prefix / "lib" / "libdemo.so").exists()


def test_the_bundle_asks_for_gsplat_and_the_installed_ros_wheels():
    wanted = bundle.requirements()
    assert bundle.GSPLAT in wanted
    assert all("==" in spec for spec in wanted)
    assert any(spec.lower().startswith("ros-jazzy-rclpy==") for spec in wanted)  # a requirements.txt pin


def write_metrics(folder: Path, stage: str, **metrics) -> None:
    (folder / stage).mkdir(parents=True)
    (folder / stage / "metrics.json").write_text(json.dumps({"metrics": metrics}))


def test_the_acceptance_record_judges_each_criterion_and_marks_the_stages_not_run(tmp_path):
    write_metrics(tmp_path, "sync", tracking_ms_median=12.0, mapping_ms_median=200.0, fps=11.0, ate_rmse_cm=1.0,
                  num_gaussians=900_000)
    write_metrics(tmp_path, "realtime", ate_rmse_cm=1.2, live={"frames_processed": 340, "frames_released": 360})
    (tmp_path / "tests.txt").write_text("....\n12 passed, 3 skipped in 41.2s\n")
    (tmp_path / "live.txt").write_text("== 3 s: apart\nprocessed 300 of 360 frames; gaps median 1.0; ATE 1.50 cm\n")
    for name, value in (("machine", "Xeon, 16 cores, NVIDIA H200"), ("commit", "0123abcd"), ("date", "2026-12-01")):
        (tmp_path / f"{name}.txt").write_text(value + "\n")
    rows = {name: (value, met) for name, _, value, met in acceptance.criteria(tmp_path)}
    assert rows["CUDA tests"] == ("12 passed, 3 skipped in 41.2s", True)
    assert rows["tracking a frame (ms)"] == (12.0, True) and rows["mapping a keyframe (ms)"] == (200.0, False)
    assert rows["sync fps, synthetic loop"] == (11.0, True)
    assert rows["sync fps, TUM fr1/rpy"] == (None, None)  # the stage did not run: not measured, not failed
    assert rows["tracking a frame, torch step (ms)"] == (None, None)
    assert rows["Gaussians at the end, synthetic loop, defaults"] == (900_000, None)  # reported, not judged
    assert rows["--realtime 1 frames processed, synthetic loop"] == (340 / 360, True)
    assert rows["--realtime 1 ATE / sync ATE, synthetic loop"][1] is True  # 1.2x
    assert rows["live node at 30 Hz: frames processed"] == (300 / 360, False)
    assert rows["live node at 30 Hz: ATE (cm)"] == (1.5, True)

    acceptance.main([str(tmp_path), "--name", str(tmp_path / "record")])
    doc = json.loads((tmp_path / "record.json").read_text())
    assert (doc["machine"], doc["commit"], doc["date"]) == ("Xeon, 16 cores, NVIDIA H200", "0123abcd", "2026-12-01")
    cells = {row[0]: row[2:] for row in doc["table"]["rows"]}
    assert cells["sync fps, TUM fr1/rpy"] == ["not measured", "-"]
    assert cells["mapping a keyframe (ms)"] == ["200", "no"]


def test_a_packed_tum_folder_reads_as_the_original_with_its_colour_as_jpeg(tmp_path):
    original = write_tum_folder(SyntheticDataset("default", resolution=(64, 48), max_frames=3), tmp_path / "tum")
    size = pack_tum.pack(original, tmp_path / "small")
    assert size > 0 and sorted(p.suffix for p in (tmp_path / "small" / "rgb").iterdir()) == [".jpg"] * 3
    before, after = open_dataset(f"tum:{original}"), open_dataset(f"tum:{tmp_path / 'small'}")
    assert len(after) == len(before) == 3
    for a, b in zip(after, before):
        assert np.array_equal(a.depth, b.depth) and np.allclose(a.gt_pose, b.gt_pose)
        assert np.abs(a.rgb.astype(float) - b.rgb.astype(float)).mean() < 0.05 * float(b.rgb.max())
