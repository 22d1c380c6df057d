"""Where a run's PSNR is lost: pixels with a measured depth vs pixels without (holes, out of range).

Runs the pipeline on a dataset, then renders the final map at every 5th frame's estimated pose (the evaluation of
`gausem run`) and reports PSNR over all pixels, over pixels with valid depth and over pixels without, and the share of
the squared colour error that lies in the pixels without depth. Run from the repository root, e.g.
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/psnr_by_depth.py tum:../shared/data/tum_fr1_rpy --set mapping.iterations=120
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.eval.image import psnr
from gausem_core.pipeline import Pipeline
from gausem_core.report import evaluation_positions, rendered_views
from gausem_core.tools.run import default_params_file, parse_override, parse_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--frames", type=int)
    parser.add_argument("--set", type=parse_override, action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    cfg = load_config(default_params_file(args.dataset), dict(args.set))
    dataset = open_dataset(args.dataset, size=args.size, max_frames=args.frames)
    pipeline = Pipeline(dataset, cfg, progress=True)
    result = pipeline.run()
    scores = {"all": [], "valid_depth": [], "no_depth": []}
    error_no_depth = error_total = hole_fraction = 0.0
    positions = evaluation_positions(len(result.frame_ids), 5)
    for _, obs, out in rendered_views(result, pipeline, positions):
        valid = obs.valid_depth
        scores["all"].append(psnr(out.color, obs.rgb))
        scores["valid_depth"].append(psnr(out.color, obs.rgb, valid))
        if not valid.all():
            scores["no_depth"].append(psnr(out.color, obs.rgb, ~valid))
        squared = ((out.color - obs.rgb) ** 2).mean(-1)
        error_no_depth += float(squared[~valid].sum())
        error_total += float(squared.sum())
        hole_fraction += float((~valid).float().mean()) / len(positions)
    report = {"dataset": args.dataset, "frames": len(result.frame_ids), "overrides": dict(args.set),
              **{f"psnr_{name}": float(np.mean(values)) if values else None for name, values in scores.items()},
              "fraction_without_depth": hole_fraction, "share_of_squared_error_without_depth":
              error_no_depth / error_total if error_total else None}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
