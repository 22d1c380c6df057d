"""Submap benchmarks (issue 4) on the synthetic "default" sequence at 160x120; results in benchmarks/results/.

    python benchmarks/submaps.py allocation              # benchmarks/results/submaps_allocation.json
    python benchmarks/submaps.py slam [--set NAME=VALUE]  # benchmarks/results/submaps_slam.json
    python benchmarks/submaps.py memory --frames 500 2000 [--set NAME=VALUE]  # benchmarks/results/submaps_memory.json

allocation: the allocation policies alone on ground-truth keyframe poses (every 5th frame): boundaries, counts and
object cohesion (fraction of each object's points in its majority submap), over the whole sequence and per visit.
slam: GauSemSLAM over the sequence, once per policy: boundaries, counts, cohesion of its keyframe-to-submap assignment
and of its Gaussians (each submap placed with its ground-truth anchor, so that drift does not separate an object).
memory: one fresh process per length (the default sequence's closed walk repeated) reports peak RSS after the run.
With ``--poses ground-truth`` (slam, memory) the tracker runs as usual (its time and memory count) but its estimate is
replaced by the ground-truth pose, which keeps the map sane when the tracker diverges.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import torch

from gausem_bench import results
from gausem_core.config import SubmapConfig, flatten, load_config
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.data.synthetic import SEQUENCES
from gausem_core.eval.fragmentation import allocation_cohesion, object_instances, submap_cohesion
from gausem_core.geometry import invert_pose, transform_points
from gausem_core.pipeline import Pipeline, peak_rss_mb
from gausem_core.slam.allocation import make_allocation, partition_keyframes
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import Tracker, TrackingResult
from gausem_core.options import parse_override

ROOT = Path(__file__).resolve().parents[1]
TITLES = {"allocation": "Submap allocation: what it does to objects", "slam": "Submaps: the full system",
          "memory": "Submaps: memory over long runs"}
PARAMS = ROOT / "params" / "synthetic.yaml"
SIZE = (160, 120)
STRUCTURE = tuple(SYNTHETIC_CLASSES.id_of(n) for n in ("floor", "wall", "ceiling"))
REVISIT_GAP = 5  # keyframes: an object out of view longer than this and seen again is a revisit (a loop)
POLICIES = {"semantic": {}, "semantic, no hysteresis": {"min_keyframes": 1}, "motion": {"policy": "motion"}}


class RepeatedWalk(SyntheticDataset):
    """The "default" sequence's closed walk, repeated up to ``frames`` frames (its poses are periodic)."""

    def __init__(self, frames: int):
        super().__init__("default", resolution=SIZE)
        self.frames = frames

    def _source_length(self) -> int:
        return self.frames


class GroundTruthPoses:
    """A tracker for ``GauSemSLAM(tracker=...)``: runs the wrapped tracker, then returns the ground-truth pose (in the
    active submap's frame) instead. :attr:`slam` is the system it tracks for, set once that exists."""

    def __init__(self, tracker: Tracker, dataset):
        self.tracker, self.dataset = tracker, dataset
        self.backend = tracker.backend  # relocalisation renders with it
        self.slam: GauSemSLAM | None = None
        self.first = torch.as_tensor(dataset[0].gt_pose)

    def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None) -> TrackingResult:
        result = self.tracker.track(cloud, obs, init_cam_to_world, alternatives, search)
        world = invert_pose(self.first) @ torch.as_tensor(self.dataset[len(self.slam.frames)].gt_pose)
        local = invert_pose(self.slam.active.anchor.double()) @ world.to(self.slam.device)
        return TrackingResult(local.to(result.cam_to_world.dtype), result.loss, result.iterations)


def boundary_frames(submap_ids: list[int], frame_ids: list[int]) -> list[int]:
    return [frame_ids[k] for k in range(1, len(submap_ids)) if submap_ids[k] != submap_ids[k - 1]]


def keyframe_views(dataset, frame_ids: list[int]):
    """(depth, labels, camera, ground-truth pose) per frame id, as the cohesion measure takes them."""
    frames = [dataset[i] for i in frame_ids]
    return [(torch.as_tensor(f.depth), torch.as_tensor(f.labels), f.camera, torch.as_tensor(f.gt_pose))
            for f in frames]


def cohesion_figures(views, submap_ids: list[int]) -> dict:
    whole = allocation_cohesion(views, submap_ids, STRUCTURE)
    visits = allocation_cohesion(views, submap_ids, STRUCTURE, revisit_gap=REVISIT_GAP)
    return {"cohesion_whole": whole.mean, "cohesion_whole_worst": whole.worst, "cohesion_per_visit": visits.mean,
            "cohesion_per_visit_worst": visits.worst, "objects": len(whole.objects), "visits": len(visits.objects)}


