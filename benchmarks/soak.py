"""Soak: the node suite fed a looping source at the camera's pace for half an hour; does anything grow or break?

Runs ``gausem-launch`` (each node its own process; the player ``--loop``-ing a bag of SOURCE at ``--rate`` 1,
160x120; the tracking node on the CPU in its live defaults, ``worker.mode`` async) for ``--minutes``, and every
``--sample-every`` seconds samples each process's resident set, threads and open files (``/proc/PID/status``,
``/proc/PID/fd``) and the tracking node's input accounting from its ``gausem/diagnostics`` (frames in, processed,
dropped, pending), read by a listener in this process. The node changes and reads them under one lock, so every
message should add up: the record counts the messages that do not (naming the first). Then SIGINT to the launcher,
which stops its children (what is left after ``--grace`` s is killed). A process that dies ends the soak early, as a
failure. Writes the record ``benchmarks/results/<name>.json`` (the samples; the RSS growth over the last 20 minutes,
whether frames in = processed + dropped + pending at every sample, the exceptions and errors in the nodes' log, the
dead processes), the curves in ``benchmarks/results/<name>.png`` and the log in ``out/<name>.log``. Issue 63's
acceptance (exit code 1 when not met): at most 10 % RSS growth over the last 20 minutes, the counts add up, no
exception.

The default source is the synthetic loop (360 frames, 12 s a pass, with labels): its labels let the semantic submap
policy open and close submaps, which spill to disk beyond ``submaps.memory_budget_mb`` as in a long session (TUM
fr1/rpy without labels keeps one submap, ``params/tum.yaml``), and it needs no shared data. A TUM pass is closer to
a real camera: ``--source tum:PATH --params params/tum.yaml -- -p use_labels:=false``. A dataset is first written
to a bag (in a temporary folder), which the player reads as a driver hands frames over: rendering the synthetic room
costs 26 ms a frame, and a player doing so beside the node on a 2-core machine sent 11 frames a second, not 30.

    python benchmarks/soak.py [--minutes 30] [--sample-every 60] [--source synthetic:loop] [--name NAME] [-- ROS_ARGS]
"""
from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm import tqdm

from gausem_bench import results
from gausem_bench.launch import (DiagnosticsListener, add_launch_arguments, adds_up, children, launch_command,
                                 local_domain, log_file, parse_launch_arguments, process_stats, scan_log, source_bag,
                                 start_launcher, stop)
from gausem_ros.preflight import TRACKING_NODE

REPO = Path(__file__).resolve().parents[1]
GROWTH_WINDOW_S = 20 * 60  # the RSS growth is measured over the last 20 minutes (the run's, when shorter)
MAX_GROWTH_PCT = 10.0
WHAT = ("`benchmarks/soak.py`: `gausem-launch` with the player looping a bag of the source at the recorded pace (CPU, "
        "160x120, the tracking node's live defaults), each process's resident set, threads and open files and the "
        "tracking node's input accounting (`gausem/diagnostics`) sampled at the given interval.")
COUNT_KEYS = ("frames_in", "frames_processed", "dropped", "frames_pending")


def rss_growth(samples: list[dict], process: str = TRACKING_NODE) -> dict | None:
    """RSS growth of ``process`` from the first sample of the last ``GROWTH_WINDOW_S`` to the last sample."""
    rows = [(s["t_s"], s["processes"][process]["rss_mb"]) for s in samples if s["processes"].get(process)]
    if len(rows) < 2:
        return None
    start = next((t, rss) for t, rss in rows if t >= rows[-1][0] - GROWTH_WINDOW_S)
    return {"from_s": start[0], "to_s": rows[-1][0], "from_mb": start[1], "to_mb": rows[-1][1],
            "peak_mb": max(rss for t, rss in rows if t >= start[0]),
            "growth_pct": round(100 * (rows[-1][1] - start[1]) / start[1], 2)}


def plot(path: Path, samples: list[dict], title: str) -> None:
    """RSS, threads, open files of every process and the frame counts against time."""
    figure = Figure(figsize=(12, 8), dpi=100)
    FigureCanvasAgg(figure)
    minutes = [s["t_s"] / 60 for s in samples]
    names = sorted({name for s in samples for name in s["processes"]})
    for k, (key, label) in enumerate((("rss_mb", "resident set (MB)"), ("threads", "threads"),
                                      ("files", "open files"))):
        ax = figure.add_subplot(2, 2, k + 1)
        for name in names:
            ax.plot(minutes, [(s["processes"].get(name) or {}).get(key) for s in samples], ".-", label=name)
        ax.set(xlabel="minutes", ylabel=label, title=label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    ax = figure.add_subplot(2, 2, 4)
    for key in COUNT_KEYS:
        ax.plot(minutes, [(s["counts"] or {}).get(key) for s in samples], ".-", label=key.replace("_", " "))
    ax.set(xlabel="minutes", ylabel="frames", title=f"{TRACKING_NODE}: frames")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path, format="png")


