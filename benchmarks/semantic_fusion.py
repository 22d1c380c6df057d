"""Labels from the ade20k segmenter, per frame and fused in the map. One sequence, two ``sync`` runs: with
``semantics.segmenter: ade20k`` and without it (the data's own labels, or none). For the segmented run, at every
``--eval-every``-th processed frame: the per-frame predictions and the map's rendered classes (the final map at the
frame's estimated pose), scored by

- cross-view consistency: frame t's labels carried into frame t + ``--gap`` by measured depth and estimated pose,
  the share that agrees with frame t + gap's labels (``gausem_core.eval.label_consistency``);
- on data with semantic ground truth whose class names NYU40 shares (the synthetic sequences), the mIoU of both
  against it, the segmenter's NYU40 classes renamed to the data's (other classes count as wrong).

Both runs: ATE, PSNR of the final map, submaps, the classes holding at least 1 % of the map's Gaussians, loop
detection (every candidate pair of the checks) and the accepted closures under the paper's protocol (with labels the
landmarks re-rank the candidates; without, they cannot); the segmenter's time a frame. Writes
``benchmarks/results/semantic_fusion_<name>.json`` (a results record).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/semantic_fusion.py --dataset tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy \
        --frames 200 --name tum_fr1_rpy_160x120
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tqdm import tqdm

from gausem_core.config import load_config
from gausem_core.data import NYU40_CLASSES, open_dataset
from gausem_core.eval.label_consistency import label_agreement
from gausem_core.eval.semantic import confusion_matrix, mean_iou, pixel_accuracy
from gausem_core.pipeline import Pipeline, percentile
from gausem_core.report import (estimated_trajectory, evaluate_rendering, evaluation_positions,
                                ground_truth_trajectory, loop_metrics, nearest_palette_class, rendered_views,
                                trajectory_metrics)
from gausem_core.semantics.source import IMAGE_SEGMENTERS
from gausem_core.options import default_params_file, parse_override, parse_size

from gausem_bench import results
from gausem_bench.data import expand

WHAT = ("`benchmarks/semantic_fusion.py`: the ade20k segmenter's labels per frame against the map's rendered "
        "classes (cross-view consistency; mIoU where the data has ground truth), and what segmenting does to the "
        "run (ATE, PSNR, submaps, classes in the map, loop detection and closures under the paper's protocol), "
        "`sync`, loop closure on, refinement off.")


class RecordedSemantics:
    """Wraps a pipeline's :class:`FrameSemantics`: each frame's labels computed once (the evaluation renders ask
    again) and the seconds each computation took."""

    def __init__(self, semantics):
        self.inner, self.labels_of, self.seconds = semantics, {}, []

    def labels(self, frame) -> np.ndarray:
        if frame.index not in self.labels_of:
            start = time.perf_counter()
            self.labels_of[frame.index] = self.inner.labels(frame)
            self.seconds.append(time.perf_counter() - start)
        return self.labels_of[frame.index]

    def __getattr__(self, name):
        return getattr(self.inner, name)


def run(dataset, cfg, eval_every: int, label: str):
    """A run of ``dataset`` under ``cfg``: (result, pipeline, summary row)."""
    pipeline = Pipeline(dataset, cfg, progress=True)
    pipeline.semantics = recorded = RecordedSemantics(pipeline.semantics)
    result = pipeline.run()
    reference = ground_truth_trajectory(result)
    ate = trajectory_metrics(estimated_trajectory(result), reference)[0]["ate_rmse_cm"] if reference else None
    rendering = evaluate_rendering(result, pipeline, eval_every).metrics()
    ids = result.slam.global_cloud().class_ids(pipeline.palette).cpu().numpy()
    shares = np.bincount(ids, minlength=len(pipeline.palette)) / max(1, len(ids))
    table = pipeline.semantics.class_table
    classes = [(table.names[i] if table else "unlabelled", round(float(shares[i]), 3))
               for i in np.argsort(-shares) if shares[i] >= 0.01]
    row = {"run": label, "source": pipeline.semantics.kind, "frames": len(result.frame_ids), "ate_cm": ate,
           "psnr": rendering["psnr"], "submaps": len(result.slam.submaps), "classes_in_map": classes,
           "segmenter_ms_median": 1e3 * percentile(recorded.seconds, 0.5) if label in IMAGE_SEGMENTERS else None,
           "seconds": result.seconds, "loops": loop_metrics(result) if result.slam.loop_closure else None}
    return result, pipeline, row


def renamed(truth_table, predicted_table) -> np.ndarray | None:
    """Lookup: predicted class id -> the truth table's id of the same name (``len(truth_table)``: none); None when
    the tables share no name."""
    lut = np.array([truth_table.names.index(n) if n in truth_table.names else len(truth_table)
                    for n in predicted_table.names])
    return lut if (lut < len(truth_table)).any() else None


def fusion_scores(result, pipeline, eval_every: int, gap: int) -> dict:
    """Per-frame predictions against the map's rendered classes: consistency over processed-frame pairs ``gap``
    apart (a multiple of ``eval_every``), and
    mIoU against the data's labels where their class names allow."""
    positions = evaluation_positions(len(result.frame_ids), eval_every)
    views = {}
    for k, (frame, obs, out) in zip(positions, tqdm(rendered_views(result, pipeline, positions), total=len(positions),
                                                    desc="map renders", unit="view")):
        views[k] = (frame, obs, nearest_palette_class(out.semantic, pipeline.palette).cpu())
    agree, compared = {"per_frame": 0, "map": 0}, 0
    for k in positions:
        later = k + gap
        if later not in views:
            continue
        (_, a, map_a), (_, b, map_b) = views[k], views[later]
        pose_a, pose_b = (torch.as_tensor(result.poses[i]) for i in (k, later))
        for name, (labels_a, labels_b) in {"per_frame": (a.labels, b.labels), "map": (map_a, map_b)}.items():
            hits, n = label_agreement(labels_a, a.depth, pose_a, labels_b, b.depth, pose_b, a.camera)
            agree[name] += hits
        compared += n
    scores = {f"consistency_{name}": hits / compared if compared else None for name, hits in agree.items()}
    scores["compared_pixels"] = compared
    truth_table = getattr(pipeline.dataset, "class_table", None)
    lut = renamed(truth_table, pipeline.semantics.class_table) if truth_table is not None else None
    if lut is not None:
        size = len(truth_table) + 1
        confusion = {"per_frame": np.zeros((size, size), np.int64), "map": np.zeros((size, size), np.int64)}
        for frame, obs, map_labels in views.values():
            truth = torch.as_tensor(frame.labels)
            for name, labels in {"per_frame": obs.labels, "map": map_labels}.items():
                confusion[name] += confusion_matrix(lut[labels.cpu().numpy()], truth, size)
        scores.update({f"miou_{name}": mean_iou(c) for name, c in confusion.items()})
        scores.update({f"pixel_accuracy_{name}": pixel_accuracy(c) for name, c in confusion.items()})
    return scores


