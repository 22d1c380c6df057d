"""One benchmark run, meant to execute in a fresh process: GauSem's offline pipeline or an Open3D baseline.

:func:`run_case` returns a JSON-ready record: what ran (sequence, configuration, every parameter, seed), where
(device, git commit, threads), the metrics and the status. A run that raises is recorded as ``failed`` with the
error, so that one broken configuration does not end a suite. Peak CPU memory is the process's maximum resident set
(``ru_maxrss``): per run, because each run has its own process.
"""
from __future__ import annotations

import json
import time
import traceback
from pathlib import Path

import numpy as np
import torch

from gausem_bench.suite import Case, open_sequence
from gausem_core.io.metrics import git_commit, to_jsonable


def rendering_lpips(result, pipeline, eval_every: int, weights: str) -> float:
    """Mean LPIPS of the final map rendered at every ``eval_every``-th frame's estimated pose (as PSNR/SSIM are)."""
    from gausem_core.eval.image import lpips
    from gausem_core.report import evaluation_positions, rendered_views

    positions = evaluation_positions(len(result.frame_ids), eval_every)
    return float(np.mean([lpips(out.color, obs.rgb, weights)
                          for _, obs, out in rendered_views(result, pipeline, positions)]))


def run_gausem(case: Case) -> tuple[dict, str]:
    """GauSem's offline pipeline; its outputs (``gausem run``'s files) go to ``case.out_dir``."""
    from gausem_core.config import from_flat
    from gausem_core.io.metrics import describe_device
    from gausem_core.pipeline import Pipeline
    from gausem_core.report import write_outputs

    cfg = from_flat(case.parameters)
    dataset = open_sequence(case.sequence)
    pipeline = Pipeline(dataset, cfg, progress=case.progress)
    result = pipeline.run()
    metrics = write_outputs(result, dataset, cfg, case.out_dir, eval_every=case.sequence.eval_every,
                            params_file=case.params_file)
    if case.lpips_weights:
        metrics["rendering"]["lpips"] = rendering_lpips(result, pipeline, case.sequence.eval_every, case.lpips_weights)
        path = Path(case.out_dir) / "metrics.json"
        document = json.loads(path.read_text())
        document["metrics"]["rendering"]["lpips"] = metrics["rendering"]["lpips"]
        path.write_text(json.dumps(document, indent=2) + "\n")
    return metrics, describe_device(pipeline.device)


def run_open3d(case: Case) -> tuple[dict, str]:
    """An Open3D baseline; writes ``trajectory.txt`` (and ``trajectory_gt.txt``) in TUM format to ``case.out_dir``."""
    from gausem_bench.baselines import Open3DParams, run_baseline
    from gausem_core.io.trajectory import Trajectory, write_tum_trajectory
    from gausem_core.pipeline import peak_rss_mb
    from gausem_core.report import ground_truth_trajectory, trajectory_metrics

    run = run_baseline(case.method, open_sequence(case.sequence), Open3DParams(**case.parameters), case.progress)
    out = Path(case.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    estimate = Trajectory(run.timestamps, run.poses)
    write_tum_trajectory(out / "trajectory.txt", estimate)
    metrics = {}
    reference = ground_truth_trajectory(run)
    if reference is not None:
        write_tum_trajectory(out / "trajectory_gt.txt", reference)
        metrics.update(trajectory_metrics(estimate, reference)[0])
    frames = len(run.timestamps)
    metrics.update(frames=frames, seconds=run.seconds, fps=frames / run.seconds, seconds_per_frame=run.seconds / frames,
                   tracking_failures=run.tracking_failures, peak_rss_mb=peak_rss_mb(), open3d=run.details)
    return metrics, f"open3d {run.device}"


RUNNERS = {"gausem": run_gausem, "open3d_odometry": run_open3d, "open3d_slam": run_open3d}


def describe(case: Case) -> dict:
    """What a run is: names, dataset, every parameter, seed, frames; with the commit and the thread count."""
    s = case.sequence
    return {"sequence": s.name, "dataset": s.dataset, "dataset_name": case.dataset_name,
            "configuration": case.configuration.name, "method": case.method, "note": case.configuration.note,
            "overrides": case.overrides, "parameters": case.parameters, "params_file": case.params_file,
            "seed": case.seed, "size": s.size, "stride": s.stride, "frames": case.frames,
            "eval_every": s.eval_every, "depth_registered": case.depth_registered,
            "color_calibration": s.color_calibration, "out_dir": str(case.out_dir),
            "git_commit": git_commit(), "threads": torch.get_num_threads()}


def send_run_case(case: Case, connection) -> None:
    """:func:`run_case`, its record sent through ``connection`` (a multiprocessing pipe end), which is then closed."""
    try:
        connection.send(run_case(case))
    finally:
        connection.close()


def run_case(case: Case) -> dict:
    """Run ``case`` in this process and return its record (status ``ok`` with metrics, or ``failed`` with error)."""
    if case.threads:
        torch.set_num_threads(case.threads)
    torch.manual_seed(case.seed)
    np.random.seed(case.seed)
    record = describe(case)
    start = time.perf_counter()
    try:
        metrics, device = RUNNERS[case.method](case)
        record.update(status="ok", device=device, metrics=metrics)
    except Exception as exc:  # noqa: BLE001 (a failed run is a benchmark result, not the end of the suite)
        traceback.print_exc()
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    record["wall_seconds"] = time.perf_counter() - start
    return to_jsonable(record)