def soak(args, bag: str, ros_args: list[str], log_path: Path) -> dict:
    """Run the launcher playing ``bag`` for ``args.minutes``, sampling; the samples, the dead processes and how it
    ended."""
    domain = local_domain(71)
    listener = DiagnosticsListener(domain)
    samples, dead, ended = [], [], "ran its time"
    duration = 60 * args.minutes
    launcher = start_launcher(launch_command(args, bag, ros_args), log_path)
    start, pids = time.monotonic(), {}
    bar = tqdm(total=round(duration), unit="s", desc="soak")
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        next_sample = args.sample_every
        while True:
            listener.spin(1.0)
            now = time.monotonic() - start
            found = children(launcher.pid)
            pids.update({name: pid for name, pid in found.items() if name not in pids})
            dead = [name for name, pid in pids.items() if found.get(name) != pid]
            if now >= next_sample or now >= duration or dead or launcher.poll() is not None:
                stats = {name: process_stats(pid) for name, pid in {"launcher": launcher.pid, **pids}.items()}
                samples.append({"t_s": round(now, 1), "processes": stats, "counts": listener.latest,
                                "dropped_by_reason": listener.dropped,
                                "diagnostics_age_s": round(time.monotonic() - listener.received_at, 1)
                                if listener.latest else None})
                next_sample = (now // args.sample_every + 1) * args.sample_every
                tracking = stats.get(TRACKING_NODE) or {}
                bar.set_postfix(rss_mb=tracking.get("rss_mb"), processed=(listener.latest or {}).get(
                    "frames_processed"), refresh=False)
            bar.update(min(round(now), bar.total) - bar.n)
            if dead or launcher.poll() is not None:
                ended = f"stopped early: {', '.join(dead) or 'the launcher'} ended after {now:.0f} s"
                break
            if now >= duration:
                break
    except KeyboardInterrupt:
        ended = f"interrupted after {time.monotonic() - start:.0f} s"
    finally:
        signal.signal(signal.SIGTERM, previous)
        bar.close()
        killed = stop(launcher, args.grace + 15)
        listener.close()
    return {"samples": samples, "dead": dead, "ended": ended, "killed": killed,
            "launcher_exit_code": launcher.returncode, "diagnostics_messages": listener.messages,
            "diagnostics_mismatches": listener.mismatches, "first_mismatch": listener.first_mismatch,
            "domain": domain}


def sample_table(samples: list[dict]) -> dict:
    """The tracking node's resident set, threads, open files and input accounting at each sample."""
    rows = []
    for s in samples:
        tracking, c = s["processes"].get(TRACKING_NODE) or {}, s["counts"] or {}
        rows.append([round(s["t_s"] / 60, 2), *(tracking.get(k) for k in ("rss_mb", "threads", "files")),
                     *(c.get(k) for k in COUNT_KEYS), ("yes" if adds_up(c) else "NO") if c else None])
    return results.table(["min", "RSS (MB)", "threads", "open files", "frames in", "processed", "dropped", "pending",
                          "adds up"], rows, title=TRACKING_NODE)


def others_table(samples: list[dict]) -> dict:
    """The other processes' resident set, threads and open files at each sample."""
    others = sorted({name for s in samples for name in s["processes"]} - {TRACKING_NODE})

    def cell(stats: dict | None) -> str:
        return "gone" if stats is None else f"{stats['rss_mb']} / {stats['threads']} / {stats['files']}"
    return results.table(["min", *(f"{name}: RSS MB / threads / files" for name in others)],
                         [[round(s["t_s"] / 60, 2), *(cell(s["processes"].get(n)) for n in others)] for s in samples],
                         title="The other processes")


def summarise(run: dict, log: dict) -> dict:
    """The acceptance figures: RSS growth, whether the counts added up at every sample, exceptions (logged
    tracebacks and inputs dropped as ``processing_error``), errors and dead processes; ``passed`` when the run lasted
    and met issue 63's criteria."""
    counted = [s["counts"] for s in run["samples"] if s["counts"]]
    dropped = run["samples"][-1]["dropped_by_reason"] if run["samples"] else {}
    growth = rss_growth(run["samples"])
    summary = {"ended": run["ended"], "rss_growth": growth,
               "counts_add_up": bool(counted) and all(map(adds_up, counted)),
               "samples_adding_up": f"{sum(map(adds_up, counted))} of {len(counted)}",
               "exceptions": log["exceptions"], "processing_errors": dropped.get("processing_error", 0),
               "dropped_by_reason": dropped, "errors": log["errors"][:20], "errors_total": len(log["errors"]),
               "dead": run["dead"], "launcher_reports": log["launcher"], "killed_at_shutdown": run["killed"],
               "launcher_exit_code": run["launcher_exit_code"]}
    summary["passed"] = (run["ended"] == "ran its time" and growth is not None
                         and growth["growth_pct"] <= MAX_GROWTH_PCT and summary["counts_add_up"]
                         and not log["exceptions"] and not summary["processing_errors"] and not run["dead"])
    return summary


def notes(run: dict, summary: dict, png: str) -> list[str]:
    growth = summary["rss_growth"]
    lines = [f"The soak {summary['ended']}; acceptance (issue 63): {'passed' if summary['passed'] else 'FAILED'}."]
    if growth:
        lines.append(f"{TRACKING_NODE} RSS from {growth['from_mb']} MB at {growth['from_s'] / 60:.1f} min to "
                     f"{growth['to_mb']} MB at {growth['to_s'] / 60:.1f} min: {growth['growth_pct']:+.1f} % "
                     f"(peak {growth['peak_mb']} MB; at most {MAX_GROWTH_PCT:g} % over the last "
                     f"{GROWTH_WINDOW_S // 60} minutes).")
    ages = [s["diagnostics_age_s"] for s in run["samples"] if s["diagnostics_age_s"] is not None]
    lines.append(f"Frames in = processed + dropped + pending at {summary['samples_adding_up']} samples and in "
                 f"{run['diagnostics_messages'] - run['diagnostics_mismatches']} of {run['diagnostics_messages']} "
                 "diagnostics messages" + (f" (first mismatch: {run['first_mismatch']})" if run["first_mismatch"]
                                           else "") + f"; the newest was at most {max(ages, default=0)} s old at a "
                 "sample.")
    reasons = ", ".join(f"{k} {v}" for k, v in summary["dropped_by_reason"].items()) or "none"
    lines.append(f"Dropped by reason at the end: {reasons}.")
    lines.append(f"Exceptions in the nodes' log: {'; '.join(summary['exceptions']) or 'none'}; inputs dropped as "
                 f"processing_error: {summary['processing_errors']}; error lines: "
                 f"{summary['errors_total']}; processes that died: {', '.join(summary['dead']) or 'none'}"
                 + (f"; killed at shutdown: {', '.join(summary['killed_at_shutdown'])}"
                    if summary["killed_at_shutdown"] else "") + ".")
    lines.append(f"Curves: `{png}`.")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="how long to run (default %(default)s)")
    parser.add_argument("--sample-every", type=float, default=60.0, help="seconds between samples")
    add_launch_arguments(parser, "soak_synthetic_loop_160x120")
    args, ros_args = parse_launch_arguments(parser, sys.argv[1:])
    log_path = log_file(args.name)
    with tempfile.TemporaryDirectory() as tmp:
        bag = source_bag(args.source, args.size, tmp)
        run = soak(args, bag, ros_args, log_path)
    summary = summarise(run, scan_log(log_path.read_text(errors="replace")))
    png = results.RESULTS / f"{args.name}.png"
    title = f"Soak: {results.label(args.source)} looped for {args.minutes:g} minutes, {args.size}"
    plot(png, run["samples"], title)
    doc = {"source": args.source, "size": args.size, "rate": args.rate, "minutes": args.minutes,
           "sample_every_s": args.sample_every, "params_file": str(args.params), "nodes": args.nodes,
           "device": args.device, "ros_args": ros_args, "summary": summary, **run}
    results.write(results.RESULTS / args.name, results.record(
        title=title, what=WHAT, table=sample_table(run["samples"]), tables=[others_table(run["samples"])],
        notes=notes(run, summary, str(png.relative_to(REPO))), data=doc))
    print("\n".join(notes(run, summary, str(png))) + f"\nlog: {log_path}")
    return 0 if summary["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
