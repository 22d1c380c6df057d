"""Can GauSem follow a camera? Per sequence, three runs of ``gausem run`` in fresh processes on the same parameters:

1. ``sync`` lock-step: every frame tracked and its keyframe mapped before the next (the reference ATE);
2. ``async`` lock-step: every frame, the mapping worker beside the tracker; its median per-frame cost is the
   tracker's own cost T (``frame_ms_median``: the ``process`` call, which in async returns after tracking);
3. ``--realtime``: the frames released on the wall clock, the tracker taking the newest, the rest superseded: at
   ``--rate`` times the recorded pace (1: as recorded), or else at one every ``--interval-factor`` x T (default 1.5).
   In the second case, where the tracker's median cost in that run exceeds T by over 10 % (a busy machine,
   relocalisations of a lost tracker), the run is repeated at the interval factor of that live cost; both runs are
   reported.

Reported per run: frames processed (and released, superseded), T, the median of a frame's tracking and of a
keyframe's mapping, latency median / p95, the worker's lag and the map's age, the optimisation steps each newest
keyframe's window got and its age in frames, tracking losses and the ATE of the processed frames. Writes
``benchmarks/results/live_replay_<name>.json`` (a results record).

    .venv/bin/python benchmarks/live_replay.py --dataset synthetic:loop --rate 1 --name synthetic_loop_160x120
    .venv/bin/python benchmarks/live_replay.py --dataset "tum:${GAUSEM_SHARED_DATA:-../shared/data}/tum_fr1_rpy" \
        --rate 1 --name tum_fr1_rpy_160x120
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from gausem_bench import results
from gausem_bench.runs import add_run_arguments, gausem_run

WHAT = ("`benchmarks/live_replay.py`: three `gausem run` processes per sequence: `sync` lock-step, `async` "
        "lock-step, and `--realtime` releasing the frames on the wall clock (at `--rate` times the recorded pace, or "
        "one every 1.5 T, T: the tracker's median cost per frame in async lock-step, with a fourth at 1.5 times the "
        "tracker's live cost where that exceeds T by over 10 %). No ROS.")


def row(mode: str, metrics: dict) -> dict:
    status = metrics.get("tracking_status", {})
    worker, live = metrics.get("worker", {}), metrics.get("live", {})
    return {"mode": mode, "frames_processed": metrics["frames"], "frames_released": live.get("frames_released"),
            "frames_superseded": live.get("frames_superseded"), "tracker_ms_median": metrics.get("frame_ms_median"),
            "tracker_ms_p95": metrics.get("frame_ms_p95"), "tracking_ms_median": metrics.get("tracking_ms_median"),
            "mapping_ms_median": metrics.get("mapping_ms_median"), "latency_ms_median": live.get("latency_ms_median"),
            "latency_ms_p95": live.get("latency_ms_p95"), "duration_s": live.get("duration_s", metrics["seconds"]),
            "lost": status.get("lost", 0), "keyframes_superseded": worker.get("keyframes_superseded"),
            "worker_lag_frames_median": worker.get("lag_frames_median"),
            "worker_lag_frames_max": worker.get("lag_frames_max"),
            "map_age_frames_median": worker.get("map_age_frames_median"),
            "map_age_frames_p95": worker.get("map_age_frames_p95"),
            "iterations_per_keyframe": worker.get("iterations_per_keyframe_median"),
            "window_age_frames_median": worker.get("window_age_frames_median"),
            "window_age_frames_p95": worker.get("window_age_frames_p95"), "ate_cm": metrics.get("ate_rmse_cm"),
            "num_submaps": metrics.get("num_submaps")}


def markdown(doc: dict) -> str:
    fmt = lambda v, d=1: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    lines = ["| mode | processed | released | superseded | T median / p95 (ms) | tracking / mapping median (ms) "
             "| latency median / p95 (ms) | duration (s) | lost | keyframes superseded | worker lag median / max "
             "| map age median / p95 | steps per keyframe | window age median / p95 | ATE (cm) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        lines.append(f"| {r['mode']} | {r['frames_processed']} | {fmt(r['frames_released'])} | "
                     f"{fmt(r['frames_superseded'])} | {fmt(r['tracker_ms_median'], 0)} / {fmt(r['tracker_ms_p95'], 0)} "
                     f"| {fmt(r.get('tracking_ms_median'), 0)} / {fmt(r.get('mapping_ms_median'), 0)} "
                     f"| {fmt(r['latency_ms_median'], 0)} / {fmt(r['latency_ms_p95'], 0)} | {fmt(r['duration_s'])} | "
                     f"{r['lost']} | {fmt(r['keyframes_superseded'])} | {fmt(r['worker_lag_frames_median'])} / {fmt(r['worker_lag_frames_max'])} | "
                     f"{fmt(r['map_age_frames_median'])} / {fmt(r['map_age_frames_p95'])} | "
                     f"{fmt(r.get('iterations_per_keyframe'))} | {fmt(r.get('window_age_frames_median'))} / "
                     f"{fmt(r.get('window_age_frames_p95'))} | {fmt(r['ate_cm'], 2)} |")
    return "\n".join(lines) + "\n"


def note(doc: dict) -> str:
    fmt = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    if doc.get("fixed_rate"):
        return (f"Tracker cost T in async lock-step: {fmt(doc.get('T_lockstep_ms'))} ms; the camera at {doc['rate']:g} "
                f"times the recorded pace, a frame every {fmt(doc['camera_interval_ms'])} ms.")
    return (f"Tracker cost T: {fmt(doc['T_ms'])} ms (async lock-step median {fmt(doc.get('T_lockstep_ms'))} ms); camera "
            f"interval in the last real-time run {fmt(doc['camera_interval_ms'])} ms (rate {doc['rate']:.4f} of the "
            f"recorded pace).")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--interval-factor", type=float, default=1.5, help="camera interval in units of T")
    parser.add_argument("--rate", type=float, help="the live run at this many times the recorded pace instead")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sync = gausem_run(args, Path(tmp) / "sync", ["--set", "worker.mode=sync"])
        lockstep = gausem_run(args, Path(tmp) / "async", ["--set", "worker.mode=async"])
        t_s = lockstep["frame_ms_median"] / 1e3
        rate = args.rate or sync["interval_s"] / (args.interval_factor * t_s)
        live = gausem_run(args, Path(tmp) / "live", ["--realtime", f"{rate:.6f}"])
        rows = [row("sync lock-step", sync), row("async lock-step", lockstep),
                row(f"async --realtime {rate:g}" if args.rate else "async --realtime", live)]
        if not args.rate and live["frame_ms_median"] / 1e3 > 1.1 * t_s:  # slower live: again at its live cost
            factor = f"{args.interval_factor:g}"
            rows[-1]["mode"] += f" at {factor} T lock-step"
            t_s = live["frame_ms_median"] / 1e3
            rate = sync["interval_s"] / (args.interval_factor * t_s)
            again = gausem_run(args, Path(tmp) / "live_again", ["--realtime", f"{rate:.6f}"])
            rows.append(row(f"async --realtime at {factor} T live", again))
    interval_ms = 1e3 * (sync["interval_s"] / rate if args.rate else args.interval_factor * t_s)
    doc = {"dataset": args.dataset, "size": args.size, "T_ms": 1e3 * t_s, "T_lockstep_ms": lockstep["frame_ms_median"],
           "camera_interval_ms": interval_ms, "rate": rate, "fixed_rate": bool(args.rate), "rows": rows}
    results.write_report(results.RESULTS / f"live_replay_{args.name}",
                         title=f"Following a camera: the mapping worker, {results.label(args.dataset)}", what=WHAT,
                         markdown=markdown(doc), notes=[note(doc)], data=doc)


if __name__ == "__main__":
    main()
