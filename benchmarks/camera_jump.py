"""A camera that jumps: the sequence with ``--cut`` consecutive frames removed from its middle (true stamps kept, as
a camera switched off and on elsewhere, or a bag with a hole), run in lock-step with loop closure (refinement off),
against the whole sequence. With each variant (``--variants``, comma-separated overrides): ATE of the frames not lost,
frames lost, tracking segments started and left separate at the end (``relocalisation.new_segment_after``), loops
accepted. Run from the repository root, e.g.
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/camera_jump.py --source synthetic:loop --cut 60 \\
        --variants "" "relocalisation.new_segment_after=0,health.lost_coverage=0" --out benchmarks/results/camera_jump
"""
from __future__ import annotations

import argparse
import time
from collections import Counter
from pathlib import Path

import numpy as np
from frame_gaps import SkippedFrames, overrides

from gausem_bench import results
from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.io.trajectory import Trajectory
from gausem_core.options import default_params_file, parse_size
from gausem_core.pipeline import Pipeline
from gausem_core.report import trajectory_metrics

WHAT = ("Each row one lock-step run (loop closure on, global refinement off) of the frames kept; ATE over the frames "
        "not lost, SE(3)-aligned; segments: tracking segments started / left separate at the end.")


def run(spec: str, dataset, variant: str) -> dict:
    cfg = load_config(default_params_file(spec), {"device": "cpu", "refinement.enabled": False, **overrides(variant)})
    result = Pipeline(dataset, cfg, progress=False).run()
    statuses = Counter(health.status for _, _, health in result.health)
    kept = [(t, pose, gt) for t, pose, gt, (_, _, health) in zip(result.timestamps, result.poses, result.gt_poses,
                                                                  result.health) if health.status != "lost"]
    metrics, _ = trajectory_metrics(Trajectory([t for t, _, _ in kept], np.array([p for _, p, _ in kept])),
                                    Trajectory([t for t, _, _ in kept], np.array([g for _, _, g in kept])))
    slam = result.slam
    return {"variant": variant or "defaults", "frames": len(dataset), "ate_rmse_cm": round(metrics["ate_rmse_cm"], 2),
            "lost": statuses.get("lost", 0), "segments": 1 + sum(s.starts_segment for s in slam.submaps),
            "separate": len(slam.segments()), "loops": len(slam.loop_closure.loops) if slam.loop_closure else 0,
            "seconds": round(result.seconds, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default="synthetic:loop", help="dataset spec (default: synthetic:loop)")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--cut", type=int, default=60, help="consecutive frames removed from the middle")
    parser.add_argument("--variants", nargs="+", default=[""],
                        help='SLAM parameter overrides per run, "K=V,K=V" ("": the defaults)')
    parser.add_argument("--out", type=Path, default=None, help="write the results record OUT.json")
    args = parser.parse_args()
    source = open_dataset(args.source, size=parse_size(args.size))
    start = (len(source) - args.cut) // 2
    jumped = SkippedFrames(source, [i for i in range(len(source)) if not start <= i < start + args.cut])
    rows = []
    for name, dataset, variants in (("whole", SkippedFrames(source, list(range(len(source)))), [""]),
                                    (f"frames {start}-{start + args.cut - 1} cut", jumped, args.variants)):
        for variant in variants:
            began = time.perf_counter()
            rows.append({"sequence": name, **run(args.source, dataset, variant)})
            print(f"{rows[-1]} ({time.perf_counter() - began:.0f} s)", flush=True)
    table = ("| sequence | variant | frames | ATE cm | lost | segments started / separate | loops |\n"
             "|---|---|---|---|---|---|---|\n" + "".join(
                 f"| {r['sequence']} | {r['variant']} | {r['frames']} | {r['ate_rmse_cm']} | {r['lost']} | "
                 f"{r['segments']} / {r['separate']} | {r['loops']} |\n" for r in rows))
    if not args.out:
        print(table)
        return
    results.write_report(args.out, title=f"A camera that jumps: {results.label(args.source)}, {args.cut} frames cut",
                         what=f"{results.label(args.source)} at {args.size}. {WHAT}", markdown=table,
                         data={"source": args.source, "size": args.size, "cut": [start, start + args.cut],
                               "rows": rows})


if __name__ == "__main__":
    main()
