"""How accurate is what a loop edge measures? (issue #23) The relative pose of two keyframes, against ground truth.

A loop edge pulls the pose graph towards its measured relative pose with the loop's standard deviations; when it is
further from the truth than the drift it corrects, closing the loop costs accuracy. For each sequence of the paper
suite, the keyframe pairs a loop could join are taken from the ground truth: frames on the loop grid (every
``loop.keyframe_every``-th), at least ``min_frame_gap`` apart, and for each query frame the earlier one whose view it
overlaps most (ground-truth view overlap at least ``min_overlap``). Each pair goes through the intra-submap loop's
steps as the system runs them (``slam.loop_closure``): geometric verification (ORB matches, RANSAC PnP; the pairs
it turns down are left out) and keyframe alignment (``registration.align_keyframes``, started from
the verified pose), with each variant's ``loop.registration`` settings; then the acceptance test (overlap and
fitness). Per variant: the accepted pairs and the median and 90th-percentile error of the measured relative pose
(translation cm, rotation degrees), with the verified PnP pose's for comparison. Writes
benchmarks/results/<name>.json (a results record).

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python benchmarks/loop_edges.py \\
        --variant w_depth_0.5:w_depth=0.5
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from gausem_bench import results as records  # noqa: E402
from gausem_bench.suite import gausem_parameters, load_suite, open_sequence  # noqa: E402
from gausem_core.config import from_flat  # noqa: E402
from gausem_core.eval.loops import view_overlap  # noqa: E402
from gausem_core.geometry import invert_pose, se3_log  # noqa: E402
from gausem_core.pipeline import Pipeline  # noqa: E402
from gausem_core.slam.depth_filter import filter_observation  # noqa: E402
from gausem_core.slam.features import extract_features  # noqa: E402
from gausem_core.slam.loop.verification import verify  # noqa: E402
from gausem_core.slam.registration import align_keyframes  # noqa: E402

SEQUENCES = ("tum_fr1_rpy", "7scenes_redkitchen", "synthetic_loop_noisy")


def pose_error(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """(translation cm, rotation degrees) of estimate^-1 truth."""
    error = invert_pose(estimate.double()) @ truth.double()
    return 100 * float(error[:3, 3].norm()), math.degrees(float(se3_log(error)[3:].norm()))


def loop_pairs(observations: dict, poses: dict, min_gap: int, min_overlap: float) -> list[tuple[int, int, float]]:
    """(query, match, overlap): per query frame the earlier grid frame its view overlaps most, if enough."""
    frames, pairs = sorted(observations), []
    for query in frames:
        best = max(((view_overlap(observations[m], poses[m], observations[query], poses[query]), m)
                    for m in frames if query - m >= min_gap), default=(0.0, None))
        if best[0] >= min_overlap:
            pairs.append((query, best[1], best[0]))
    return pairs


def measure(pair: tuple[int, int, float], observations: dict, poses: dict, features: dict, cfg) -> dict | None:
    """The loop steps for one pair under ``cfg`` (a LoopConfig); None when verification turns it down."""
    query, match, overlap = pair
    verified = verify(features[query], features[match], observations[query], observations[match], cfg.bow,
                      cfg.registration.max_depth_residual)
    if not verified.passed:
        return None
    truth = invert_pose(poses[query]) @ poses[match]  # query camera from match camera
    start = invert_pose(verified.relative.double())
    motion, (measured_overlap, fitness) = align_keyframes(observations[match], observations[query], start.float(),
                                                          cfg.registration)
    reg = cfg.registration
    return {"query": query, "match": match, "view_overlap": overlap, "inliers": verified.inliers,
            "pnp_error": pose_error(start, truth), "error": pose_error(motion, truth),
            "accepted": measured_overlap >= reg.min_overlap and fitness >= reg.min_fitness, "fitness": fitness}


def summary(rows: list[dict]) -> dict:
    """Accepted pairs and the error percentiles of their measured and PnP poses."""
    accepted = [r for r in rows if r["accepted"]]
    out = {"verified": len(rows), "accepted": len(accepted)}
    for key in ("error", "pnp_error"):
        for i, unit in enumerate(("cm", "deg")):
            values = [r[key][i] for r in accepted]
            for q in (50, 90):
                out[f"{key}_{unit}_p{q}"] = float(np.percentile(values, q)) if values else math.nan
    return out


def run_sequence(name: str, suite, variants: dict[str, dict], min_gap: int, min_overlap: float) -> dict:
    sequence = next(s for s in suite.sequences if s.name == name)
    configuration = next(c for c in suite.configurations if c.name == "gausem")
    _, _, flat = gausem_parameters(sequence, configuration, {})
    base = from_flat(flat)
    dataset = open_sequence(sequence)
    pipeline = Pipeline(dataset, base, progress=False)
    grid = [i for i in range(len(dataset)) if i % base.loop.keyframe_every == 0]
    observations, poses = {}, {}
    for i in tqdm(grid, desc=f"{name}: frames", leave=False):
        frame = dataset[i]
        observations[i] = filter_observation(pipeline.observation(frame), base.depth_filter)
        poses[i] = torch.as_tensor(np.asarray(frame.gt_pose), dtype=torch.float64)
    features = {i: extract_features(o.rgb, o.depth, o.camera, base.loop.bow) for i, o in observations.items()}
    pairs = loop_pairs(observations, poses, min_gap, min_overlap)
    result = {"frames": len(dataset), "pairs": len(pairs), "variants": {}}
    for variant, overrides in variants.items():
        cfg = dataclasses.replace(base.loop, registration=dataclasses.replace(base.loop.registration, **overrides))
        rows = [r for r in (measure(p, observations, poses, features, cfg)
                            for p in tqdm(pairs, desc=f"{name}: {variant}", leave=False)) if r is not None]
        result["variants"][variant] = {"overrides": overrides, "summary": summary(rows), "pairs": rows}
    return result


def parse_variant(text: str) -> tuple[str, dict]:
    """NAME:key=value,key=value (loop.registration fields) -> (NAME, {key: float})."""
    name, _, settings = text.partition(":")
    return name, {k: float(v) for k, v in (kv.split("=") for kv in settings.split(",") if kv)}


def table(results: dict) -> list[str]:
    lines = ["| sequence | variant | pairs verified / accepted | error cm median / p90 | error deg median / p90 | "
             "PnP cm median / p90 | PnP deg median / p90 |", "|---|---|---|---|---|---|---|"]
    for name, result in results.items():
        for variant, data in result["variants"].items():
            s = data["summary"]
            lines.append(f"| {name} ({result['frames']} frames, {result['pairs']} pairs) | {variant} | "
                         f"{s['verified']} / {s['accepted']} | {s['error_cm_p50']:.2f} / {s['error_cm_p90']:.2f} | "
                         f"{s['error_deg_p50']:.2f} / {s['error_deg_p90']:.2f} | "
                         f"{s['pnp_error_cm_p50']:.2f} / {s['pnp_error_cm_p90']:.2f} | "
                         f"{s['pnp_error_deg_p50']:.2f} / {s['pnp_error_deg_p90']:.2f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES), help="paper-suite sequences")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                        help="loop.registration settings to compare with the defaults (repeatable)")
    parser.add_argument("--min-frame-gap", type=int, default=30, help="frames between a pair's keyframes, at least")
    parser.add_argument("--min-overlap", type=float, default=0.5, help="ground-truth view overlap, at least")
    parser.add_argument("--name", default="loop_edges")
    args = parser.parse_args()
    torch.manual_seed(0)
    variants = dict([("defaults", {})] + [parse_variant(v) for v in args.variant])
    suite = load_suite(ROOT / "benchmarks" / "suites" / "paper.yaml")
    results = {}
    for name in args.sequences:
        try:
            results[name] = run_sequence(name, suite, variants, args.min_frame_gap, args.min_overlap)
        except FileNotFoundError as exc:
            print(f"{name}: skipped ({exc})")
    what = (f"`benchmarks/loop_edges.py`: keyframe pairs on the loop grid at least {args.min_frame_gap} frames apart "
            f"whose ground-truth view overlap is at least {args.min_overlap}, run through the intra-submap loop's steps "
            "as the system does (PnP verification, keyframe alignment from the verified pose, acceptance); errors of "
            "the accepted pairs' measured relative pose and of that PnP pose, per variant of the registration's "
            "settings (defaults: `loop.registration.w_depth` 5).")
    records.write_report(records.RESULTS / args.name, title="Loop edges: how far a loop's measurement lies from the "
                         "truth", what=what, markdown="\n".join(table(results)),
                         data={"min_frame_gap": args.min_frame_gap, "min_overlap": args.min_overlap,
                               "results": results})


if __name__ == "__main__":
    main()
