"""The spatial-semantic allocation rule's inputs at every keyframe, on ground-truth poses (issue #23, part 4).

    python benchmarks/submap_allocation.py   # benchmarks/results/submap_allocation.json (a results record)

For each sequence (synthetic 'default' and 'loop' with labels; TUM fr1_rpy and 7-Scenes redkitchen from
$GAUSEM_SHARED_DATA, without labels) and each overlap measure (``submaps.overlap``: ``view`` = |F n V| / |F|, the
measure before this change; ``iou`` = |F n V| / |F u V|), the policy (params/synthetic.yaml's submaps section, with that
measure) runs over the keyframes (every 5th frame, 160x120, ground-truth poses). At every keyframe both measures are
taken on the same submap volume, with the overlap of the previous keyframe's frustum alone, |V| / |F| and the class KL.
"""
from __future__ import annotations

import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import torch

from gausem_bench import results
from gausem_bench.data import SHARED_DATA
from gausem_core.config import flatten, load_config
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.slam.allocation import (FrustumUnion, SubmapExtent, depth_range, frustum_iou, frustum_overlap,
                                         frustum_volume, make_allocation)

ROOT = Path(__file__).resolve().parents[1]
WHAT = ("`benchmarks/submap_allocation.py`: on ground-truth poses, the allocation rule's inputs at every keyframe, for "
        "the overlap measures `view` (share of the keyframe's view inside the submap's frusta) and `iou` (the "
        "default).")
SEQUENCES = {"synthetic default": "synthetic:default", "synthetic loop": "synthetic:loop",
             "tum fr1_rpy": f"tum:{SHARED_DATA / 'tum_fr1_rpy'}", "7-scenes redkitchen": f"tum:{SHARED_DATA / '7scenes_redkitchen'}"}
SIZE, EVERY = (160, 120), 5


def keyframe_inputs(spec: str, measure: str) -> list[dict]:
    cfg = load_config(ROOT / "params" / "synthetic.yaml", {"submaps.overlap": measure})
    dataset = open_dataset(spec, size=SIZE)
    pipeline = Pipeline(dataset, replace(cfg, device="cpu"), progress=False)
    policy = make_allocation(cfg.submaps)
    origin = torch.linalg.inv(torch.as_tensor(dataset[0].gt_pose))
    rows, extent, previous = [], None, None
    for i in range(0, len(dataset), EVERY):
        frame = dataset[i]
        obs, pose = pipeline.observation(frame), (origin @ torch.as_tensor(frame.gt_pose)).float()
        if extent is None:
            extent = SubmapExtent.start(obs, pose, len(pipeline.palette))
            previous = extent.volume.frusta[-1]
            continue
        span = depth_range(obs.depth)
        last = FrustumUnion([previous])
        decision = policy.should_start_new(extent, obs, pose)
        rows.append({"frame": i, "keyframes": extent.num_keyframes,
                     "view": frustum_overlap(obs.camera, pose, span, extent.volume),
                     "iou": frustum_iou(obs.camera, pose, span, extent.volume),
                     "previous_keyframe_view": frustum_overlap(obs.camera, pose, span, last),
                     "volume_ratio": extent.volume.volume() / frustum_volume(obs.camera, *span),
                     "kl": decision.kl, "new": decision.new})
        if decision.new:
            extent = SubmapExtent.start(obs, pose, len(pipeline.palette))
        else:
            extent.add(obs, pose)
        previous = extent.volume.frusta[-1]
    return rows


def summary(rows: list[dict]) -> dict:
    def median(key):
        return statistics.median(r[key] for r in rows)
    return {"keyframes": len(rows) + 1, "submaps": 1 + sum(r["new"] for r in rows),
            "boundaries": [r["frame"] for r in rows if r["new"]],
            "median_view": median("view"), "median_iou": median("iou"),
            "median_previous_keyframe_view": median("previous_keyframe_view"),
            "keyframes_view_below_0.5": sum(r["view"] < 0.5 for r in rows),
            "keyframes_iou_below_0.5": sum(r["iou"] < 0.5 for r in rows),
            "keyframes_kl_above_0.4": sum(r["kl"] > 0.4 for r in rows)}


def markdown(result: dict, settings: dict) -> str:
    lines = ["# Submap allocation: the rule's inputs per keyframe", "", "`python benchmarks/submap_allocation.py`", "",
             __doc__.split("\n\n", 2)[2].strip(), "",
             "| sequence | measure | keyframes | submaps | boundaries (frames) | median view | median IoU | "
             "median view of the previous keyframe alone | view < 0.5 | IoU < 0.5 | KL > 0.4 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, runs in result.items():
        for measure, run in runs.items():
            s = run["summary"]
            lines.append(f"| {name} | {measure} | {s['keyframes']} | {s['submaps']} | {s['boundaries']} | "
                         f"{s['median_view']:.3f} | {s['median_iou']:.3f} | "
                         f"{s['median_previous_keyframe_view']:.3f} | {s['keyframes_view_below_0.5']} | "
                         f"{s['keyframes_iou_below_0.5']} | {s['keyframes_kl_above_0.4']} |")
    lines += ["", "Per keyframe (synthetic loop, `iou`; columns: frame, keyframes in the submap, view, IoU, view of "
              "the previous keyframe alone, |V|/|F|, KL, new):", "", "```"]
    lines += [f"{r['frame']:4d} {r['keyframes']:3d} {r['view']:.3f} {r['iou']:.3f} {r['previous_keyframe_view']:.3f} "
              f"{r['volume_ratio']:6.2f} {r['kl']:.3f} {'NEW' if r['new'] else ''}"
              for r in result["synthetic loop"]["iou"]["keyframes"]]
    lines += ["```", "", "Settings: " + ", ".join(f"{k}={v}" for k, v in settings.items()), ""]
    return "\n".join(lines)


def main() -> int:
    torch.set_num_threads(1)
    result = {}
    for name, spec in SEQUENCES.items():
        if spec.startswith("tum:") and not Path(spec[4:]).is_dir():
            print(f"{name}: {spec[4:]} is absent, skipped")
            continue
        result[name] = {}
        for measure in ("view", "iou"):
            rows = keyframe_inputs(spec, measure)
            result[name][measure] = {"summary": summary(rows), "keyframes": rows}
            print(name, measure, json.dumps(result[name][measure]["summary"]), flush=True)
    settings = {k: v for k, v in flatten(load_config(ROOT / "params" / "synthetic.yaml")).items()
                if k.startswith("submaps.")}
    results.write_report(results.RESULTS / "submap_allocation", title="Submap allocation: the rule's inputs per "
                         "keyframe", what=WHAT, markdown=markdown(result, settings),
                         data={"parameters": settings, "metrics": result})
    return 0


if __name__ == "__main__":
    sys.exit(main())
