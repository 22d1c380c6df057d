"""Does tracking against a map built from noisy depth under-estimate the camera's motion? (issue #25)

A one-keyframe map is built from frame 0 of the synthetic walk at its true pose (initialisation and
``mapping.init_iterations`` of optimisation, ``params/synthetic.yaml``), from the clean depth, the depth through the
sensor model's axial noise, or that noisy depth through the depth filter (``slam.depth_filter``). Frames 2, 4, ...
are then tracked against it from the constant-velocity prediction of their true poses. Per frame: the motion ratio,
the estimated displacement from the keyframe projected on the true one over the true one (1: exact, < 1: the motion
comes out too short, the trajectory shrinks). In both noisy variants the tracked frames are the raw noisy ones, so
the rows differ only in the map. Writes
benchmarks/results/<name>.json (a results record). From the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/depth_noise_tracking.py
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from gausem_bench import results
from gausem_core.config import SensorConfig, load_config
from gausem_core.data import SyntheticDataset
from gausem_core.data.sensor import COLOR_EFFECTS, DEPTH_EFFECTS
from gausem_core.pipeline import Pipeline
from gausem_core.slam.depth_filter import filter_observation
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.tracker import Tracker, constant_velocity
from gausem_core.options import default_params_file

ROOT = Path(__file__).resolve().parents[1]
WHAT = ("`benchmarks/depth_noise_tracking.py` builds a one-keyframe map from frame 0 at its true pose (clean depth, depth "
        "with the axial noise alone, or that noisy depth filtered) and tracks frames 2-14 against it from the "
        "constant-velocity prediction of their true poses; the motion ratio is the estimated displacement from the "
        "keyframe over the true one (1: exact, < 1: too short). Synthetic walk at 160x120.")
AXIAL_NOISE = SensorConfig(**{name: name == "axial_noise" for name in DEPTH_EFFECTS + COLOR_EFFECTS})
VARIANTS = ("clean", "noisy", "noisy, filtered")


def motion_ratios(variant: str, frames: list[int]) -> list[float]:
    """The motion ratio of each of ``frames`` tracked against the one-keyframe map of ``variant``."""
    cfg = load_config(default_params_file("synthetic"), {"depth_filter.enabled": False})
    dataset = SyntheticDataset("default", sensor=None if variant == "clean" else AXIAL_NOISE, size=(160, 120),
                               max_frames=max(frames) + 1)
    pipeline = Pipeline(dataset, cfg, progress=False)

    def pose(i):
        return torch.as_tensor(dataset[i].gt_pose, dtype=torch.float32)
    keyframe = pipeline.observation(dataset[0])
    if variant.endswith("filtered"):
        keyframe = filter_observation(keyframe, replace(cfg.depth_filter, enabled=True))
    mapper = Mapper(cfg.mapping, cfg.backend, cfg.seed)
    cloud, _ = mapper.optimise(mapper.strategy.initial(keyframe, pose(0)), [Keyframe(0, keyframe, pose(0), fixed=True)],
                               cfg.mapping.init_iterations)
    tracker, ratios = Tracker(cfg.tracking, cfg.backend), []
    for i in frames:
        start = constant_velocity(pose(i - 1), pose(i - 2))
        estimate = tracker.track(cloud, pipeline.observation(dataset[i]), start, [pose(i - 1)]).cam_to_world
        true, moved = (pose(i) - pose(0))[:3, 3].double(), (estimate - pose(0))[:3, 3].double()
        ratios.append(float(moved @ true / (true @ true)))
    return ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=list(range(2, 16, 2)),
                        help="frames to track (>= 2; the map covers about the first 15)")
    parser.add_argument("--name", default="depth_noise_tracking")
    args = parser.parse_args()
    torch.manual_seed(0)
    rows = {variant: motion_ratios(variant, args.frames) for variant in VARIANTS}
    document = {"frames": args.frames, "sensor": "axial_noise only", "rows": rows}
    lines = ["| Map built from | " + " | ".join(f"frame {i}" for i in args.frames) + " | median |",
             "|---|" + "---|" * (len(args.frames) + 1)]
    for variant, ratios in rows.items():
        lines.append(f"| {variant} depth | " + " | ".join(f"{r:.3f}" for r in ratios)
                     + f" | **{np.median(ratios):.3f}** |")
    results.write_report(results.RESULTS / args.name, title="Why noisy depth shrinks the trajectory", what=WHAT,
                         markdown="\n".join(lines), data=document)


if __name__ == "__main__":
    main()
