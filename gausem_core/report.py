"""The outputs of an offline run (the README's table): trajectories, keyframes, the map, metrics, a montage and a plot.

Rendering is evaluated as the paper does, on the processed frames' own views: the final global map is rendered at
each evaluated frame's *estimated* pose and compared with that frame's input. Ground truth is read here for
evaluation only (this module belongs with ``eval/`` in that respect).
"""
from __future__ import annotations

import csv
import math
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from gausem_core.config import SlamConfig, flatten
from gausem_core.eval.image import depth_l1, psnr, ssim
from gausem_core.data.synthetic import Scene
from gausem_core.eval.loops import DEFAULT_PROTOCOL, loop_scores
from gausem_core.eval.occupancy import layout_cells, occupancy_scores
from gausem_core.eval.semantic import confusion_matrix, mean_iou, pixel_accuracy
from gausem_core.eval.trajectory import absolute_trajectory_error, associate_trajectories
from gausem_core.geometry import invert_pose
from gausem_core.io import metrics as metrics_io
from gausem_core.io.montage import MontageRow, write_montage
from gausem_core.io.plots import write_trajectory_plot
from gausem_core.io.map_server import write_map_server
from gausem_core.io.ply import write_gaussian_ply
from gausem_core.io.trajectory import Trajectory, write_tum_trajectory
from gausem_core.maps.slam_grid import floor_class_id, slam_grid
from gausem_core.pipeline import Pipeline, RunResult, peak_rss_mb, percentile
from gausem_core.render import render
from gausem_core.slam.health import SIGNALS, STATUSES
from gausem_core.slam.system import GauSemSLAM

MONTAGE_FRAMES = 4


def estimated_trajectory(result: RunResult) -> Trajectory:
    """The estimated poses; a ValueError names the first frame whose estimate is not finite (tracking diverged)."""
    finite = np.isfinite(result.poses).reshape(len(result.poses), -1).all(1)
    if not finite.all():
        first = int(np.argmin(finite))
        raise ValueError(f"the estimated pose of frame {result.frame_ids[first]} (processed frame {first}) and "
                         f"{int((~finite).sum()) - 1} later ones are not finite: tracking diverged")
    return Trajectory(result.timestamps, result.poses)


def ground_truth_trajectory(result: RunResult) -> Trajectory | None:
    """The ground-truth poses of the processed frames that have one (None when none has)."""
    pairs = [(t, pose) for t, pose in zip(result.timestamps, result.gt_poses) if pose is not None]
    if not pairs:
        return None
    return Trajectory([t for t, _ in pairs], np.stack([pose for _, pose in pairs]))


def keyframe_trajectory(slam: GauSemSLAM) -> Trajectory:
    """World-frame keyframe poses (submap anchor applied) in frame order."""
    keyframes = sorted(((kf.frame_id, kf.obs.timestamp, submap.anchor @ kf.cam_to_world)
                        for submap in slam.submaps for kf in submap.keyframes), key=lambda item: item[0])
    poses = [pose.detach().cpu().double().numpy() for _, _, pose in keyframes]
    return Trajectory([t for _, t, _ in keyframes], np.array(poses).reshape(-1, 4, 4))


def trajectory_metrics(estimate: Trajectory, reference: Trajectory) -> tuple[dict, Trajectory | None]:
    """ATE after SE(3) Umeyama alignment on timestamp-associated poses (metres, plus ``ate_rmse_cm``).

    Returns the metrics and the aligned estimate; when the alignment is undetermined (fewer than 3 poses or a
    degenerate path) the metrics hold ``ate.error`` with the reason and no aligned estimate is returned.
    """
    try:
        est, ref = associate_trajectories(estimate, reference)
        ate = absolute_trajectory_error(est, ref)
    except ValueError as exc:
        return {"ate": {"error": str(exc)}, "ate_rmse_cm": math.nan}, None
    stats = {key: ate.stats[key] for key in ("rmse", "mean", "median", "max")}
    return {"ate": {**stats, "pairs": len(est)}, "ate_rmse_cm": 100.0 * ate.rmse}, est.transformed(ate.transform)


