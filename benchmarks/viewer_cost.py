"""What does the live 3D view cost a run? ``gausem run`` on the embedded synthetic sequence once without and once with
``--viewer`` (record: the Rerun recording only, no viewer attached), each in its own process; reports the pipeline's
time (metrics.json ``seconds``: tracking, mapping, the viewer's logging, the global refinement), the process's wall
time and the recording's size. Writes ``benchmarks/results/viewer_cost_<name>.{json,md}``.

    .venv/bin/python benchmarks/viewer_cost.py --frames 30 --size 160x120
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gausem_core.io.metrics import git_commit

REPO = Path(__file__).resolve().parents[1]


def run(args: argparse.Namespace, out: Path, viewer: bool) -> dict:
    """One ``gausem run`` process; its pipeline seconds, frame time, wall seconds and recording size."""
    command = [sys.executable, "-m", "gausem_core.cli", "run", "--dataset", args.dataset, "--size", args.size,
               "--frames", str(args.frames), "--quiet", "--out", str(out)] + (["--viewer"] if viewer else [])
    began = time.perf_counter()
    subprocess.run(command, cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - began
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    recording = out / "gausem.rrd"
    return {"viewer": viewer, "pipeline_s": metrics["seconds"], "frame_ms_median": metrics["frame_ms_median"],
            "wall_s": wall, "recording_mb": recording.stat().st_size / 2**20 if recording.exists() else None}


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
    ratio = on["pipeline_s"] / off["pipeline_s"]
    doc = {"command": ".venv/bin/python benchmarks/viewer_cost.py " + " ".join(sys.argv[1:]),
           "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, no GPU; load average {os.getloadavg()[0]:.1f} "
                      "at the end: the cores are shared)", "commit": git_commit(), "dataset": args.dataset,
           "size": args.size, "frames": args.frames, "ratio_pipeline": ratio,
           "ratio_wall": on["wall_s"] / off["wall_s"], "table": rows}
    lines = [f"# The viewer's cost: {args.dataset}, {args.frames} frames at {args.size}", "",
             f"`{doc['command']}` at commit {doc['commit']} on {doc['machine']}.", "",
             f"With `--viewer` (record) / without: pipeline time x{ratio:.3f}, process wall time "
             f"x{doc['ratio_wall']:.3f} (one run each).", "",
             "| viewer | pipeline (s) | median frame (ms) | process (s) | recording (MB) |", "|---|---|---|---|---|"]
    lines += [f"| {'record' if r['viewer'] else 'off'} | {r['pipeline_s']:.1f} | {r['frame_ms_median']:.0f} | "
              f"{r['wall_s']:.1f} | {r['recording_mb'] or 0:.1f} |" for r in rows]
    results = REPO / "benchmarks" / "results"
    (results / f"viewer_cost_{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    (results / f"viewer_cost_{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
