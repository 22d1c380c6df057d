"""Overhead of the ROS path over the offline CLI on the synthetic sequence (same frames, same parameters).

Each repeat runs, in fresh processes and in alternating order, ``gausem run`` and ``gausem-ros`` (every node in one
process, the player in lock-step on the same dataset spec, evaluated with ``--report``). Recorded per run: the process
wall time, its CPU time (user + system, all threads; less disturbed than wall time by other jobs on a shared machine)
and the SLAM loop time from its metrics.json (``seconds``: offline the frame loop, ROS the first frame's arrival to the
last frame's end, so message conversion, publishing and the loop-detection/pose-graph nodes count). The medians, their
ratios and the largest pose difference between the two trajectories go to ``benchmarks/results/ros_overhead.json`` (a results record).

    .venv/bin/python benchmarks/ros_overhead.py [--frames 30] [--size 160x120] [--repeats 3] [--set NAME=VALUE ...]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from gausem_bench import results
from gausem_core.io.metrics import git_commit
from gausem_core.io.trajectory import read_tum_trajectory
from gausem_core.options import parse_size

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TARGET = 1.10  # issue 6: ROS wall time at most 10 % above the offline CLI's
KEYS = ("loop_s", "cpu_s", "wall_s")
WHAT = ("`benchmarks/ros_overhead.py`: `gausem-ros` in lock-step against `gausem run` on the same synthetic frames, "
        "median of 3 each, one thread per process. Loop: offline, the frame loop of `gausem run`; ROS, from the first "
        "frame's arrival at tracking_mapping to the end of the last frame. Process CPU and wall: the whole command.")


def commands(args, out: Path) -> dict[str, list[str]]:
    size = f"{args.size[0]}x{args.size[1]}"
    sets = [s for name, value in args.set for s in ("--set", f"{name}={value}")]
    ros_params = [p for name, value in args.set for p in ("-p", f"{name}:={value}")]
    return {"offline": [str(BIN / "gausem"), "run", "--dataset", "synthetic", "--size", size, "--frames",
                        str(args.frames), "--params", str(args.params), "--quiet", "--out", str(out / "offline"),
                        *sets],
            "ros": [str(BIN / "gausem-ros"), "synthetic", "--size", size, "--max-frames", str(args.frames),
                    "--lockstep", "--rate", "0", "--timeout", "600", "--report", str(out / "ros"), "--ros-args",
                    "--params-file", str(args.params), *ros_params]}


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_run(cmd: list[str], out: Path, env: dict) -> dict:
    start, cpu = time.perf_counter(), _children_cpu()
    done = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - start, _children_cpu() - cpu
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "loop_s": round(metrics["seconds"], 3),
            "trajectory": read_tum_trajectory(out / "trajectory.txt")}


def pose_difference(a, b) -> float:
    """Largest camera-position difference (m) between two trajectories of the same frames."""
    if len(a.poses) != len(b.poses):
        return float("inf")
    return float(np.linalg.norm(a.positions - b.positions, axis=1).max())


def summarise(runs: list[dict], args) -> dict:
    median = {mode: {key: round(statistics.median(r[key] for r in runs if r["mode"] == mode), 3)
                     for key in KEYS} for mode in ("offline", "ros")}
    ratio = {f"{key}_ratio": round(median["ros"][key] / median["offline"][key], 4) for key in KEYS}
    return {"git_commit": git_commit(REPO), "torch": torch.__version__, "python": platform.python_version(),
            "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(), "threads": 1,
            "machine_note": args.note, "frames": args.frames, "size": list(args.size),
            "params_file": str(args.params.relative_to(REPO)), "overrides": dict(args.set), "repeats": args.repeats,
            "runs": runs, "median": median, "overhead": ratio, "target_ratio": TARGET}


def markdown(result: dict) -> str:
    med, ratio = result["median"], result["overhead"]
    rows = [f"| {mode} | " + " | ".join(str(med[mode][key]) for key in KEYS) + " |" for mode in ("offline", "ros")]
    load = ", ".join(f"{r['mode']} {r['load_average'][0]:.1f}" for r in result["runs"])
    return "\n".join([
        f"# ROS path vs offline CLI, synthetic {result['frames']} frames at {result['size'][0]}x{result['size'][1]}",
        "",
        f"`benchmarks/ros_overhead.py`, torch {result['torch']}, 1 thread per process, {result['cpu_count']} cores. {result['machine_note']}",
        "",
        f"Parameters: `{result['params_file']}`" + (f" with {result['overrides']}" if result['overrides'] else "")
        + f"; median of {result['repeats']} runs each, alternating order.",
        "",
        "| path | SLAM loop s | process CPU s | process wall s |", "|---|---|---|---|", *rows, "",
        f"Overhead (ROS / offline): loop **{ratio['loop_s_ratio']:.3f}**, process CPU **{ratio['cpu_s_ratio']:.3f}**, "
        f"process wall **{ratio['wall_s_ratio']:.3f}** (target <= {result['target_ratio']:.2f}). Largest position "
        "difference "
        f"between the two trajectories: {max(r['max_pose_difference_m'] for r in result['runs']):.2e} m.",
        "",
        "Loop: offline, the frame loop of `gausem run`; ROS, from the first frame's arrival at tracking_mapping to "
        "the end of the last frame (conversions, publishing, TF/path/map output and the loop_detection and "
        "pose_graph nodes included). Process CPU and wall: the whole command (start-up, player, evaluation, "
        "outputs); CPU counts every thread (DDS included).",
        f"1-min load average at each run's start: {load}.", ""])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--size", type=parse_size, default=(160, 120))
    parser.add_argument("--params", type=Path, default=REPO / "params" / "synthetic.yaml")
    parser.add_argument("--set", type=lambda t: tuple(t.split("=", 1)), action="append", default=[],
                        metavar="NAME=VALUE", help="parameter override for both paths")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument("--note", default="", help="what else ran on the machine (goes into the results)")
    args = parser.parse_args(argv)
    args.params = args.params.resolve()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "97"),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            cmds = commands(args, Path(tmp))
            trajectories = {}
            for mode in ("offline", "ros") if repeat % 2 == 0 else ("ros", "offline"):
                load = os.getloadavg()
                run = timed_run(cmds[mode], Path(tmp) / mode, env)
                trajectories[mode] = run.pop("trajectory")
                runs.append({"mode": mode, "repeat": repeat, **run, "load_average": [round(v, 2) for v in load]})
                print(f"repeat {repeat} {mode}: " + ", ".join(f"{k} {run[k]}" for k in KEYS), flush=True)
            difference = pose_difference(trajectories["offline"], trajectories["ros"])
            for run in runs[-2:]:
                run["max_pose_difference_m"] = difference
    result = summarise(runs, args)
    text = markdown(result)
    results.write_report(args.out / "ros_overhead", title="The ROS path's overhead", what=WHAT, markdown=text,
                         notes=[line for line in text.splitlines() if line.startswith("Overhead")], data=result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