def nearest_palette_class(colors: torch.Tensor, palette: torch.Tensor) -> torch.Tensor:
    """(..., 3) colours -> (...) index of the nearest palette colour (C, 3)."""
    flat = colors.reshape(-1, 3)
    ids = torch.cdist(flat, palette.to(flat.device, flat.dtype)).argmin(-1)
    return ids.reshape(colors.shape[:-1])


def evenly_spaced(items: list, count: int) -> list:
    """Up to ``count`` items spread evenly over ``items``, first and last included."""
    if len(items) <= count:
        return list(items)
    return [items[round(i)] for i in np.linspace(0, len(items) - 1, count)]


@dataclass
class RenderingEvaluation:
    """Per-frame image scores, the summed confusion matrix (None without labels) and the montage rows."""

    scores: dict[str, list[float]] = field(default_factory=lambda: {"psnr": [], "ssim": [], "depth_l1_m": []})
    confusion: np.ndarray | None = None
    rows: list[MontageRow] = field(default_factory=list)

    def metrics(self) -> dict:
        """Means over the evaluated frames; mIoU and pixel accuracy over all their pixels (NaN without labels)."""
        out = {"frames": len(self.scores["psnr"])}
        out.update({name: float(np.mean(values)) if values else math.nan for name, values in self.scores.items()})
        labelled = self.confusion is not None
        out["miou"] = mean_iou(self.confusion) if labelled else math.nan
        out["pixel_accuracy"] = pixel_accuracy(self.confusion) if labelled else math.nan
        return out


def evaluation_positions(frames: int, eval_every: int) -> list[int]:
    """The processed-frame positions evaluated: every ``eval_every``-th of ``frames``, from the first."""
    if eval_every < 1:
        raise ValueError(f"eval_every must be >= 1, got {eval_every}")
    return list(range(0, frames, eval_every))


def rendered_views(result: RunResult, pipeline: Pipeline, positions: list[int]):
    """Yield (frame, observation, render) per processed-frame position: the final global map rendered at the frame's
    estimated pose (no gradients), its colour as the camera records it (times the run's vignetting estimate)."""
    cloud = result.slam.global_cloud().to(pipeline.device)
    for k in positions:
        i = result.dataset_positions[k]
        frame = pipeline.dataset[i]
        if frame.index != result.frame_ids[k]:
            raise ValueError(f"processed frame {k} has id {result.frame_ids[k]} but the dataset's frame {i} is "
                             f"{frame.index}: the run result does not belong to this dataset")
        obs = pipeline.observation(frame)
        world_to_cam = invert_pose(torch.as_tensor(result.poses[k], dtype=cloud.dtype, device=cloud.device))
        with torch.no_grad():
            out = render(cloud, world_to_cam, obs.camera, backend=pipeline.cfg.backend)
        yield frame, obs, replace(out, color=result.slam.vignetting.apply(out.color, obs.camera))


def evaluate_rendering(result: RunResult, pipeline: Pipeline, eval_every: int,
                       montage_frames: int = MONTAGE_FRAMES) -> RenderingEvaluation:
    """Render the global map at every ``eval_every``-th processed frame's estimated pose and score it.

    PSNR and SSIM over the whole image; depth L1 of the rendered (alpha-accumulated) depth over pixels with a
    measured depth; semantics by the nearest palette class of each rendered semantic colour, against the dataset's
    labels when they index the run's classes (:meth:`FrameSemantics.ground_truth`).
    """
    positions = evaluation_positions(len(result.frame_ids), eval_every)
    shown = set(evenly_spaced(positions, montage_frames))
    evaluation = RenderingEvaluation()
    for k, (frame, obs, out) in zip(positions, rendered_views(result, pipeline, positions)):
        evaluation.scores["psnr"].append(psnr(out.color, obs.rgb))
        evaluation.scores["ssim"].append(float(ssim(out.color, obs.rgb)))
        if obs.valid_depth.any():
            evaluation.scores["depth_l1_m"].append(depth_l1(out.depth, obs.depth))
        truth = pipeline.semantics.ground_truth(frame)
        if truth is not None:
            predicted = nearest_palette_class(out.semantic, pipeline.palette)
            confusion = confusion_matrix(predicted, torch.as_tensor(truth, device=predicted.device),
                                         len(pipeline.palette))
            evaluation.confusion = confusion if evaluation.confusion is None else evaluation.confusion + confusion
        if k in shown:
            evaluation.rows.append(MontageRow(frame.rgb, out.color, out.semantic, out.depth, obs.depth,
                                              label=f"frame {frame.index}"))
    return evaluation


