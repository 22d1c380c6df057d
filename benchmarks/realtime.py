"""The node suite on a sequence replayed like a live camera (``--rate 1``) against the same sequence in lock-step.

Runs ``gausem-ros SOURCE --report DIR`` in fresh processes on the same parameters: once in lock-step (every frame
processed, the reference) and once per ``--rates`` value at that fraction of the recorded rate (the tracker takes
the newest frame and drops what it cannot keep up with; the run ends once its pending frame is processed).
Recorded per run: frames in, processed, dropped by reason, pending, latency median and p95 (a synchronised frame's
arrival to its pose's publication), the player's playback time, and the ATE of the processed frames (none with fewer
than 3); written to ``benchmarks/results/realtime_<name>.json`` (a results record).

    .venv/bin/python benchmarks/realtime.py [--source "tum:${GAUSEM_SHARED_DATA:-../shared/data}/tum_fr1_rpy"] [--size 160x120]
        [--params params/tum.yaml] [--name tum_fr1_rpy_160x120] [--rates 1 0.1] [-- ROS_ARGS...]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gausem_bench import results
from gausem_bench.data import SHARED_DATA

REPO = Path(__file__).resolve().parents[1]
WHAT = ("`benchmarks/realtime.py`: the frames played to the node suite (`gausem-ros`) in lock-step (the node in `sync`) "
        "and at the given rates of their recorded pace (the node in `async`); ROS arguments after `--`.")
BIN = Path(sys.executable).parent
LOCKSTEP = ["--lockstep", "--rate", "0", "--timeout", "600"]


def run(mode: str, args, ros_args: list[str], out: Path) -> dict:
    timing = LOCKSTEP if mode == "lock-step" else ["--rate", mode.split()[1]]
    cmd = [str(BIN / "gausem-ros"), args.source, "--size", args.size, *timing, "--quiet", "--report", str(out),
           "--ros-args", "--params-file", args.params, *ros_args]
    env = {**os.environ, "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "57"),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    start = time.monotonic()
    result = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"{mode} run failed ({result.returncode}):\n{result.stderr[-3000:]}")
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    accounting = json.loads((out / "input.json").read_text())
    ate = metrics["ate_rmse_cm"]  # None (NaN) with fewer than 3 processed frames
    return {"mode": mode, "wall_s": round(time.monotonic() - start, 1), "ate_cm": ate if ate is None else round(ate, 2),
            "ate": metrics["ate"], **accounting}


def markdown(rows: list[dict], args, ros_args: list[str]) -> str:
    lines = ["| mode | frames in | processed | dropped (by reason) | pending | latency median / p95 (ms) | playback (s) "
             "| ATE (cm, processed frames) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        dropped = ", ".join(f"{k} {v}" for k, v in r["dropped"].items()) or "none"
        lines.append(f"| {r['mode']} | {r['frames_in']} | {r['frames_processed']} | {sum(r['dropped'].values())} "
                     f"({dropped}) | {r['frames_pending']} | {r.get('latency_ms.median', '-')} / "
                     f"{r.get('latency_ms.p95', '-')} | {r['player']['playback_seconds']} | {r['ate_cm']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    argv = sys.argv[1:]
    ros_args = argv[argv.index("--") + 1:] if "--" in argv else []
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--source", default=f"tum:{SHARED_DATA / 'tum_fr1_rpy'}")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--params", default="params/tum.yaml")
    parser.add_argument("--name", default="tum_fr1_rpy_160x120")
    parser.add_argument("--rates", type=float, nargs="+", default=[1.0, 0.1], help="replay rates besides lock-step")
    args = parser.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    modes = ["lock-step", *(f"rate {r:g}" for r in args.rates)]
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run(mode, args, ros_args, Path(tmp) / mode.replace(" ", "_")) for mode in modes]
    results.write_report(results.RESULTS / f"realtime_{args.name}",
                         title=f"The node suite in real time: {results.label(args.source)}", what=WHAT,
                         markdown=markdown(rows, args, ros_args), data=rows)


if __name__ == "__main__":
    main()
