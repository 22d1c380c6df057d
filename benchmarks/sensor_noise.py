"""GauSem on the synthetic walk, clean vs through the Kinect-like sensor model (issue #25).

Each variant is what ``gausem run --dataset synthetic:SEQ[_noisy] --size 160x120`` does (params/synthetic.yaml,
loop closure as there; ``--set`` overrides go to every variant): "clean", "noisy" (every sensor effect), "depth"
(only the depth effects), "colour" (only the colour effects), "only_<effect>" and "without_<effect>" (one sensor
effect alone, or all but one). Per variant: ATE RMSE after SE(3) alignment, the
Sim(3) scale of the estimate and the ATE after it, PSNR and depth L1 of the final map against the (noisy) input, fps.
Writes benchmarks/results/<name>.json (a results record) and the runs' outputs under out/sensor_noise/<name>/. From the root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sensor_noise.py --sequence default --variants clean noisy
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from gausem_bench import results
from gausem_core.config import SensorConfig, load_config
from gausem_core.data import SyntheticDataset
from gausem_core.data.sensor import COLOR_EFFECTS, DEPTH_EFFECTS
from gausem_core.eval.trajectory import absolute_trajectory_error, associate_trajectories
from gausem_core.io.trajectory import read_tum_trajectory
from gausem_core.pipeline import Pipeline
from gausem_core.report import write_outputs
from gausem_core.options import default_params_file, parse_override, parse_size

ROOT = Path(__file__).resolve().parents[1]
EFFECTS = DEPTH_EFFECTS + COLOR_EFFECTS
VARIANTS = {"clean": None, "noisy": SensorConfig(),
            "depth": SensorConfig(**{name: False for name in COLOR_EFFECTS}),
            "colour": SensorConfig(**{name: False for name in DEPTH_EFFECTS}),
            **{f"only_{effect}": SensorConfig(**{name: name == effect for name in EFFECTS}) for effect in EFFECTS},
            **{f"without_{effect}": SensorConfig(**{effect: False}) for effect in EFFECTS}}


def run_variant(sequence: str, sensor: SensorConfig | None, size, frames: int | None, overrides: dict,
                out: Path) -> dict:
    """One ``gausem run`` on the walk seen through ``sensor`` (None: clean); the row of the results table."""
    params = default_params_file("synthetic")
    cfg = load_config(params, overrides)
    dataset = SyntheticDataset(sequence, sensor=sensor, size=size, max_frames=frames)
    result = Pipeline(dataset, cfg, progress=False).run()
    metrics = write_outputs(result, dataset, cfg, out, params_file=params)
    estimate, reference = associate_trajectories(read_tum_trajectory(out / "trajectory.txt"),
                                                 read_tum_trajectory(out / "trajectory_gt.txt"))
    similarity = absolute_trajectory_error(estimate, reference, with_scale=True)
    rendering = metrics["rendering"]
    return {"dataset": dataset.name, "ate_rmse_cm": metrics["ate_rmse_cm"], "sim3_scale": similarity.scale,
            "ate_sim3_cm": 100 * similarity.rmse, "psnr": rendering["psnr"],
            "depth_l1_cm": 100 * rendering["depth_l1_m"], "fps": len(result.frame_ids) / result.seconds,
            "loops": metrics.get("loops", {}).get("accepted"), "out": str(out.relative_to(ROOT))}


def table(rows: dict) -> str:
    lines = ["| Variant | ATE RMSE [cm] | Sim(3) scale | ATE after scale [cm] | PSNR [dB] | Depth L1 [cm] | fps |",
             "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['ate_rmse_cm']:.2f} | {r['sim3_scale']:.4f} | {r['ate_sim3_cm']:.2f} | "
                     f"{r['psnr']:.2f} | {r['depth_l1_cm']:.2f} | {r['fps']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", default="default", choices=["default", "loop"])
    parser.add_argument("--variants", nargs="+", default=["clean", "noisy"], choices=list(VARIANTS), metavar="VARIANT",
                        help="clean, noisy, depth, colour, only_<effect> or without_<effect>; effects: "
                             + ", ".join(EFFECTS))
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--frames", type=int, help="only the first this many frames (default: the whole walk)")
    parser.add_argument("--set", dest="overrides", type=parse_override, action="append", default=[],
                        metavar="NAME=VALUE", help="a SLAM parameter for every variant")
    parser.add_argument("--name", help="results file name (default: sensor_noise_<sequence>)")
    args = parser.parse_args()
    name = args.name or f"sensor_noise_{args.sequence}"
    overrides = dict(args.overrides)
    rows = {}
    for variant in args.variants:
        rows[variant] = run_variant(args.sequence, VARIANTS[variant], args.size, args.frames, overrides,
                                    ROOT / "out" / "sensor_noise" / name / variant)
        print(variant, json.dumps(rows[variant]), flush=True)
    document = {"sequence": args.sequence, "size": list(args.size), "frames": args.frames, "overrides": overrides,
                "rows": rows}
    what = (f"`benchmarks/sensor_noise.py`: `gausem run`'s pipeline on the synthetic {args.sequence} sequence at "
            f"{args.size[0]}x{args.size[1]}" + (f", first {args.frames} frames" if args.frames else "")
            + "".join(f", `{k}={v}`" for k, v in overrides.items()) + " (params/synthetic.yaml, loop closure on), per "
            "variant of the Kinect-like sensor model: " + ", ".join(args.variants) + ". Sim(3) scale > 1: the "
            "estimate is too small.")
    results.write_report(results.RESULTS / name, title=f"Sensor noise: {name.removeprefix('sensor_noise_')}",
                         what=what, markdown=table(rows), data=document)


if __name__ == "__main__":
    main()
