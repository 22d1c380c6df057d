"""A TUM RGB-D folder made small enough to carry to the GPU machine: the colour images as JPEG (quality 95, about 0.2
MB a frame at 640x480 against 0.56 MB as PNG), depth, ground truth and calibration as they are, the lists rewritten to
the JPEG names. ``benchmarks/gpu/acceptance.sh`` reads it from ``.gpu/tum_fr1_rpy`` (git-ignored; carry it in a call
of its own: it does not fit beside the prefix).

    .venv/bin/python benchmarks/gpu/pack_tum.py ${GAUSEM_SHARED_DATA:-../shared/data}/tum_fr1_rpy .gpu/tum_fr1_rpy
"""
from __future__ import annotations

import argparse
import re
import shutil
from pathlib import Path

import cv2

LISTS = ("rgb.txt", "associations.txt")  # the files that name colour images


def pack(source: Path, target: Path, quality: int = 95) -> int:
    """Write the small copy of ``source`` into ``target``; returns its size in bytes."""
    if not (source / "rgb.txt").is_file():
        raise SystemExit(f"{source}: not a TUM folder (no rgb.txt)")
    (target / "rgb").mkdir(parents=True, exist_ok=True)
    for path in sorted((source / "rgb").glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or not cv2.imwrite(str(target / "rgb" / f"{path.stem}.jpg"), image,
                                            [cv2.IMWRITE_JPEG_QUALITY, quality]):
            raise SystemExit(f"{path}: cannot convert to JPEG")
    for path in source.iterdir():
        if path.name == "rgb":
            continue
        if path.is_dir():
            shutil.copytree(path, target / path.name, dirs_exist_ok=True)
        elif path.name in LISTS:
            text = re.sub(r"(rgb/[^\s]+)\.png", r"\1.jpg", path.read_text())
            (target / path.name).write_text(text)
        else:
            shutil.copy2(path, target / path.name)
    return sum(p.stat().st_size for p in target.rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a TUM RGB-D folder")
    parser.add_argument("target", type=Path, help="where the small copy goes")
    parser.add_argument("--quality", type=int, default=95, help="JPEG quality")
    args = parser.parse_args(argv)
    size = pack(args.source, args.target, args.quality)
    print(f"wrote {args.target} ({size / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
