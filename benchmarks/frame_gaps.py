"""Tracking across the frames a live node skips: the sequence's frames with seeded random gaps (``--min-gap`` to
``--max-gap`` source frames between processed ones, true stamps kept, the frames left out counted as skipped, as a
node slower than its camera sees and reports them; equal bounds: a node steadily N times slower), run with each
variant (``--variants``: comma-separated SLAM parameter overrides, "" for the defaults); loop closure and the global
refinement off, so the ATE is tracking's. Reports ATE, tracking status counts and seconds a frame. Run from the
repository root, e.g.
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/frame_gaps.py --source "tum:${GAUSEM_SHARED_DATA:-../shared/data}/tum_fr1_rpy" \
        --max-gap 3 --variants tracking.gauss_newton.search=never "" --out benchmarks/results/frame_gaps_tum_fr1_rpy
"""
from __future__ import annotations

import argparse
import time
from collections import Counter
from pathlib import Path

import numpy as np

from gausem_bench import results
from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.io.trajectory import Trajectory
from gausem_core.pipeline import Pipeline
from gausem_core.report import trajectory_metrics
from gausem_core.options import default_params_file, parse_override, parse_size

WHAT = ("Live-like patterns offline: seeded gaps, true stamps, the skipped frames counted as the tracking node counts "
        "the frames it drops; each variant's overrides in its row.")


class SkippedFrames:
    """The frames of ``dataset`` at ``positions`` (a dataset view: the others are never seen)."""

    def __init__(self, dataset, positions: list[int]):
        self._dataset, self.positions = dataset, positions

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, i: int):
        return self._dataset[self.positions[i]]

    def __getattr__(self, name: str):
        return getattr(self._dataset, name)


def live_positions(length: int, min_gap: int, max_gap: int, seed: int) -> list[int]:
    """0, then each next position ``min_gap`` to ``max_gap`` frames on (uniform, seeded)."""
    rng = np.random.default_rng(seed)
    positions = [0]
    while (following := positions[-1] + int(rng.integers(min_gap, max_gap + 1))) < length:
        positions.append(following)
    return positions


def overrides(variant: str) -> dict:
    """``"K=V,K=V"`` as a dict of SLAM parameter overrides (each as ``gausem run --set`` reads it)."""
    return dict(parse_override(item) for item in variant.split(",") if item)


def run(spec: str, dataset, variant: str) -> dict:
    cfg = load_config(default_params_file(spec), {"device": "cpu", "loop.enabled": False, "refinement.enabled": False,
                                                  **overrides(variant)})
    result = Pipeline(dataset, cfg, progress=False).run()
    gt = [(t, pose) for t, pose in zip(result.timestamps, result.gt_poses) if pose is not None]
    metrics, _ = trajectory_metrics(Trajectory(result.timestamps, result.poses),
                                    Trajectory([t for t, _ in gt], np.array([p for _, p in gt])))
    statuses = Counter(health.status for _, _, health in result.health)
    return {"variant": variant or "defaults", "frames": len(dataset), "ate_rmse_cm": round(metrics["ate_rmse_cm"], 2),
            **{status: statuses.get(status, 0) for status in ("ok", "degraded", "lost")},
            "seconds_per_frame": round(result.seconds / len(dataset), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default="synthetic", help="dataset spec (default: synthetic)")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=None, help="source frames to draw from (default: all)")
    parser.add_argument("--min-gap", type=int, default=1, help="smallest step between processed frames")
    parser.add_argument("--max-gap", type=int, default=3, help="largest step between processed frames")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variants", nargs="+", default=[""],
                        help='SLAM parameter overrides per run, "K=V,K=V" ("": the defaults)')
    parser.add_argument("--out", type=Path, default=None, help="write the results record OUT.json")
    args = parser.parse_args()
    source = open_dataset(args.source, size=parse_size(args.size), max_frames=args.frames)
    dataset = SkippedFrames(source, live_positions(len(source), args.min_gap, args.max_gap, args.seed))
    rows = []
    for variant in args.variants:
        start = time.perf_counter()
        rows.append(run(args.source, dataset, variant))
        print(f"{rows[-1]['variant']}: {rows[-1]} ({time.perf_counter() - start:.0f} s)", flush=True)
    what = (f"Frame gaps: {results.label(args.source)} at {args.size}, {len(dataset)} of {len(source)} frames, steps "
            f"{args.min_gap}-{args.max_gap} (seed {args.seed}); loop closure and refinement off. {WHAT}")
    table = "| variant | frames | ATE cm | ok | degraded | lost | s/frame |\n|---|---|---|---|---|---|---|\n" + "".join(
        f"| {r['variant']} | {r['frames']} | {r['ate_rmse_cm']} | {r['ok']} | {r['degraded']} | {r['lost']} | "
        f"{r['seconds_per_frame']} |\n" for r in rows)
    if not args.out:
        print(table)
        return
    results.write_report(args.out, title=f"Frame gaps: {results.label(args.source)}, steps of {args.min_gap}-"
                         f"{args.max_gap} frames", what=what, markdown=table,
                         data={"source": args.source, "size": args.size, "min_gap": args.min_gap,
                               "max_gap": args.max_gap, "seed": args.seed, "positions": dataset.positions,
                               "rows": rows})


if __name__ == "__main__":
    main()
