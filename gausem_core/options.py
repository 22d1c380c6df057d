"""Values the command lines share (``gausem``, the player, the benchmarks): dataset specs, image sizes, ``--set``
overrides and the default parameter file of a dataset kind."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

DATASET_HELP = "synthetic[:default|loop][_noisy], tum:PATH, scannet:PATH or replica:PATH"


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` (e.g. ``160x120``) -> (W, H)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 160x120, got '{text}'") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got '{text}'")
    return w, h


def parse_override(text: str) -> tuple[str, object]:
    """``NAME=VALUE`` -> (NAME, VALUE read as YAML)."""
    name, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--set takes NAME=VALUE (e.g. mapping.iterations=20), got '{text}'")
    return name.strip(), yaml.safe_load(value)


def default_params_file(dataset: str) -> Path | None:
    """params/<kind>.yaml from the source tree or the installed share folder (pip and colcon), if present."""
    kind = dataset.split(":", 1)[0]
    for root in (Path(__file__).resolve().parents[1] / "params", Path(sys.prefix) / "share" / "gausem" / "params"):
        if (root / f"{kind}.yaml").is_file():
            return root / f"{kind}.yaml"
    return None