# --- allocation alone ---------------------------------------------------------------------------------------------
def allocation(args) -> dict:
    dataset = SyntheticDataset("default", resolution=SIZE)
    frame_ids = list(range(0, len(dataset), 5))
    pipeline = Pipeline(dataset, load_config(PARAMS), progress=False)
    keyframes = [(pipeline.observation(dataset[i]), torch.as_tensor(dataset[i].gt_pose)) for i in frame_ids]
    views = keyframe_views(dataset, frame_ids)
    out = {}
    for name, options in POLICIES.items():
        cfg = SubmapConfig(**options)
        ids, decisions = partition_keyframes(make_allocation(cfg), keyframes, len(SYNTHETIC_CLASSES))
        bounds = boundary_frames(ids, frame_ids)
        reasons = [f"frame {i}: {d.reason}" for i, d in zip(frame_ids[1:], decisions) if d.new]
        out[name] = {"config": vars(cfg), "submaps": ids[-1] + 1, "boundaries": bounds, "reasons": reasons,
                     **cohesion_figures(views, ids)}
    return out


# --- SLAM runs ----------------------------------------------------------------------------------------------------
def run_slam(dataset, cfg, poses: str) -> tuple[GauSemSLAM, list, float]:
    pipeline = Pipeline(dataset, cfg, progress=False)
    oracle = GroundTruthPoses(Tracker(cfg.tracking, cfg.backend), dataset) if poses == "ground-truth" else None
    slam = GauSemSLAM(cfg, pipeline.device, len(SYNTHETIC_CLASSES), tracker=oracle)
    if oracle is not None:
        oracle.slam = slam
    start = time.perf_counter()
    results = [slam.process(pipeline.observation(dataset[i])) for i in range(len(dataset))]
    return slam, results, time.perf_counter() - start


def gaussian_cohesion(slam: GauSemSLAM, dataset) -> dict:
    """Cohesion of the Gaussians themselves, each submap placed in the world with its anchor keyframe's ground truth."""
    first = invert_pose(torch.as_tensor(dataset[0].gt_pose))
    points, labels, submaps = [], [], []
    for submap in slam.submaps:
        cloud = submap.load_cloud("cpu")
        anchor = first @ torch.as_tensor(dataset[submap.keyframes[0].frame_id].gt_pose)
        points.append(transform_points(anchor, cloud.means.double()))
        labels.append(cloud.class_ids(SYNTHETIC_CLASSES.palette))
        submaps.append(torch.full((len(cloud),), submap.submap_id))
    labels = torch.cat(labels)
    instances = object_instances(torch.cat(points), labels, 0.1, STRUCTURE)
    cohesion = submap_cohesion(instances, labels, torch.cat(submaps))
    return {"gaussian_cohesion_whole": cohesion.mean, "gaussian_cohesion_whole_worst": cohesion.worst,
            "gaussian_objects": len(cohesion.objects)}


def slam_runs(args) -> dict:
    dataset = SyntheticDataset("default", resolution=SIZE)
    out = {}
    for name, options in POLICIES.items():
        overrides = {**dict(args.overrides), **{f"submaps.{k}": v for k, v in options.items()}}
        cfg = load_config(PARAMS, overrides)
        slam, results, seconds = run_slam(dataset, cfg, args.poses)
        keyframes = [r for r in results if r.is_keyframe]
        ids, frame_ids = [r.submap_id for r in keyframes], [r.frame_id for r in keyframes]
        reasons = [f"frame {r.frame_id}: {r.allocation.reason}" for r in keyframes if r.allocation and r.allocation.new]
        gt = [invert_pose(torch.as_tensor(dataset[0].gt_pose)) @ torch.as_tensor(dataset[i].gt_pose)
              for i in range(len(dataset))]
        drift = max(float((p.double()[:3, 3] - g[:3, 3]).norm()) for (_, p), g in zip(slam.trajectory(), gt))
        out[name] = {"submaps": len(slam.submaps), "boundaries": boundary_frames(ids, frame_ids), "reasons": reasons,
                     "seconds": seconds, "max_position_error_m": drift,
                     **cohesion_figures(keyframe_views(dataset, frame_ids), ids), **gaussian_cohesion(slam, dataset)}
        slam.close()
        print(f"{name}: {out[name]}", flush=True)
    return out


# --- peak memory vs length ----------------------------------------------------------------------------------------
def memory_case(args) -> None:
    """One length in this process: prints one JSON line."""
    torch.set_num_threads(1)
    dataset = RepeatedWalk(args.frames[0])
    cfg = load_config(PARAMS, dict(args.overrides))
    slam, results, seconds = run_slam(dataset, cfg, args.poses)
    figures = {"frames": len(results), "seconds": seconds, "peak_rss_mb": peak_rss_mb(), "submaps": len(slam.submaps),
               "keyframes": sum(len(s.keyframes) for s in slam.submaps),
               "active_gaussians": slam.active.num_gaussians,
               "stored_gaussians": sum(s.num_gaussians for s in slam.submaps[:-1]),
               "store_memory_mb": slam.back_end.store.nbytes / 2**20, "store_disk_mb": slam.back_end.store.disk_bytes / 2**20}
    print(json.dumps(figures))