def _loops(loops: dict | None) -> str:
    """The loop columns: detection P / R / F1 (candidate pairs) and the accepted closures' P / R (count)."""
    if not loops:
        return "- | -"
    detection = loops.get("detection", {})
    scores = lambda d, keys: " / ".join(f"{d[k]:.2f}" if k in d else "-" for k in keys)  # noqa: E731
    return (f"{scores(detection, ('precision', 'recall', 'f1'))} ({detection.get('pairs', 0)}) | "
            f"{scores(loops, ('precision', 'recall'))} ({loops['accepted']})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic")
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--name", default="synthetic_160x120")
    parser.add_argument("--eval-every", type=int, default=5)
    parser.add_argument("--gap", type=int, default=2, help="consistency pairs: this many evaluated frames apart")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="passed to both runs")
    parser.add_argument("--runs", default="labels,ade20k", help="which runs: labels (the data's, or none), ade20k")
    args = parser.parse_args()
    dataset = open_dataset(expand(args.dataset), size=args.size, max_frames=args.frames)
    base = {"worker.mode": "sync", "refinement.enabled": False, **dict(parse_override(s) for s in args.set)}
    rows, scores = [], None
    for segmenter in args.runs.split(","):
        cfg = load_config(default_params_file(args.dataset), {**base, "semantics.segmenter": segmenter})
        result, pipeline, row = run(dataset, cfg, args.eval_every, segmenter)
        rows.append(row)
        if segmenter == "ade20k":
            scores = fusion_scores(result, pipeline, args.eval_every, args.gap * args.eval_every)
        result.slam.close()
    fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    lines = ["| run | labels | ATE (cm) | PSNR (dB) | submaps | classes (>= 1 % of the map's Gaussians) | "
             "segmenter (ms a frame) | loop detection P / R / F1 (pairs) | closures P / R (accepted) |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['run']} | {r['source']} | {fmt(r['ate_cm'], '.2f')} | {r['psnr']:.2f} | {r['submaps']} | "
              f"{', '.join(f'{n} {100 * s:.0f} %' for n, s in r['classes_in_map'])} | "
              f"{fmt(r['segmenter_ms_median'], '.0f')} | {_loops(r['loops'])} |" for r in rows]
    gap = args.gap * args.eval_every
    if scores is not None:
        lines += ["", f"| ade20k labels | cross-view consistency (frames {gap} apart) | mIoU against the data's "
                  "labels | pixel accuracy |", "|---|---|---|---|"]
        lines += [f"| {name.replace('_', ' ')} | {fmt(scores[f'consistency_{name}'], '.3f')} | "
                  f"{fmt(scores.get(f'miou_{name}'), '.3f')} | {fmt(scores.get(f'pixel_accuracy_{name}'), '.3f')} |"
                  for name in ("per_frame", "map")]
    doc = {"dataset": args.dataset, "size": f"{args.size[0]}x{args.size[1]}", "frames": args.frames,
           "eval_every": args.eval_every, "gap_frames": gap, "rows": rows, "fusion": scores}
    results.write_report(results.RESULTS / f"semantic_fusion_{args.name}", title="Segmented labels, per frame and "
                         "fused in the map", what=WHAT, markdown="\n".join(lines), data=doc)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
