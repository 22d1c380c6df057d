"""How well the tracking status (ok / degraded / lost) predicts per-frame pose error.

Runs the pipeline on (a) the synthetic sequence with a planted failure (frame ``--source``'s images at frame
``--slot``), (b) the synthetic sequence through the Kinect-like sensor model (``--noisy``, no planted failure) and
(c) the real TUM frames (skipped with a message when the folder is absent), computes each frame's relative pose error
against ground truth (frame i-1 to i, translation and rotation) and reports, for each, the share of the 1 % and 5 %
worst frames flagged degraded or lost and the false-flag rate (flagged frames outside the 5 % worst). The errors are
those of the poses as tracked, which the status judges (and a live subscriber gets), and, for comparison, of the final
poses, which loop closure and the global refinement moved later (by submap, so their errors jump where submaps
meet). Frames dropped by a failed relocalisation have no pose and are counted as flags, not ranked. Run from the
repository root, e.g.
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/health.py --frames 120 --out benchmarks/results/health_160x120
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from gausem_bench import results as records
from gausem_bench.data import SHARED_DATA
from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.eval.health import PlantedFailure, flag_scores, relative_errors
from gausem_core.pipeline import Pipeline
from gausem_core.options import default_params_file, parse_size


def evaluate(name: str, spec: str, dataset) -> dict:
    """Run the pipeline on ``dataset`` and score its statuses against the per-frame relative pose errors."""
    cfg = load_config(default_params_file(spec), {"device": "cpu"})
    start = time.perf_counter()
    result = Pipeline(dataset, cfg, progress=False).run()
    seconds = time.perf_counter() - start
    status = {frame: health.status for frame, _, health in result.health}
    reasons = Counter(r for _, _, health in result.health for r in health.reasons)
    flagged = np.array([status[f] != "ok" for f in result.frame_ids])
    truths = np.stack(result.gt_poses)
    errors = {poses: relative_errors(estimate, truths)
              for poses, estimate in (("tracked", result.tracked_poses), ("final", result.poses))}
    # a frame whose loop closure corrected the map was recorded at the corrected pose: its step from the frame before
    # is the correction, not tracking, so it is left out of the tracked poses' ranking
    after_first = np.arange(len(result.frame_ids)) > 0
    kept = {"tracked": after_first & ~np.isin(result.frame_ids, result.corrected_frames), "final": after_first}
    ranked = {f"{poses}, {by}": flag_scores(error[kept[poses]], flagged[kept[poses]])
              for poses, (translation, rotation) in errors.items()
              for by, error in (("translation", translation), ("rotation", rotation))}
    translation, rotation = errors["tracked"]
    worst = int(np.argmax(np.where(kept["tracked"], translation, -1.0)))
    return {"name": name, "frames": len(result.health), "seconds": round(seconds, 1),
            "corrected_frames": result.corrected_frames,
            "statuses": dict(Counter(status.values())), "reasons": dict(reasons), "scores": ranked,
            "rpe_median": [float(np.median(translation[kept["tracked"]]) * 100),
                           float(np.median(rotation[kept["tracked"]]))],
            "worst_frame": [result.frame_ids[worst], float(translation[worst] * 100), float(rotation[worst]),
                            status[result.frame_ids[worst]]],
            "per_frame": [[f, status[f], float(t * 100), float(r)]
                          for f, t, r in zip(result.frame_ids, translation, rotation)]}


WHAT = ("`benchmarks/health.py`: the per-frame status (ok / degraded / lost) against each frame's relative pose error "
        "(frame i-1 to i against ground truth), for a planted failure, the noisy walk and TUM fr1/rpy. Error of the "
        "poses as tracked (what the status judged; frames at which loop closure corrected the map left out, as their "
        "step is the correction) or of the final ones (moved later by loop closure and the global refinement); "
        "flagged: degraded or lost; false-flag rate: flagged frames among those outside the 5 % worst. Median and "
        "worst RPE in the notes: poses as tracked.")


def markdown(results: list[dict]) -> str:
    lines = ["| Sequence | Frames | ok / degraded / lost | Poses, error ranked by | Worst 1 % flagged | Worst 5 % flagged "
              "| False-flag rate |", "|---|---|---|---|---|---|---|"]
    for r in results:
        counts = " / ".join(str(r["statuses"].get(s, 0)) for s in ("ok", "degraded", "lost"))
        for by, s in r["scores"].items():
            lines.append(f"| {r['name']} | {r['frames']} | {counts} | {by} | {s['worst_1%_flagged']:.0%} | "
                         f"{s['worst_5%_flagged']:.0%} | {s['false_flag_rate']:.1%} |")
    return "\n".join(lines) + "\n"


def notes(results: list[dict], skipped: list[str]) -> list[str]:
    lines = [f"Skipped: {s}" for s in skipped]
    for r in results:
        frame, t, rot, status = r["worst_frame"]
        lines.append(f"{r['name']}: median RPE {r['rpe_median'][0]:.2f} cm / {r['rpe_median'][1]:.2f} deg; worst "
                     f"frame {frame} ({t:.2f} cm, {rot:.2f} deg) was {status}; rules fired: {r['reasons'] or 'none'};"
                     f" loop corrections at frames {r['corrected_frames'] or 'none'}; {r['seconds']} s.")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120, help="frames per sequence")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--slot", type=int, default=20, help="synthetic: the frame whose images are swapped out")
    parser.add_argument("--source", type=int, default=40, help="synthetic: the frame whose images are swapped in")
    parser.add_argument("--noisy", default="synthetic:default_noisy", help="a noisy synthetic sequence (dataset spec)")
    parser.add_argument("--tum", default=str(SHARED_DATA / "tum_fr1_rpy"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/health_160x120"),
                        help="the results record (OUT.json)")
    args = parser.parse_args()
    results, skipped = [], []
    synthetic = open_dataset("synthetic", size=args.size, max_frames=args.frames)
    results.append(evaluate(f"{synthetic.name}, frame {args.source} at {args.slot}", "synthetic",
                            PlantedFailure(synthetic, args.slot, args.source)))
    noisy = open_dataset(args.noisy, size=args.size, max_frames=args.frames)
    results.append(evaluate(noisy.name, args.noisy, noisy))
    if Path(args.tum).is_dir():
        spec = f"tum:{args.tum}"
        results.append(evaluate(Path(args.tum).name, spec, open_dataset(spec, size=args.size,
                                                                        max_frames=args.frames)))
    else:
        skipped.append(f"{args.tum} (not found)")
        print(f"skipping the TUM sequence: {args.tum} not found", file=sys.stderr)
    records.write_report(args.out, title="Tracking health: does the status predict per-frame error?", what=WHAT,
                         markdown=markdown(results), notes=notes(results, skipped), data=results)


if __name__ == "__main__":
    main()
