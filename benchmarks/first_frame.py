"""How soon can a new map track? From the first frame's arrival until the second frame can be tracked: in ``sync`` the
first ``process`` call (the whole initialisation), in ``async`` the same call, which places the first submap's
Gaussians from the frame's depth and leaves their optimisation to the worker. Also the first 10 frames' ATE against
the truth, so that the faster start is seen not to cost accuracy. Median of ``--repeats`` runs per mode, each in
this process after a warm-up. Writes ``benchmarks/results/first_frame_<name>.json`` (a results record).

    .venv/bin/python benchmarks/first_frame.py --dataset synthetic:loop --name synthetic_loop_160x120
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.slam.system import GauSemSLAM
from gausem_core.options import default_params_file, parse_size

from gausem_bench import results

WHAT = ("`benchmarks/first_frame.py`: how long until the second frame can be tracked, synthetic loop, first 10 "
        "frames, loop closure and refinement off.")


def first_frame(pipeline: Pipeline, cfg, frames: int) -> tuple[float, float]:
    """(seconds until the second frame can be tracked, the first ``frames`` frames' worst position error in cm)."""
    slam = GauSemSLAM(cfg, pipeline.device, num_classes=len(pipeline.palette))
    observations = [pipeline.observation(pipeline.dataset[i]) for i in range(frames)]
    start = time.perf_counter()
    slam.process(observations[0])
    ready = time.perf_counter() - start
    for obs in observations[1:]:
        slam.process(obs)
    slam.drain()
    truth = [np.asarray(pipeline.dataset[i].gt_pose) for i in range(frames)]
    estimate = [p.detach().cpu().double().numpy() for _, p in slam.trajectory()]
    worst = max(float(np.linalg.norm((np.linalg.inv(truth[0]) @ t)[:3, 3] - e[:3, 3])) for t, e in zip(truth, estimate))
    slam.close()
    return ready, 100 * worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic:loop")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--name", default="synthetic_loop_160x120")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=10)
    args = parser.parse_args()
    dataset = open_dataset(args.dataset, size=args.size, max_frames=args.frames)
    rows = []
    for mode in ("sync", "async"):
        cfg = load_config(default_params_file(args.dataset), {"worker.mode": mode, "loop.enabled": False,
                                                               "refinement.enabled": False})
        pipeline = Pipeline(dataset, cfg, progress=False)
        first_frame(pipeline, cfg, 2)  # warm-up (imports, compiled kernels)
        runs = [first_frame(pipeline, cfg, args.frames) for _ in range(args.repeats)]
        rows.append({"mode": mode, "seconds_median": statistics.median(r[0] for r in runs),
                     "seconds": [r[0] for r in runs], "worst_error_cm": statistics.median(r[1] for r in runs),
                     "init_iterations": cfg.mapping.init_iterations, "publish_every": cfg.worker.publish_every})
        torch.set_num_threads(os.cpu_count() or 1)  # async set the tracker's share; the next mode starts afresh
    doc = {"dataset": args.dataset, "size": f"{args.size[0]}x{args.size[1]}", "rows": rows}
    lines = [f"| mode | until the second frame can be tracked (s, median of {args.repeats}) | worst error of the first "
             f"{args.frames} frames (cm) |", "|---|---|---|"]
    lines += [f"| {r['mode']} | {r['seconds_median']:.2f} | {r['worst_error_cm']:.2f} |" for r in rows]
    results.write_report(results.RESULTS / f"first_frame_{args.name}", title="The map's first frame", what=WHAT,
                         markdown="\n".join(lines), data=doc)


if __name__ == "__main__":
    main()
