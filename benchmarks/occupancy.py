"""How good and how cheap is the occupancy grid? Runs GauSem on the embedded synthetic walk, then builds the grid of
the final map (``gausem_core.maps``) with the floor from the floor class and from the plane fit alone, scores each
against the room's known layout (``gausem_core.eval.occupancy``) and times a rebuild from scratch and with the
keyframes' rays kept (what the tracking node pays after a loop correction). Writes
``benchmarks/results/occupancy_<name>.{json,md}``.

    .venv/bin/python benchmarks/occupancy.py --frames 60 --set mapping.init_iterations=60 --set mapping.iterations=5
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.eval.occupancy import layout_cells, occupancy_scores
from gausem_core.io.metrics import git_commit
from gausem_core.maps.slam_grid import KeyframeRays, floor_class_id, slam_grid
from gausem_core.pipeline import Pipeline
from gausem_core.report import estimated_trajectory, ground_truth_trajectory, trajectory_metrics
from gausem_core.tools.run import parse_override

REPO = Path(__file__).resolve().parents[1]
REPEATS = 5


def timed(build) -> tuple[object, float]:
    begin = time.perf_counter()
    grid = build()
    return grid, time.perf_counter() - begin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic:default")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--set", dest="overrides", type=parse_override, action="append", default=[],
                        metavar="NAME=VALUE")
    parser.add_argument("--name", default="synthetic_default_160x120")
    args = parser.parse_args()
    dataset = open_dataset(args.dataset, size=tuple(int(v) for v in args.size.split("x")), max_frames=args.frames)
    cfg = load_config(REPO / "params" / "synthetic.yaml", {"device": "cpu", **dict(args.overrides)})
    pipeline = Pipeline(dataset, cfg, progress=False)
    result = pipeline.run()
    slam, grid_cfg = result.slam, cfg.grid
    floor_class = floor_class_id(pipeline.semantics.class_table.names, grid_cfg.floor_class)
    rows = []
    for label, palette, floor in (("floor class", pipeline.palette, floor_class), ("plane fit", None, None)):
        rays = KeyframeRays(grid_cfg.pixel_stride)
        grid, cold = timed(lambda: slam_grid(slam, grid_cfg, palette, floor, rays))
        warm = statistics.median(timed(lambda: slam_grid(slam, grid_cfg, palette, floor, rays))[1]
                                 for _ in range(REPEATS))
        truth, in_room = layout_cells(grid, dataset.scene, result.gt_poses[0], grid_cfg.min_height,
                                      grid_cfg.max_height)
        up = result.gt_poses[0][2, :3]  # the room's up in the map frame
        rows.append({"floor": label, "source": grid.floor.source,
                     "floor_tilt_deg": float(np.degrees(np.arccos(np.clip(grid.floor.normal @ up, -1, 1)))),
                     "floor_height_error_m": float(grid.floor.offset - result.gt_poses[0][2, 3]),
                     **occupancy_scores(grid, truth, in_room), "cells": grid.counts(),
                     "seconds_first": cold, "seconds_rebuild_median": warm})
        print(rows[-1], flush=True)
    doc = {"command": ".venv/bin/python benchmarks/occupancy.py " + " ".join(sys.argv[1:]),
           "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, no GPU)", "commit": git_commit(),
           "dataset": args.dataset, "size": args.size, "frames": len(result.frame_ids),
           "keyframes": sum(len(s.keyframes) for s in slam.submaps), "gaussians": len(slam.global_cloud()),
           "ate_rmse_cm": trajectory_metrics(estimated_trajectory(result), ground_truth_trajectory(result))[0][
               "ate_rmse_cm"], "frame_ms_median": 1e3 * statistics.median(result.frame_seconds),
           "grid": vars(grid_cfg), "table": rows}
    lines = [f"# Occupancy grid: {args.dataset} at {args.size}, {doc['frames']} frames", "",
             f"`{doc['command']}` at commit {doc['commit']} on {doc['machine']}.", "",
             f"ATE RMSE {doc['ate_rmse_cm']:.2f} cm; {doc['keyframes']} keyframes, {doc['gaussians']} Gaussians; median "
             f"frame (tracking and mapping): {doc['frame_ms_median']:.0f} ms. Scores over the cells the keyframes saw "
             "(eval/occupancy.py).", "",
             "| floor from | tilt (deg) | height error (cm) | IoU | precision | recall | coverage | free cells truly "
             "occupied | first grid (ms) | rebuild (ms) |", "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['floor']} ({r['source']}) | {r['floor_tilt_deg']:.2f} | {100 * r['floor_height_error_m']:.1f} | "
              f"{r['iou']:.3f} | {r['precision']:.3f} | {r['recall']:.3f} | {r['coverage']:.3f} | "
              f"{r['free_truly_occupied']:.3f} | {1e3 * r['seconds_first']:.0f} | "
              f"{1e3 * r['seconds_rebuild_median']:.0f} |" for r in rows]
    results = REPO / "benchmarks" / "results"
    (results / f"occupancy_{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    (results / f"occupancy_{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
