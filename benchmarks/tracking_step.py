"""What one tracking step costs on one CPU thread, and what it gets right: model views rendered per level against one
model view per frame (``tracking.gauss_newton.model_views``), on a fixed map.

The map is built at the ground-truth poses of every ``--keyframe-every``-th frame of the first ``--frames`` (the
dataset's parameter file, mapping as the SLAM system maps a keyframe), then every frame (every ``--step``-th: a live
tracker slower than its camera) is tracked against it from the constant-velocity prediction of its variant's own
previous estimates (the previous estimate as the alternative start, as the system does). The variants take turns frame
by frame, so that load on a shared machine falls on both. Per variant: median and 90th-percentile milliseconds of
``Tracker.track``, renders per frame, translation error (RMSE, mm) and rotation error (median, degrees) against the
ground truth, and the median milliseconds of the health signals the front end then takes (``inspect_pose``), on the view
tracking aligned against as the system does and on a view rendered at the pose. From the repository root:

    python benchmarks/tracking_step.py --dataset synthetic:loop
    python benchmarks/tracking_step.py --dataset 'tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy'
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
import torch

from gausem_core.config import TrackingConfig, load_config
from gausem_core.data import open_dataset
from gausem_core.geometry import invert_pose, so3_log
from gausem_core.pipeline import Pipeline
from gausem_core.slam import tracker as tracker_module
from gausem_core.slam.mapper import Keyframe, Mapper
from gausem_core.slam.health import image_signals
from gausem_core.slam.tracker import Tracker, TrackingResult, constant_velocity, inspect_pose
from gausem_core.options import default_params_file

from gausem_bench import results
from gausem_bench.data import expand
VARIANTS = ("per_level", "per_frame")  # model_views[,KEY=VALUE...] of tracking.gauss_newton
WHAT = ("Tracker.track against a fixed map built at the ground-truth poses of every 5th frame, each frame from the "
        "constant-velocity prediction of its variant's own estimates (variants take turns frame by frame); "
        "model views rendered at every pyramid level (per_level) or once per frame at full resolution and "
        "downsampled, again only when the estimate moved rerender_motion (per_frame); other tracking.gauss_newton "
        "values after commas. Health: inspect_pose + image_signals after each frame, on the tracked view where it "
        "holds (as the system does) and on a view rendered at the pose.")


def fixed_map(pipeline: Pipeline, poses: list[torch.Tensor], every: int):
    """Gaussians mapped from every ``every``-th observation at its true pose, as the system maps keyframes."""
    cfg = pipeline.cfg.mapping
    mapper = Mapper(cfg, pipeline.cfg.backend, pipeline.cfg.seed)
    keyframes = [Keyframe(0, pipeline.observation(pipeline.dataset[0]), poses[0], fixed=True)]
    cloud, _ = mapper.optimise(mapper.strategy.initial(keyframes[0].obs, poses[0]), keyframes, cfg.init_iterations)
    for i in range(every, len(poses), every):
        keyframes.append(Keyframe(i, pipeline.observation(pipeline.dataset[i]), poses[i], fixed=True))
        cloud = mapper.strategy.grow(cloud, keyframes[-1].obs, poses[i])
        cloud, _ = mapper.optimise(cloud, keyframes[-cfg.window:], cfg.iterations)
    return cloud


def judge_health(cloud, obs, pose: torch.Tensor, tracking: TrackingConfig, cfg, tracked: TrackingResult | None):
    """What the front end does after tracking a frame: the health signals at ``pose``, on the view ``tracked`` was
    aligned against where it holds (None: a view rendered at the pose)."""
    view, motion, hessian = inspect_pose(cloud, obs, pose, tracking, cfg.backend, tracked)
    return image_signals(view, obs, hessian, cfg.health, motion)


def with_variant(cfg, name: str):
    """``cfg`` (tracking.gauss_newton) with the model views and the other values that ``name`` sets
    (``MODEL_VIEWS[,KEY=VALUE...]``, e.g. ``per_frame,min_step=1e-5``)."""
    views, *settings = name.split(",")
    values = {key: type(getattr(cfg, key))(value) for key, value in (s.split("=", 1) for s in settings)}
    return replace(cfg, model_views=views, **values)


class RenderCounter:
    """Counts the tracker module's renders."""

    def __init__(self):
        self.count, self._render = 0, tracker_module.render
        tracker_module.render = self

    def __call__(self, *args, **kwargs):
        self.count += 1
        return self._render(*args, **kwargs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="synthetic:loop")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--keyframe-every", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--step", type=int, default=1,
                        help="track every STEP-th frame, as a live tracker slower than its camera does (default 1)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS),
                        help="model_views values, each optionally with tracking.gauss_newton values "
                             "(e.g. per_frame,min_step=1e-5,rerender_motion=0.01)")
    parser.add_argument("--name", help="results file name (default: tracking_step_<dataset>_<size>)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    size = tuple(int(v) for v in args.size.split("x"))
    dataset = open_dataset(expand(args.dataset), size=size, max_frames=args.frames)
    cfg = load_config(default_params_file(args.dataset.split(":")[0]))
    pipeline = Pipeline(dataset, cfg, progress=False)
    origin = np.linalg.inv(dataset[0].gt_pose)
    truths = [torch.tensor(origin @ dataset[i].gt_pose, dtype=torch.float32) for i in range(len(dataset))]
    cloud = fixed_map(pipeline, truths, args.keyframe_every)
    observations = [pipeline.observation(dataset[i]) for i in range(len(dataset))]
    trackers = {v: Tracker(replace(cfg.tracking, gauss_newton=with_variant(cfg.tracking.gauss_newton, v)), cfg.backend)
                for v in args.variants}
    counter = RenderCounter()
    estimates = {v: [truths[0]] for v in args.variants}
    stats = {v: {"ms": [], "renders": [], "t_err": [], "r_err": [], "health_ms": [], "rendered_health_ms": []}
             for v in args.variants}
    tracked_frames = range(args.step, len(dataset), args.step)
    for turn, i in enumerate(tracked_frames):
        for variant in args.variants if turn % 2 else reversed(args.variants):
            chain = estimates[variant]
            start = constant_velocity(chain[-1], chain[-2] if len(chain) > 1 else None)
            before, t0 = counter.count, time.perf_counter()
            tracked = trackers[variant].track(cloud, observations[i], start, [chain[-1]])
            stats[variant]["ms"].append(1000 * (time.perf_counter() - t0))
            stats[variant]["renders"].append(counter.count - before)
            for key, given in (("health_ms", tracked), ("rendered_health_ms", None)):
                t0 = time.perf_counter()
                judge_health(cloud, observations[i], tracked.cam_to_world, trackers[variant].cfg, cfg, given)
                stats[variant][key].append(1000 * (time.perf_counter() - t0))
            pose = tracked.cam_to_world
            delta = invert_pose(pose) @ truths[i]
            stats[variant]["t_err"].append(1000 * float(delta[:3, 3].norm()))
            stats[variant]["r_err"].append(float(np.degrees(float(so3_log(delta[:3, :3]).norm()))))
            chain.append(pose)
    columns = ["model views", "track ms median", "track ms p90", "renders per frame", "translation RMSE mm",
               "rotation median deg", "health ms median", "health ms median, rendered"]
    rows = [[v, round(float(np.median(s["ms"])), 1), round(float(np.percentile(s["ms"], 90)), 1),
             round(float(np.mean(s["renders"])), 2), round(float(np.sqrt(np.mean(np.square(s["t_err"])))), 2),
             round(float(np.median(s["r_err"])), 3), round(float(np.median(s["health_ms"])), 1),
             round(float(np.median(s["rendered_health_ms"])), 1)] for v, s in stats.items()]
    ratios = ", ".join(f"{row[0]} {rows[0][1] / row[1]:.2f}x" for row in rows[1:])
    step = f" (every {args.step}th of {len(dataset)})" if args.step > 1 else ""
    name = args.name or f"tracking_step_{results.label(args.dataset).replace(' ', '_')}_{args.size}"
    results.write(results.RESULTS / name, results.record(
        title=f"Tracking step on a fixed map: {results.label(args.dataset)} at {args.size}",
        what=WHAT + f" {len(tracked_frames)} frames tracked{step}, {args.threads} thread(s); median times, {rows[0][0]} "
                    f"over the others: {ratios}.",
        table=results.table(columns, rows)))
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(v) for v in row))

if __name__ == "__main__":
    main()
