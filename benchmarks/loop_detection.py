"""Loop DETECTION under the paper's protocol (§IV-C-2: 10-frame intervals, ``DEFAULT_PROTOCOL``), apart from what
verification accepts: which place descriptor finds the revisits. A keyframe every ``--keyframe-every`` frames of the
sequence; each is scored against every earlier keyframe but the ``--exclude-recent`` newest (Algorithm 1's
search, at every keyframe), and every pair closer than a threshold is a detection. Per descriptor: precision, recall
and F1 at the threshold that the OTHER sequences' best F1 chose (held out) and at this sequence's own best, and the
time a keyframe. No SLAM run: the images alone decide (landmarks need a map; see the loop-closure records).

Descriptors: ``bow`` (the tf-idf score of the bag of ORB words the system builds online, distance 1 - score),
``efficientnet`` (EfficientNet-Lite0's head features of the RGB image, GeM-pooled, L2-normalised; distance = L2),
``layout`` (the colour-layout descriptor of the RGB image, the weightless fallback).
Writes ``benchmarks/results/loop_detection.json``.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/loop_detection.py
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tqdm import tqdm

from gausem_core.config import BowConfig
from gausem_core.data import open_dataset
from gausem_core.eval.loops import DEFAULT_PROTOCOL, loop_scores
from gausem_core.semantics.descriptors import ColourLayoutDescriptor
from gausem_core.semantics.place import LearnedPlaceDescriptor
from gausem_core.slam.features import extract_features
from gausem_core.slam.loop.words import BagOfWords

from gausem_bench import results
from gausem_bench.data import expand

SEQUENCES = {"tum_fr1_rpy": ("tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy", 200),
             "7scenes_redkitchen": ("tum:$GAUSEM_SHARED_DATA/7scenes_redkitchen", 200),
             "synthetic_loop": ("synthetic:loop", 360)}
WHAT = ("`benchmarks/loop_detection.py`: loop detection under the paper's protocol (10-frame intervals, "
        "1 m, 30 frames apart), every keyframe scored against all earlier ones, per place descriptor; the threshold "
        "held out (chosen on the other sequences).")


def keyframe_distances(frames, descriptor: str) -> tuple[np.ndarray, float]:
    """(K, K) distances between the keyframes (row: query, NaN where not compared) and seconds a keyframe."""
    count = len(frames)
    distances = np.full((count, count), np.nan)
    start = time.perf_counter()
    if descriptor == "bow":
        cfg = BowConfig()
        words = BagOfWords(cfg)
        for q, frame in enumerate(frames):
            rgb = torch.as_tensor(frame.rgb).float() / 255
            features = extract_features(rgb, torch.as_tensor(frame.depth), frame.camera, cfg)
            ids, scores = words.scores(features)
            distances[q, :] = 1.0
            distances[q, ids] = 1.0 - scores
            words.add(q, features)
            distances[q, q:] = np.nan
    else:
        model = LearnedPlaceDescriptor() if descriptor == "efficientnet" else ColourLayoutDescriptor()
        vectors = np.stack([model.describe(frame.rgb) for frame in frames])
        distances = np.linalg.norm(vectors[:, None] - vectors[None], axis=-1)
        distances[np.triu_indices(count)] = np.nan
    return distances, (time.perf_counter() - start) / count


def detections(distances: np.ndarray, threshold: float, exclude_recent: int) -> list[tuple[int, int]]:
    """Keyframe pairs (query, match) closer than ``threshold``, the match not among the query's newest predecessors."""
    query, match = np.nonzero(distances < threshold)
    keep = match < query - exclude_recent
    return list(zip(query[keep].tolist(), match[keep].tolist()))


def scores_at(case: dict, threshold: float, exclude_recent: int):
    pairs = [(case["frames"][q], case["frames"][m]) for q, m in detections(case["distances"], threshold,
                                                                            exclude_recent)]
    return loop_scores(pairs, case["positions"], timestamps=case["stamps"], **{
        k: v for k, v in DEFAULT_PROTOCOL.items() if k != "frame_rate"}, frame_rate=DEFAULT_PROTOCOL["frame_rate"])


def best_threshold(cases: list[dict], exclude_recent: int) -> float:
    """The threshold of the best mean F1 over ``cases``."""
    values = np.unique(np.concatenate([c["distances"][np.isfinite(c["distances"])] for c in cases]))
    candidates = np.quantile(values, np.linspace(0.0, 1.0, 101)) + 1e-9
    f1 = [np.nanmean([scores_at(c, t, exclude_recent).f1 for c in cases]) for t in candidates]
    return float(candidates[int(np.nanargmax(f1))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--keyframe-every", type=int, default=5)
    parser.add_argument("--exclude-recent", type=int, default=6)
    parser.add_argument("--descriptors", default="bow,efficientnet,layout")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    cases = {}
    for name, (spec, frames) in SEQUENCES.items():
        data = open_dataset(expand(spec), size=size, max_frames=frames)
        keyframes = [data[i] for i in tqdm(range(0, len(data), args.keyframe_every), desc=name, unit="keyframe")]
        first = np.linalg.inv(np.asarray(keyframes[0].gt_pose))
        all_frames = [data[i] for i in range(len(data))]  # the protocol's intervals need every frame's position
        cases[name] = {"keyframes": keyframes, "frames": [i for i in range(0, len(data), args.keyframe_every)],
                       "positions": np.stack([(first @ np.asarray(f.gt_pose))[:3, 3] for f in all_frames]),
                       "stamps": np.array([f.timestamp for f in all_frames])}
    rows, data = [], {}
    for descriptor in args.descriptors.split(","):
        for case in cases.values():
            case["distances"], case["seconds"] = keyframe_distances(case["keyframes"], descriptor)
        for name, case in cases.items():
            held_out = best_threshold([c for n, c in cases.items() if n != name], args.exclude_recent)
            own = best_threshold([case], args.exclude_recent)
            at_held, at_own = scores_at(case, held_out, args.exclude_recent), scores_at(case, own, args.exclude_recent)
            rows.append([name, descriptor, f"{held_out:.3f}", f"{at_held.precision:.2f}", f"{at_held.recall:.2f}",
                         f"{at_held.f1:.2f}", f"{own:.3f}", f"{at_own.f1:.2f}", at_held.ground_truth_loops,
                         f"{1e3 * case['seconds']:.0f}"])
            data[f"{name}/{descriptor}"] = {"held_out": at_held.as_dict(), "own": at_own.as_dict(),
                                            "threshold_held_out": held_out, "threshold_own": own}
    columns = ["sequence", "descriptor", "threshold (held out)", "P", "R", "F1", "own best threshold", "own best F1",
               "ground-truth loops", "ms a keyframe"]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    results.write_report(results.RESULTS / "loop_detection", title="Loop detection by place descriptor", what=WHAT,
                         markdown="\n".join(lines), data={"size": args.size, "keyframe_every": args.keyframe_every,
                                                          "exclude_recent": args.exclude_recent, "scores": data})
    print("\n".join(lines))


if __name__ == "__main__":
    main()
