"""What does a crash-safe checkpoint cost the tracking node? Runs a sequence in ``sync`` mode, checkpointing into one
folder at every ``--every``-th keyframe as the node does (``gausem_core.slam.checkpoint``), and reports each
checkpoint's write time and the session's size on disk against the run's median frame time. Writes
``benchmarks/results/checkpoint_cost_<name>.json`` (a results record).

    .venv/bin/python benchmarks/checkpoint_cost.py --dataset tum:../shared/data/tum_fr1_rpy --frames 100 --name tum_fr1_rpy_160x120
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from gausem_core.config import load_config
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.slam.checkpoint import Checkpointer
from gausem_core.slam.system import GauSemSLAM

from gausem_bench import results

REPO = Path(__file__).resolve().parents[1]
WHAT = ("`benchmarks/checkpoint_cost.py`: what writing a session checkpoint (`map_path`, every "
        "`checkpoint_keyframes` keyframes) costs as the map grows, `sync` mode.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="synthetic:loop")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--every", type=int, default=5, help="checkpoint every this many new keyframes")
    parser.add_argument("--name", default="synthetic_loop_160x120")
    args = parser.parse_args()
    dataset = open_dataset(args.dataset, size=tuple(int(v) for v in args.size.split("x")), max_frames=args.frames)
    kind = args.dataset.split(":")[0]
    cfg = load_config(REPO / "params" / f"{kind}.yaml", {"worker.mode": "sync"})
    pipeline = Pipeline(dataset, cfg, progress=False)
    rows, frame_seconds = [], []
    with tempfile.TemporaryDirectory() as tmp, GauSemSLAM(cfg, pipeline.device, len(pipeline.palette)) as slam:
        checkpoints = Checkpointer(Path(tmp) / "session", args.every, 0.0)
        checkpoints.start(slam)
        for i in range(len(dataset)):
            obs = pipeline.observation(dataset[i])
            begin = time.perf_counter()
            slam.process(obs)
            frame_seconds.append(time.perf_counter() - begin)
            if checkpoints.due(slam):
                seconds = checkpoints.write(slam)
                size = sum(p.stat().st_size for p in checkpoints.folder.iterdir())
                rows.append({"frame": i, "frames": len(slam.frames), "submaps": len(slam.submaps),
                             "gaussians": sum(s.num_gaussians for s in slam.submaps), "seconds": seconds,
                             "size_mb": size / 2**20})
                print(rows[-1], flush=True)
    frame_ms = 1e3 * statistics.median(frame_seconds)
    doc = {"dataset": args.dataset, "size": args.size, "frame_ms_median": frame_ms,
           "checkpoint_ms_median": 1e3 * statistics.median(r["seconds"] for r in rows) if rows else None,
           "rows": rows}
    note = (f"Median frame (tracking and mapping, sync): {frame_ms:.0f} ms; median checkpoint: "
            f"{doc['checkpoint_ms_median'] or 0:.0f} ms.")
    lines = ["| after frame | frames | submaps | Gaussians | write (ms) | size (MB) |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['frame']} | {r['frames']} | {r['submaps']} | {r['gaussians']} | {1e3 * r['seconds']:.0f} | "
              f"{r['size_mb']:.1f} |" for r in rows]
    results.write_report(results.RESULTS / f"checkpoint_cost_{args.name}",
                         title=f"Checkpoint cost: {results.label(args.dataset)}", what=WHAT,
                         markdown="\n".join(lines), notes=[note], data=doc)


if __name__ == "__main__":
    main()
