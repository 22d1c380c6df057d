"""What does the live 3D view cost a run? ``gausem run`` on the embedded synthetic sequence once without and once with
``--viewer`` (record: the Rerun recording only, no viewer attached), each in its own process; reports the process's
CPU time (user + system, every thread: Rerun's logging threads too), the pipeline's wall time (metrics.json
``seconds``: tracking, mapping, the viewer's logging, the global refinement), the process's wall time and the
recording's size. On shared cores the wall times follow the other work; the CPU time much less. Writes the record
``benchmarks/results/viewer_cost_<name>.json``.

    python benchmarks/viewer_cost.py --frames 30 --size 160x120
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gausem_bench import results

REPO = Path(__file__).resolve().parents[1]
WHAT = ("`gausem run` without and with `--viewer` (record: the Rerun recording only, no viewer attached), each in its "
        "own process: the process's CPU time (every thread, Rerun's too), the pipeline's wall time, the process's "
        "wall time and the recording's size. On shared cores the wall times follow the other work, the CPU time much "
        "less.")


def run(args: argparse.Namespace, out: Path, viewer: bool) -> dict:
    """One ``gausem run`` process; its CPU seconds, pipeline seconds, frame time, wall seconds and recording size."""
    command = [sys.executable, "-m", "gausem_core.cli", "run", "--dataset", args.dataset, "--size", args.size,
               "--frames", str(args.frames), "--quiet", "--out", str(out)] + (["--viewer"] if viewer else [])
    load = os.getloadavg()[0]
    began, cpu = time.perf_counter(), cpu_seconds()
    subprocess.run(command, cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    wall, cpu = time.perf_counter() - began, cpu_seconds() - cpu
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    recording = out / "gausem.rrd"
    return {"viewer": viewer, "load_before": load, "cpu_s": cpu, "pipeline_s": metrics["seconds"], "frame_ms_median": metrics["frame_ms_median"],
            "wall_s": wall, "recording_mb": recording.stat().st_size / 2**20 if recording.exists() else None}


def cpu_seconds() -> float:
    """User and system time of this process's finished children."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--name", default="synthetic_160x120")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run(args, Path(tmp) / name, viewer) for name, viewer in (("off", False), ("record", True))]
    off, on = rows
    ratio = {key: on[key] / off[key] for key in ("cpu_s", "pipeline_s", "wall_s")}
    columns = ["viewer", "load before", "CPU (s)", "pipeline (s)", "median frame (ms)", "process (s)",
               "recording (MB)"]
    table = [["record" if r["viewer"] else "off", round(r["load_before"], 1), round(r["cpu_s"], 1),
              round(r["pipeline_s"], 1), round(r["frame_ms_median"]), round(r["wall_s"], 1),
              round(r["recording_mb"] or 0, 1)] for r in rows]
    results.write(results.RESULTS / f"viewer_cost_{args.name}", results.record(
        title=f"The live view's cost: {args.dataset}, {args.frames} frames at {args.size}",
        what=WHAT + f" With `--viewer` (record) over without, one run each: CPU time x{ratio['cpu_s']:.3f}, "
                    f"pipeline time x{ratio['pipeline_s']:.3f}, process wall time x{ratio['wall_s']:.3f}.",
        table=results.table(columns, table), data={"rows": rows, "ratio": ratio}))

if __name__ == "__main__":
    main()
