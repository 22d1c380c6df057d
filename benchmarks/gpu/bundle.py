"""Packs what the GPU machine lacks (``../shared/notes/gpu.md``) into ``.gpu/prefix.txz``, to carry along to it.

The machine has Python 3.12, torch with CUDA, numpy, OpenCV and the rest, but not gsplat, gtsam, rosbags or the
ROS 2 wheels. This downloads the cp312 builds of the versions installed in ``.venv`` (``make setup`` first) plus gsplat,
unpacks each wheel as pip would into a prefix (packages into ``site/``, the ROS wheels' data into ``lib/`` and
``share/``), drops what only building needs (headers, static libraries, CMake files, gtsam's data and tests) and
writes it xz-compressed (about 38 MB, within the 64 MiB a call carries). ``benchmarks/gpu/env.sh`` unpacks it there.

    .venv/bin/python benchmarks/gpu/bundle.py [--out .gpu]
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from importlib import metadata
from pathlib import Path

GSPLAT = "gsplat==1.5.3"
WANTED = re.compile(r"^(ros-|gtsam$|rosbags$|lz4$|ruamel\.yaml$|lark-parser$|apsw$|backports\.zstd$)", re.I)
BUILD_ONLY = ("ros_ament_cmake",)  # wheel-name prefixes that only building messages needs
PLATFORMS = ["manylinux_2_39_x86_64", "manylinux_2_35_x86_64", "manylinux_2_34_x86_64", "manylinux_2_28_x86_64",
             "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux1_x86_64"]
PRUNE = ["include", "tools", "site/gtsam/Data", "site/gtsam/tests", "site/gtsam_unstable"]


def requirements() -> list[str]:
    """``name==version`` of the installed distributions the GPU machine lacks, and gsplat."""
    found = {d.metadata["Name"]: d.version for d in metadata.distributions() if WANTED.match(d.metadata["Name"])}
    return sorted(f"{name}=={version}" for name, version in found.items()) + [GSPLAT]


def download(specs: list[str], folder: Path) -> None:
    platforms = [arg for p in PLATFORMS for arg in ("--platform", p)]
    for spec in specs:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
                        "--python-version", "3.12", "--implementation", "cp", *platforms, "-d", str(folder), spec],
                       check=True)


def unpack(wheel: Path, prefix: Path) -> None:
    """Install ``wheel`` into ``prefix`` as pip's prefix scheme would, with ``site/`` as its site-packages."""
    with zipfile.ZipFile(wheel) as archive:
        for info in archive.infolist():
            if info.is_dir():
                continue
            top, _, rest = info.filename.partition("/")
            if top.endswith(".data"):
                scheme, _, rest = rest.partition("/")
                target = prefix / ("site" if scheme in ("purelib", "platlib") else "" if scheme == "data"
                                   else scheme) / rest
            else:
                target = prefix / "site" / info.filename
            target.parent.mkdir(parents=True, exist_ok=True)
            with archive.open(info) as source, open(target, "wb") as sink:
                shutil.copyfileobj(source, sink)
            if (info.external_attr >> 16) & 0o111:
                target.chmod(0o755)


def prune(prefix: Path) -> None:
    for relative in PRUNE:
        shutil.rmtree(prefix / relative, ignore_errors=True)
    for pattern in ("*.a", "*.cmake"):
        for path in prefix.rglob(pattern):
            path.unlink()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(".gpu"), help="folder for prefix.txz (git-ignored)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        wheels, prefix = Path(tmp) / "wheels", Path(tmp) / "prefix"
        download(requirements(), wheels)
        for wheel in sorted(wheels.glob("*.whl")):
            if not wheel.name.startswith(BUILD_ONLY):
                unpack(wheel, prefix)
        prune(prefix)
        with tarfile.open(args.out / "prefix.txz", "w:xz") as archive:
            archive.add(prefix, arcname=".")
    print(f"wrote {args.out / 'prefix.txz'} ({(args.out / 'prefix.txz').stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