def memory(args) -> dict:
    cases = []
    for frames in args.frames:
        command = [sys.executable, __file__, "memory-case", "--frames", str(frames), "--poses", args.poses,
                   *[f"--set={k}={json.dumps(v)}" for k, v in args.overrides]]
        done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
        if done.returncode:
            raise RuntimeError(f"{shlex.join(command)} failed:\n{done.stderr[-4000:]}")
        cases.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(cases[-1], flush=True)
    return {"cases": cases, "peak_ratio_longest_to_shortest": cases[-1]["peak_rss_mb"] / cases[0]["peak_rss_mb"]}


# --- reports ------------------------------------------------------------------------------------------------------
def table(rows: dict, columns: list[tuple[str, str]]) -> str:
    def fmt(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)
    lines = ["| policy | " + " | ".join(title for _, title in columns) + " |",
             "|---" * (len(columns) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(fmt(row[key]) for key, _ in columns) + " |" for name, row in rows.items()]
    return "\n".join(lines)


NOTES = {
    "allocation": "The policies alone on ground-truth poses of every 5th frame (the keyframes of mapping.every=5).",
    "slam": "GauSemSLAM over the sequence, one run per policy; Gaussian cohesion: each submap's Gaussians placed in "
            "the world with its anchor keyframe's ground-truth pose, objects = same-class 10 cm voxel components.",
    "memory": "The default sequence's closed walk repeated to the given length, one fresh process per length; peak "
              "RSS of that process after the run (nothing exported).",
}


def description(kind: str, poses: str) -> str:
    """What a run of ``kind`` measures (the record's ``what``)."""
    cohesion = (f"Cohesion: mean over objects of the fraction of their points in their majority submap; per visit: "
                f"an object seen again after more than {REVISIT_GAP} keyframes out of view counts as a new object.")
    pose_note = {"estimated": "Poses: the tracker's estimates.",
                 "ground-truth": "Poses: the tracker runs (its time and memory count) but the ground-truth pose "
                                 "replaces its estimate."}[poses]
    return (f"`benchmarks/submaps.py {kind}`: synthetic 'default' sequence ({SEQUENCES['default'].frames} frames) at "
            f"{SIZE[0]}x{SIZE[1]}. " + NOTES[kind] + ("" if kind == "allocation" else " " + pose_note)
            + ("" if kind == "memory" else " " + cohesion))


def markdown(kind: str, result: dict, cfg) -> str:
    head = [f"# Submaps: {kind}", ""]
    if kind == "memory":
        rows = {f"{c['frames']} frames": c for c in result["cases"]}
        body = [table(rows, [("peak_rss_mb", "peak RSS MB"), ("submaps", "submaps"), ("keyframes", "keyframes"),
                             ("store_memory_mb", "store in memory MB"), ("store_disk_mb", "store on disk MB"),
                             ("seconds", "seconds")]).replace("| policy |", "| run |"),
                "", f"Peak ratio, longest / shortest: {result['peak_ratio_longest_to_shortest']:.3f}"]
    else:
        columns = [("submaps", "submaps"), ("boundaries", "boundaries (frames)"),
                   ("cohesion_per_visit", "cohesion per visit"), ("cohesion_whole", "cohesion whole sequence"),
                   ("cohesion_per_visit_worst", "worst object per visit")]
        if kind == "slam":
            columns += [("gaussian_cohesion_whole", "Gaussian cohesion whole"), ("max_position_error_m", "max err m")]
        body = [table(result, columns)]
    sections = ("submaps",) if kind == "allocation" else ("tracking", "mapping", "submaps")
    settings = {k: v for k, v in flatten(cfg).items() if k.split(".")[0] in sections}
    if kind != "memory":
        body += ["", "Boundary decisions:"] + [f"- {name}: " + "; ".join(row.get("reasons", [])) for name, row in
                                                result.items() if row.get("reasons")]
    return "\n".join(head + body + ["", "Settings: " + ", ".join(f"{k}={v}" for k, v in settings.items()), ""])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=["allocation", "slam", "memory", "memory-case"])
    parser.add_argument("--frames", type=int, nargs="+", default=[500, 2000], help="memory: sequence lengths")
    parser.add_argument("--poses", choices=["estimated", "ground-truth"], default="estimated",
                        help="slam, memory: the tracker's estimates, or the ground truth in their place")
    parser.add_argument("--set", dest="overrides", type=parse_override, action="append", default=[],
                        metavar="NAME=VALUE", help="parameter override on top of params/synthetic.yaml")
    parser.add_argument("--name", help="results file stem (default: submaps_<kind>)")
    args = parser.parse_args()
    if args.kind == "memory-case":
        memory_case(args)
        return 0
    result = {"allocation": allocation, "slam": slam_runs, "memory": memory}[args.kind](args)
    cfg = load_config(PARAMS, dict(args.overrides))
    text = markdown(args.kind, result, cfg)
    results.write_report(results.RESULTS / (args.name or f"submaps_{args.kind}"), title=TITLES[args.kind],
                         what=description(args.kind, args.poses), markdown=text,
                         notes=[line for line in text.splitlines() if line.startswith("Peak ratio")],
                         data={"parameters": {"poses": args.poses, **flatten(cfg)}, "metrics": result})
    return 0


if __name__ == "__main__":
    sys.exit(main())
