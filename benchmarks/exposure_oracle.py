"""How much of the rendering error on a real sequence is exposure? An upper bound for exposure compensation.

Runs the offline pipeline, then renders the final map at every ``--eval-every``-th estimated pose (the PSNR of
``gausem run``) and once more after an ORACLE colour correction: per frame and channel, the gain and bias that best
map the render onto that frame's image (least squares against the frame itself, so no real system can do better
with an affine exposure model). Writes benchmarks/results/exposure_oracle_<name>.{json,md}. From the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/exposure_oracle.py --dataset tum:../shared/data/tum_fr1_rpy
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.eval.image import psnr
from gausem_core.io.metrics import git_commit
from gausem_core.pipeline import Pipeline
from gausem_core.report import evaluation_positions, rendered_views
from gausem_core.tools.run import default_params_file, parse_size

OUT = Path(__file__).resolve().parent / "results"


def oracle_affine(rendered: torch.Tensor, image: torch.Tensor) -> tuple[torch.Tensor, list[list[float]]]:
    """The render (H, W, 3) after the per-channel gain and bias that best fit ``image``, and those (gain, bias)."""
    corrected, coefficients = torch.empty_like(rendered), []
    for channel in range(3):
        x = rendered[..., channel].reshape(-1)
        design = torch.stack([x, torch.ones_like(x)], 1)
        gain, bias = torch.linalg.lstsq(design, image[..., channel].reshape(-1, 1)).solution[:, 0].tolist()
        corrected[..., channel] = (gain * rendered[..., channel] + bias).clamp(0, 1)
        coefficients.append([gain, bias])
    return corrected, coefficients


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="tum:../shared/data/tum_fr1_rpy")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--eval-every", type=int, default=5)
    parser.add_argument("--name", default="tum_fr1_rpy")
    args = parser.parse_args()
    cfg = load_config(default_params_file(args.dataset), {})
    dataset = open_dataset(args.dataset, size=args.size)
    pipeline = Pipeline(dataset, cfg, progress=True)
    result = pipeline.run()
    frames = []
    for frame, obs, out in rendered_views(result, pipeline, evaluation_positions(len(result.frame_ids),
                                                                                 args.eval_every)):
        corrected, coefficients = oracle_affine(out.color, obs.rgb)
        frames.append({"frame": frame.index, "psnr": psnr(out.color, obs.rgb),
                       "psnr_oracle_exposure": psnr(corrected, obs.rgb), "gain_bias_rgb": coefficients})
    document = {"commit": git_commit(), "dataset": args.dataset, "size": list(args.size),
                "psnr": statistics.mean(f["psnr"] for f in frames),
                "psnr_oracle_exposure": statistics.mean(f["psnr_oracle_exposure"] for f in frames),
                "frames": frames}
    OUT.mkdir(exist_ok=True)
    (OUT / f"exposure_oracle_{args.name}.json").write_text(json.dumps(document, indent=2) + "\n")
    gains = [c[0] for f in frames for c in f["gain_bias_rgb"]]
    commit = (document["commit"] or "unknown")[:10]
    summary = (f"# Exposure oracle: {args.dataset} at {args.size[0]}x{args.size[1]} (commit {commit})"
               f"\n\nMean PSNR over {len(frames)} frames: {document['psnr']:.2f} dB as rendered, "
               f"{document['psnr_oracle_exposure']:.2f} dB after the per-frame oracle gain and bias "
               f"(gains {min(gains):.3f}-{max(gains):.3f}).\n")
    (OUT / f"exposure_oracle_{args.name}.md").write_text(summary)
    print(summary)


if __name__ == "__main__":
    main()
