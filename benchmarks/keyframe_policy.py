"""Keyframes every d_map-th frame or by need? Per policy (``mapping.keyframes``: every, motion), ``gausem run`` in
fresh processes on the same parameters:

1. ``sync`` lock-step: every frame tracked and its keyframe mapped before the next (deterministic);
2. ``--realtime RATE`` (``--repeats`` times, medians reported): the camera at RATE times its recorded pace, the tracker
   taking the newest frame, the mapping worker beside it. A tracker slower than the camera processes only some frames:
   every d_map-th *processed* frame is then a keyframe far apart in the camera's time, one by need where the view moved.

Reported per run: frames processed, keyframes, tracking losses, ATE of the processed frames, wall time. Writes
``benchmarks/results/keyframe_policy_<name>.json`` (a results record).

    .venv/bin/python benchmarks/keyframe_policy.py --dataset tum:../shared/data/tum_fr1_rpy --name tum_fr1_rpy_160x120
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from gausem_bench import results
from gausem_bench.runs import add_run_arguments, gausem_run

POLICIES = ("every", "motion")
WHAT = ("`benchmarks/keyframe_policy.py`: keyframes every `mapping.every`-th frame against keyframes chosen by the "
        "view's motion, lock-step and under `--realtime`.")


def summary(mode: str, policy: str, runs: list[dict]) -> dict:
    """Medians over the runs of one mode and policy."""
    def median(key, default=None):
        values = [r.get(key, default) for r in runs]
        return statistics.median(values) if None not in values else None
    return {"mode": mode, "policy": policy, "runs": len(runs), "frames_processed": median("frames"),
            "keyframes": median("num_keyframes"), "submaps": median("num_submaps"),
            "lost": statistics.median(r.get("tracking_status", {}).get("lost", 0) for r in runs),
            "ate_cm": median("ate_rmse_cm"), "seconds": median("seconds")}


def markdown(doc: dict) -> str:
    fmt = lambda v, d=1: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    lines = ["| mode | policy | runs | processed | keyframes | submaps | lost | ATE (cm) | wall time (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["table"]:
        lines.append(f"| {r['mode']} | {r['policy']} | {r['runs']} | {fmt(r['frames_processed'])} | "
                     f"{fmt(r['keyframes'])} | {fmt(r['submaps'])} | {fmt(r['lost'])} | {fmt(r['ate_cm'], 2)} | "
                     f"{fmt(r['seconds'])} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--rate", type=float, default=0.25, help="the live camera's pace, times the recorded one")
    parser.add_argument("--repeats", type=int, default=3, help="real-time runs per policy")
    args = parser.parse_args()
    table = []
    with tempfile.TemporaryDirectory() as tmp:
        for policy in POLICIES:
            chosen = ["--set", f"mapping.keyframes={policy}"]
            sync = gausem_run(args, Path(tmp) / f"sync_{policy}", [*chosen, "--set", "worker.mode=sync"])
            table.append(summary("sync lock-step", policy, [sync]))
            live = [gausem_run(args, Path(tmp) / f"live_{policy}_{i}", [*chosen, "--realtime", str(args.rate)])
                    for i in range(args.repeats)]
            table.append(summary(f"async --realtime {args.rate:g}", policy, live))
            print(markdown({"table": table}), flush=True)
    doc = {"dataset": args.dataset, "size": args.size, "rate": args.rate, "rows": table}
    results.write_report(results.RESULTS / f"keyframe_policy_{args.name}",
                         title=f"Keyframes by need (`mapping.keyframes: motion`), {results.label(args.dataset)}",
                         what=WHAT, markdown=markdown({"table": table}), data=doc)


if __name__ == "__main__":
    main()
