"""How good and how cheap is the occupancy grid? Runs GauSem on the embedded synthetic walk, then builds the grid of
the final map (``gausem_core.maps``) with the floor from the floor class and from the plane fit alone, scores each
against the room's known layout (``gausem_core.eval.occupancy``) and times a rebuild from scratch and with the
keyframes' rays kept (what the tracking node pays after a loop correction). Writes
the record ``benchmarks/results/occupancy_<name>.json``.

    .venv/bin/python benchmarks/occupancy.py --frames 180 --name synthetic_default_160x120
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.eval.occupancy import layout_cells, occupancy_scores
from gausem_core.maps.slam_grid import KeyframeRays, floor_class_id, slam_grid
from gausem_core.pipeline import Pipeline
from gausem_core.report import estimated_trajectory, ground_truth_trajectory, trajectory_metrics
from gausem_core.options import parse_override

from gausem_bench import results

REPO = Path(__file__).resolve().parents[1]
REPEATS = 5
WHAT = ("`benchmarks/occupancy.py`: the occupancy grid of the final map (`gausem_core/maps`), its floor from the floor "
        "class and from the plane fit alone, scored against the synthetic room's walls and furniture rasterised into "
        "its cells (`eval/occupancy.py`: IoU, precision and recall of the occupied cells over the cells the keyframes "
        "saw; coverage: the share of the room's truly occupied cells among them); floor tilt and height against the "
        "room's; the time of a first grid and of a rebuild with the keyframes' rays kept (what the tracking node "
        "pays after a loop correction), the global cloud included.")


def timed(build) -> tuple[object, float]:
    begin = time.perf_counter()
    grid = build()
    return grid, time.perf_counter() - begin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic:default")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=180)
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
    doc = {"dataset": args.dataset, "size": args.size, "frames": len(result.frame_ids),
           "keyframes": sum(len(s.keyframes) for s in slam.submaps), "gaussians": len(slam.global_cloud()),
           "ate_rmse_cm": trajectory_metrics(estimated_trajectory(result), ground_truth_trajectory(result))[0][
               "ate_rmse_cm"], "frame_ms_median": 1e3 * statistics.median(result.frame_seconds),
           "grid": vars(grid_cfg), "table": rows}
    write_record(results.RESULTS / f"occupancy_{args.name}", doc)


def write_record(path: Path, doc: dict, **fields) -> Path:
    """The results record of ``doc`` (this script's raw output); ``fields``: :func:`results.record`'s provenance,
    when not this process's."""
    lines = ["| floor from | tilt (deg) | height error (cm) | IoU | precision | recall | coverage | free cells truly "
             "occupied | first grid (ms) | rebuild (ms) |", "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['floor']} ({r['source']}) | {r['floor_tilt_deg']:.2f} | {100 * r['floor_height_error_m']:.1f} | "
              f"{r['iou']:.3f} | {r['precision']:.3f} | {r['recall']:.3f} | {r['coverage']:.3f} | "
              f"{r['free_truly_occupied']:.3f} | {1e3 * r['seconds_first']:.0f} | "
              f"{1e3 * r['seconds_rebuild_median']:.0f} |" for r in doc["table"]]
    note = (f"{doc['frames']} frames at {doc['size']}: ATE RMSE {doc['ate_rmse_cm']:.2f} cm, {doc['keyframes']} "
            f"keyframes, {doc['gaussians']} Gaussians, median frame (tracking and mapping) {doc['frame_ms_median']:.0f}"
            " ms.")
    return results.write_report(path, title=f"Occupancy grid: {results.label(doc['dataset'])}", what=WHAT,
                                markdown="\n".join(lines), notes=[note], data=doc, **fields)


if __name__ == "__main__":
    main()
