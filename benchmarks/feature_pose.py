"""How accurate is the pose from ORB feature matches (``slam.features.feature_pose``: the feature start of
tracking after a gap, and loop verification's seed for registration)? Per sequence and frame gap g: frame pairs
(i, i + g), i every ``--every`` frames, each pair's pose against the ground truth, for each ``depth_noise`` (0: PnP on
reprojection alone; > 0: the query's depth joins the last refinement). Reports the pairs found and the median
rotation and translation errors. Writes benchmarks/results/feature_pose.json (a results record). Run from the repository root:

    .venv/bin/python benchmarks/feature_pose.py
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from gausem_bench import results
from gausem_bench.data import SHARED_DATA
from gausem_core.config import BowConfig
from gausem_core.data import open_dataset
from gausem_core.slam.features import extract_features, feature_pose
from gausem_core.options import parse_size

SEQUENCES = ["synthetic:loop", "synthetic:loop_noisy", f"tum:{SHARED_DATA / 'tum_fr1_rpy'}",
             f"tum:{SHARED_DATA / '7scenes_redkitchen'}"]


def pose_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(rotation degrees, translation cm) of ``truth^-1 estimate``."""
    delta = np.linalg.inv(truth) @ estimate
    angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return float(angle), float(100 * np.linalg.norm(delta[:3, 3]))


def evaluate(spec: str, size, frames: int, gaps: list[int], every: int, noises: list[float]) -> list[dict]:
    dataset = open_dataset(spec, size=size, max_frames=frames)
    cfg = BowConfig()
    loaded = [dataset[i] for i in range(len(dataset))]
    features = [extract_features(torch.from_numpy(f.rgb).float() / 255, torch.from_numpy(f.depth), f.camera, cfg)
                for f in loaded]
    rows = []
    for gap in gaps:
        for noise in noises:
            errors, missed = [], 0
            for i in range(0, len(loaded) - gap, every):
                first, second = loaded[i], loaded[i + gap]
                found = feature_pose(features[i + gap], features[i], second.camera, cfg.match_ratio,
                                     cfg.max_reprojection_error, cfg.min_inliers, noise)
                if found.query_from_match is None:
                    missed += 1
                    continue
                truth = np.linalg.inv(second.gt_pose) @ first.gt_pose
                errors.append(pose_errors(found.query_from_match.numpy(), truth))
            median = np.median(errors, axis=0) if errors else [float("nan")] * 2
            rows.append({"sequence": dataset.name, "gap": gap, "depth_noise": noise, "found": len(errors),
                         "missed": missed, "rotation_deg_median": float(median[0]),
                         "translation_cm_median": float(median[1])})
    return rows


WHAT = ("`benchmarks/feature_pose.py`: frame pairs g frames apart (one every 20 frames), the RANSAC PnP pose from ORB "
        "matches against the ground truth, per `depth_noise` of its last refinement (0: reprojection alone).")


def markdown(rows: list[dict]) -> str:
    lines = ["| sequence | gap (frames) | depth_noise | pairs found / missed | rotation deg (median) | "
             "translation cm (median) |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['sequence']} | {r['gap']} | {r['depth_noise']:g} | {r['found']} / {r['missed']} | "
                     f"{r['rotation_deg_median']:.2f} | {r['translation_cm_median']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", nargs="+", default=SEQUENCES, help="dataset specs")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--gaps", type=int, nargs="+", default=[1, 3, 6, 10, 14])
    parser.add_argument("--every", type=int, default=20, help="a pair starts every this many frames")
    parser.add_argument("--depth-noise", type=float, nargs="+", default=[0.0, 0.01])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/feature_pose"))
    args = parser.parse_args()
    rows = []
    for spec in args.sequences:
        if spec.startswith("tum:") and not Path(spec[4:]).is_dir():
            print(f"skipping {spec}: folder not found")
            continue
        rows += evaluate(spec, args.size, args.frames, args.gaps, args.every, args.depth_noise)
    results.write_report(args.out, title="The feature pose with the frame's depth", what=WHAT,
                         markdown=markdown(rows), data=rows)


if __name__ == "__main__":
    main()
