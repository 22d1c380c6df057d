"""The tools for GPU sessions: the stack sampler (benchmarks/stack_sampler.py) and the bundle of what the GPU machine
lacks (benchmarks/gpu/bundle.py)."""
import os
import subprocess
import sys
import zipfile
from pathlib import Path

from gpu import bundle

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
