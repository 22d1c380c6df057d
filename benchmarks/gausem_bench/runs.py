"""``gausem run`` in fresh processes, for the scripts that compare whole runs (``live_replay.py``,
``keyframe_policy.py``): the arguments they share and one run's metrics."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``--dataset``, ``--size``, ``--frames``, ``--name`` (the record's) and ``--set`` (passed to every run)."""
    parser.add_argument("--dataset", default="synthetic:loop")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, help="at most this many frames (default: all)")
    parser.add_argument("--name", default="synthetic_loop_160x120")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="passed to every run")


def gausem_run(args, out: Path, extra: list[str]) -> dict:
    """One ``gausem run`` in a fresh process; its metrics.json and the recorded frame interval."""
    cmd = [str(Path(sys.executable).parent / "gausem"), "run", "--dataset", args.dataset, "--size", args.size,
           "--quiet", "--out", str(out), *(["--frames", str(args.frames)] if args.frames else []), *extra,
           *(x for s in args.set for x in ("--set", s))]
    result = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({result.returncode}):\n{result.stderr[-3000:]}")
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    stamps = np.loadtxt(out / "trajectory.txt", usecols=0, ndmin=1)
    metrics["interval_s"] = float(np.median(np.diff(stamps))) if len(stamps) > 1 else None
    return metrics