def performance_metrics(result: RunResult, device: torch.device) -> dict:
    """Frames, timing (a `process` call, a frame's tracking, a keyframe's mapping: median and p95 ms), map size, peak
    host memory and (on CUDA) peak GPU memory."""
    frames = len(result.frame_ids)
    slam, back = result.slam, result.slam.back_end
    out = {"frames": frames, "seconds": result.seconds, "fps": result.fps,
           "seconds_per_frame": result.seconds / frames if frames else math.nan,
           "num_gaussians": sum(len(s.cloud) for s in slam.submaps), "num_submaps": len(slam.submaps),
           "gaussians_per_submap": [len(s.cloud) for s in slam.submaps],
           "num_keyframes": sum(len(s.keyframes) for s in slam.submaps), "peak_rss_mb": peak_rss_mb()}
    phases = {"frame": result.frame_seconds, "tracking": slam.front_end.tracking_seconds,
              "mapping": back.mapping_seconds, "growth": back.growth_seconds}  # a process call; a frame's tracking;
    # a keyframe's mapping; async: a keyframe's growth on the tracker's clock
    for phase, seconds in phases.items():
        if seconds:
            out[f"{phase}_ms_median"] = 1e3 * percentile(seconds, 0.5)
            out[f"{phase}_ms_p95"] = 1e3 * percentile(seconds, 0.95)
    rules = sorted({rule for rule, _ in back.allocation_rules})
    out["allocation"] = {rule: {"decisions": back.allocation_rules[rule, False] + back.allocation_rules[rule, True],
                                "new_submaps": back.allocation_rules[rule, True]} for rule in rules}
    out["worker"] = {"mode": slam.cfg.worker.mode, **(back.worker.stats.summary() if back.worker is not None else {}),
                     "map_age_frames_median": percentile(result.map_ages, 0.5),
                     "map_age_frames_p95": percentile(result.map_ages, 0.95),
                     "iterations_per_keyframe_median": percentile(list(back.window_iterations.values()), 0.5),
                     "window_age_frames_median": percentile(back.window_ages, 0.5),
                     "window_age_frames_p95": percentile(back.window_ages, 0.95)}
    if result.live is not None:
        out["live"] = result.live
    if device.type == "cuda":
        out["gpu_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def loop_metrics(result: RunResult) -> dict:
    """Which place recognition ran, detected and accepted loops, also split into intra-submap ones (keyframe
    alignment) and inter-submap ones (each an SGR registration), candidates turned down by geometric verification,
    the loop closure's time by phase and as a fraction of the run's and, with ground truth for every frame,
    precision/recall/F1 under :data:`DEFAULT_PROTOCOL` (paper §IV-C-2) of the loops among the run's frames; the same
    for ``detection``: every candidate pair the checks found (Algorithm 1), before verification.

    Loops and rejections are counted over the session: a resumed run's include those restored with the loaded session
    (``loaded_session``). These and the run's loops back into the loaded map (``into_loaded_map``) involve frames the
    run has no ground truth for: they are not scored."""
    closure = result.slam.loop_closure
    records = closure.records
    out = {"place_recognition": closure.place_recognition, "detected": len(records),
           "accepted": sum(r.accepted for r in records), "rejected_by_verification": closure.rejected_candidates,
           "seconds": sum(r.seconds for r in records), "seconds_by_phase": dict(closure.seconds),
           "fraction_of_run_time": sum(closure.seconds.values()) / result.seconds if result.seconds > 0 else math.nan}
    for name, intra in (("intra_submap", True), ("inter_submap", False)):
        level = [r for r in records if r.intra == intra]
        out[name] = {"registrations": len(level), "accepted": sum(r.accepted for r in level)}
    first = result.first_frame  # the frames before it are a loaded session's
    out["loaded_session"] = sum(r.query_frame < first for r in records)
    out["into_loaded_map"] = sum(r.match_frame < first <= r.query_frame for r in records)
    own = [(r.query_frame - first, r.match_frame - first) for r in records if r.match_frame >= first]
    detected = [(q - first, m - first) for q, m in closure.detector.detections if m >= first]
    out["detection"] = {"pairs": len(detected)}  # every candidate pair of the checks, before verification
    if all(p is not None for p in result.gt_poses) and result.gt_poses:
        positions = np.stack([p[:3, 3] for p in result.gt_poses])
        if own:
            scores = loop_scores(own, positions, timestamps=result.timestamps, **DEFAULT_PROTOCOL)
            out.update(scores.as_dict(), protocol=DEFAULT_PROTOCOL)
        if detected:
            out["detection"].update(loop_scores(detected, positions, timestamps=result.timestamps,
                                                **DEFAULT_PROTOCOL).as_dict())
    return out


def write_tracking_status(path: Path, result: RunResult) -> dict[str, int]:
    """Write ``frame, timestamp, status, <signals>, reasons`` per frame given to the system (dropped ones
    included) as CSV; the number of frames per status."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frame", "timestamp", "status", *SIGNALS, "reasons"])
        for frame, stamp, health in result.health:
            signals = health.signals()
            writer.writerow([frame, f"{stamp:.6f}", health.status, *(f"{signals[n]:.6g}" for n in SIGNALS),
                             " ".join(health.reasons)])
    counts = Counter(health.status for _, _, health in result.health)
    return {status: counts[status] for status in STATUSES}


def write_grid(result: RunResult, pipeline: Pipeline, out: Path) -> dict:
    """The final map's occupancy grid as ``grid.pgm`` and ``grid.yaml`` (map_server); its figures: where the floor came
    from, the grid's size and cells per state, the seconds it took and, on a synthetic room seen from its first frame,
    the scores against the room's layout (:mod:`gausem_core.eval.occupancy`). A map without a floor writes no grid
    and says why."""
    cfg, table = pipeline.cfg.grid, pipeline.semantics.class_table
    start = time.perf_counter()
    try:
        grid = slam_grid(result.slam, cfg, pipeline.palette,
                         floor_class_id(table.names if table is not None else None, cfg.floor_class))
    except ValueError as err:
        return {"error": str(err)}
    seconds = time.perf_counter() - start
    write_map_server(grid, out / "grid.yaml")
    rows, cols = grid.cells.shape
    metrics = {"floor": grid.floor.source, "floor_inliers": grid.floor.inliers, "resolution": grid.resolution,
               "width": cols, "height": rows, "cells": grid.counts(), "seconds": seconds}
    scene = getattr(pipeline.dataset, "scene", None)
    if isinstance(scene, Scene) and result.first_frame == 0 and result.gt_poses[0] is not None:
        truth, in_room = layout_cells(grid, scene, result.gt_poses[0], cfg.min_height, cfg.max_height)
        metrics["layout"] = occupancy_scores(grid, truth, in_room)
    return metrics


LOOP_COLUMNS = ("query_frame", "match_frame", "query_submap", "match_submap", "intra", "accepted", "fitness", "inliers",
                "seconds")


def write_loops(path: Path, records) -> None:
    """Write one CSV row per detected loop (:class:`~gausem_core.slam.loop_closure.LoopRecord`), accepted or not."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(LOOP_COLUMNS)
        for record in records:
            writer.writerow([f"{v:.6g}" if isinstance(v, float) else int(v) for v in
                             (getattr(record, name) for name in LOOP_COLUMNS)])


def write_outputs(result: RunResult, dataset, cfg: SlamConfig, out: str | Path, *, eval_every: int = 5,
                  params_file: str | Path | None = None) -> dict:
    """Write a run's outputs into ``out`` and return its metrics.

    Files: ``trajectory.txt`` (TUM, estimate), ``loops.csv`` (every detected loop, with loop closure on),
    ``tracking_status.csv`` (per-frame tracking health, its counts per
    status in the metrics' ``tracking_status``), ``keyframes.txt`` (TUM, keyframe poses), ``map.ply`` (3DGS-style,
    class ids unless the run has no labels and no segmenter), ``grid.pgm`` and ``grid.yaml`` (the occupancy grid as
    map_server reads it, :func:`write_grid`), ``metrics.json``, ``montage.png`` and, with ground truth,
    ``trajectory_gt.txt`` and ``trajectory.png`` (SE(3)-aligned estimate vs ground truth).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pipeline = Pipeline(dataset, cfg, progress=False)
    estimate = estimated_trajectory(result)
    write_tum_trajectory(out / "trajectory.txt", estimate)
    write_tum_trajectory(out / "keyframes.txt", keyframe_trajectory(result.slam))

    metrics = {"tracking_status": write_tracking_status(out / "tracking_status.csv", result)}
    reference = ground_truth_trajectory(result)
    if reference is not None:
        write_tum_trajectory(out / "trajectory_gt.txt", reference)
        ate_metrics, aligned = trajectory_metrics(estimate, reference)
        metrics.update(ate_metrics)
        if aligned is not None:
            write_trajectory_plot(out / "trajectory.png", aligned.positions, reference.positions,
                                  title=f"{getattr(dataset, 'name', 'run')}: ATE RMSE "
                                        f"{ate_metrics['ate_rmse_cm']:.2f} cm (SE(3)-aligned)")

    cloud = result.slam.global_cloud()
    has_classes = pipeline.semantics.class_table is not None
    write_gaussian_ply(out / "map.ply", cloud, cloud.class_ids(pipeline.palette) if has_classes else None)

    metrics["grid"] = write_grid(result, pipeline, out)
    evaluation = evaluate_rendering(result, pipeline, eval_every)
    metrics["rendering"] = evaluation.metrics()
    if evaluation.rows:
        write_montage(out / "montage.png", evaluation.rows)
    metrics.update(performance_metrics(result, pipeline.device))
    a = result.slam.vignetting.a
    metrics["vignetting"] = {"a": a, "corner_gain": math.exp(a)}  # V(r) = exp(a r^2); corner_gain: V at r = 1
    metrics["segments"] = {"started": 1 + sum(s.starts_segment for s in result.slam.submaps),
                           "separate_at_end": len(result.slam.segments())}
    descriptor = result.slam.back_end.descriptor
    metrics["semantics"] = {**pipeline.semantics.summary(),
                            "descriptor": descriptor.kind if descriptor is not None else None}
    if result.slam.loop_closure is not None:
        metrics["loops"] = loop_metrics(result)
        write_loops(out / "loops.csv", result.slam.loop_closure.records)

    parameters = {**flatten(cfg), "params_file": params_file, "dataset": getattr(dataset, "name", None),
                  "eval_every": eval_every}
    metrics_io.write_metrics_json(out / "metrics.json", metrics, parameters=parameters, device=pipeline.device)
    return metrics


def _headline(metrics: dict) -> list[tuple[str, float, str]]:
    rendering = metrics.get("rendering", {})
    miou = rendering.get("miou", math.nan)
    return [("ATE RMSE", metrics.get("ate_rmse_cm", math.nan), "cm"), ("PSNR", rendering.get("psnr", math.nan), "dB"),
            ("SSIM", rendering.get("ssim", math.nan), ""), ("mIoU", 100.0 * miou if miou is not None else math.nan, "%"),
            ("fps", metrics.get("fps", math.nan), "")]


def format_summary(metrics: dict) -> str:
    """Headline figures (ATE cm, PSNR, SSIM, mIoU, fps) first, then every metric (:func:`io.metrics.format_summary`)."""
    lines = []
    for name, value, unit in _headline(metrics):
        text = "n/a" if value is None or not math.isfinite(value) else f"{value:.4g} {unit}".rstrip()
        lines.append(f"{name:<9} {text}")
    return "\n".join([*lines, "", metrics_io.format_summary(metrics)])
