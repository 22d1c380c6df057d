"""Can GauSem follow a camera? Per sequence, three runs of ``gausem run`` in fresh processes on the same parameters:

1. ``sync`` lock-step: every frame tracked and its keyframe mapped before the next (the reference ATE);
2. ``async`` lock-step: every frame, the mapping worker beside the tracker; its median per-frame cost is the
   tracker's own cost T (``frame_ms_median``: the ``process`` call, which in async returns after tracking);
3. ``--realtime``: the frames released on the wall clock at one every ``--interval-factor`` x T (default 1.5), the
   tracker taking the newest, the rest superseded. Where the tracker's median cost in that run exceeds T by over
   10 % (the camera thread reading frames beside it), T becomes that cost and the run is repeated (the one reported).

Reported per run: frames processed (and released, superseded), T, latency median / p95, the worker's lag and the map's
age, tracking losses and the ATE of the processed frames. Writes ``benchmarks/results/live_replay_<name>.{json,md}``.

    .venv/bin/python benchmarks/live_replay.py --dataset synthetic:loop --name synthetic_loop_160x120
    .venv/bin/python benchmarks/live_replay.py --dataset "tum:${GAUSEM_SHARED_DATA:-../shared/data}/tum_fr1_rpy" --name tum_fr1_rpy_160x120
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from gausem_core.io.metrics import git_commit

REPO = Path(__file__).resolve().parents[1]


def gausem_run(args, out: Path, extra: list[str]) -> dict:
    """One ``gausem run`` in a fresh process; its metrics.json and the recorded frame interval."""
    cmd = [str(Path(sys.executable).parent / "gausem"), "run", "--dataset", args.dataset, "--size", args.size,
           "--quiet", "--out", str(out), *(["--frames", str(args.frames)] if args.frames else []), *extra,
           *(x for s in args.set for x in ("--set", s))]
    result = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({result.returncode}):\n{result.stderr[-3000:]}")
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    stamps = np.loadtxt(out / "trajectory.txt", usecols=0, ndmin=1)
    metrics["interval_s"] = float(np.median(np.diff(stamps))) if len(stamps) > 1 else None
    return metrics


def row(mode: str, metrics: dict) -> dict:
    status = metrics.get("tracking_status", {})
    worker, live = metrics.get("worker", {}), metrics.get("live", {})
    return {"mode": mode, "frames_processed": metrics["frames"], "frames_released": live.get("frames_released"),
            "frames_superseded": live.get("frames_superseded"), "tracker_ms_median": metrics.get("frame_ms_median"),
            "tracker_ms_p95": metrics.get("frame_ms_p95"), "latency_ms_median": live.get("latency_ms_median"),
            "latency_ms_p95": live.get("latency_ms_p95"), "duration_s": live.get("duration_s", metrics["seconds"]),
            "lost": status.get("lost", 0), "keyframes_superseded": worker.get("keyframes_superseded"),
            "worker_lag_frames_median": worker.get("lag_frames_median"),
            "worker_lag_frames_max": worker.get("lag_frames_max"),
            "map_age_frames_median": worker.get("map_age_frames_median"),
            "map_age_frames_p95": worker.get("map_age_frames_p95"), "ate_cm": metrics.get("ate_rmse_cm"),
            "num_submaps": metrics.get("num_submaps")}


def markdown(doc: dict) -> str:
    fmt = lambda v, d=1: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    lines = [f"# Live replay: {doc['dataset']} at {doc['size']}", "", f"`{doc['command']}` at commit {doc['commit']} "
             f"on {doc['machine']}.", "", f"Tracker cost T: {fmt(doc['T_ms'])} ms (async lock-step median "
             f"{fmt(doc.get('T_lockstep_ms'))} ms); camera "
             f"interval in the real-time run {fmt(doc['camera_interval_ms'])} ms (rate {doc['rate']:.4f} of the "
             f"recorded pace).", "",
             "| mode | processed | released | superseded | T median / p95 (ms) | latency median / p95 (ms) "
             "| duration (s) | lost | keyframes superseded | worker lag median / max | map age median / p95 | ATE (cm) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["table"]:
        lines.append(f"| {r['mode']} | {r['frames_processed']} | {fmt(r['frames_released'])} | "
                     f"{fmt(r['frames_superseded'])} | {fmt(r['tracker_ms_median'], 0)} / {fmt(r['tracker_ms_p95'], 0)} "
                     f"| {fmt(r['latency_ms_median'], 0)} / {fmt(r['latency_ms_p95'], 0)} | {fmt(r['duration_s'])} | "
                     f"{r['lost']} | {fmt(r['keyframes_superseded'])} | {fmt(r['worker_lag_frames_median'])} / {fmt(r['worker_lag_frames_max'])} | "
                     f"{fmt(r['map_age_frames_median'])} / {fmt(r['map_age_frames_p95'])} | {fmt(r['ate_cm'], 2)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic:loop")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, help="at most this many frames (default: all)")
    parser.add_argument("--name", default="synthetic_loop_160x120")
    parser.add_argument("--interval-factor", type=float, default=1.5, help="camera interval in units of T")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="passed to every run")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sync = gausem_run(args, Path(tmp) / "sync", ["--set", "worker.mode=sync"])
        lockstep = gausem_run(args, Path(tmp) / "async", ["--set", "worker.mode=async"])
        t_s = lockstep["frame_ms_median"] / 1e3
        rate = sync["interval_s"] / (args.interval_factor * t_s)
        live = gausem_run(args, Path(tmp) / "live", ["--realtime", f"{rate:.6f}"])
        if live["frame_ms_median"] / 1e3 > 1.1 * t_s:  # the tracker is slower live (the camera thread reads frames
            t_s = live["frame_ms_median"] / 1e3  # beside it): again at the interval factor of its live cost
            rate = sync["interval_s"] / (args.interval_factor * t_s)
            live = gausem_run(args, Path(tmp) / "live", ["--realtime", f"{rate:.6f}"])
    command = "benchmarks/live_replay.py " + " ".join(sys.argv[1:])
    doc = {"command": f".venv/bin/python {command}", "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, "
           "no GPU)", "commit": git_commit(), "dataset": args.dataset, "size": args.size,
           "T_ms": 1e3 * t_s, "T_lockstep_ms": lockstep["frame_ms_median"], "camera_interval_ms": 1e3 * args.interval_factor * t_s, "rate": rate,
           "table": [row("sync lock-step", sync), row("async lock-step", lockstep), row("async --realtime", live)]}
    results = REPO / "benchmarks" / "results"
    (results / f"live_replay_{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    text = markdown(doc)
    (results / f"live_replay_{args.name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
