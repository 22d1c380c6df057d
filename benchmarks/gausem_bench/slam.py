"""``python benchmarks/bench.py slam``: GauSem's offline pipeline and the Open3D baselines over sequences x configurations.

Sequences and configurations come from a suite file (:mod:`gausem_bench.suite`, default
``benchmarks/suites/paper.yaml``) or from ``--dataset``. Each run executes in a fresh process, so peak memory is per
run. Results: the record ``<out>/slam_<name>.json`` (:mod:`gausem_bench.results`: the paper-shaped tables, every
run's record in its data), rewritten after each run; each run's own outputs (trajectories, map, montage, metrics.json) go to
``<work>/<name>/<sequence>/<configuration>/``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import shlex
import signal
import sys
from datetime import datetime, timezone
from pathlib import Path

import torch

from gausem_bench import results
from gausem_bench.baselines import BASELINES
from gausem_bench.suite import (Case, Configuration, Suite, SuiteError, load_suite, plan, sequence_from_dict)
from gausem_bench.tables import markdown_report
from gausem_core.options import DATASET_HELP, parse_override, parse_size

DEFAULT_SUITE = Path("benchmarks/suites/paper.yaml")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--suite", type=Path, help=f"suite YAML (default: {DEFAULT_SUITE}, or none with --dataset)")
    parser.add_argument("--dataset", action="append", metavar="SPEC",
                        help=f"run on this dataset instead of the suite's sequences (repeatable): {DATASET_HELP}")
    parser.add_argument("--sequences", nargs="+", metavar="NAME", help="only these sequences of the suite")
    parser.add_argument("--configs", nargs="+", metavar="NAME", help="only these configurations of the suite")
    parser.add_argument("--baselines", action="store_true", help="add the Open3D baselines to the configurations")
    parser.add_argument("--size", type=parse_size, help="resize every sequence to WxH, e.g. 160x120")
    parser.add_argument("--stride", type=int, help="use every n-th frame of every sequence")
    parser.add_argument("--frames", type=int, help="at most this many frames of every sequence")
    parser.add_argument("--eval-every", type=int, help="evaluate rendering on every n-th frame")
    parser.add_argument("--set", dest="overrides", type=parse_override, action="append", default=[],
                        metavar="NAME=VALUE", help="GauSem parameter on top of every GauSem configuration")
    parser.add_argument("--lpips-weights", type=Path, help="torch.export-ed LPIPS program (.pt2) for the LPIPS column")
    parser.add_argument("--threads", type=int, help="torch threads per run (default: torch's)")
    parser.add_argument("--name", help="results name (default: the suite's name, or 'cli' with --dataset)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="results folder (%(default)s)")
    parser.add_argument("--work", type=Path, default=Path("out/bench"), help="runs' outputs folder (%(default)s)")
    parser.add_argument("--dry-run", action="store_true", help="list the runs (and check every name), run nothing")
    parser.add_argument("--quiet", action="store_true", help="no per-frame progress bars")


def build_suite(args: argparse.Namespace) -> Suite:
    """The suite the arguments describe: file or ``--dataset``, plus ``--baselines``, filters and per-sequence flags."""
    if args.suite or not args.dataset:
        suite = load_suite(args.suite or DEFAULT_SUITE)
    else:
        suite = Suite("cli", [], [Configuration("gausem")])
    sequences = [sequence_from_dict({"dataset": spec}) for spec in args.dataset] if args.dataset else suite.sequences
    configurations = list(suite.configurations)
    if args.baselines:
        present = {c.method for c in configurations}
        configurations += [Configuration(method, method) for method in BASELINES if method not in present]
    given = {"size": args.size, "stride": args.stride, "frames": args.frames, "eval_every": args.eval_every}
    given = {key: value for key, value in given.items() if value is not None}
    for key, value in given.items():
        if key != "size" and value < 1:
            raise SuiteError(f"--{key.replace('_', '-')} must be >= 1, got {value}")
    sequences = [dataclasses.replace(s, **given) for s in sequences]
    return Suite(args.name or suite.name, sequences, configurations).select(args.sequences, args.configs)


def run_in_fresh_process(case: Case) -> dict:
    """``worker.run_case`` in a new interpreter (spawn). A process that dies is recorded as a failed run; one still
    running when this one is interrupted (Ctrl-C, or SIGTERM under :func:`main`) is terminated with it."""
    from gausem_bench import worker
    from gausem_core.io.metrics import to_jsonable

    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=worker.send_run_case, args=(case, send))
    process.start()
    send.close()  # the child holds the sending end: its death ends recv() with EOFError
    try:
        return receive.recv()
    except EOFError:
        process.join()
        return to_jsonable({**worker.describe(case), "status": "failed",
                            "error": f"the run's process died (exit code {process.exitcode}); out of memory?"})
    finally:
        receive.close()
        process.join(timeout=5)
        if process.is_alive():
            process.terminate()
            process.join()


def _exit_on_sigterm(signum, frame) -> None:
    raise SystemExit(128 + signum)  # unwinds through run_in_fresh_process, which terminates the running child


def listing(cases: list[Case]) -> str:
    lines = []
    for i, c in enumerate(cases, 1):
        s = c.sequence
        size = "x".join(map(str, s.size)) if s.size else "native size"
        notes = [f"{k}={v}" for k, v in c.overrides.items()]
        if s.color_calibration:
            notes.append("colour resampled into the depth camera")
        elif not c.depth_registered:
            notes.append("depth NOT registered to colour (used as if aligned)")
        lines.append(f"[{i}/{len(cases)}] {c.label}: {c.method} on {s.dataset} ({c.frames} frames, {size}, "
                     f"stride {s.stride}), seed {c.seed}{''.join(', ' + n for n in notes)} -> {c.out_dir}")
    return "\n".join(lines)


def summary(record: dict) -> str:
    if record["status"] != "ok":
        return f"FAILED: {record.get('error')}"
    m = record["metrics"]
    parts = [f"ATE {m['ate_rmse_cm']:.2f} cm" if m.get("ate_rmse_cm") is not None else "ATE n/a"]
    rendering = m.get("rendering") or {}
    if rendering.get("psnr") is not None:
        parts.append(f"PSNR {rendering['psnr']:.2f} dB")
    parts += [f"{m['fps']:.2f} fps", f"peak {m['peak_rss_mb']:.0f} MB", f"{record['wall_seconds']:.0f} s"]
    return ", ".join(parts)


def command_line(args: argparse.Namespace) -> str:
    """The ``python benchmarks/bench.py slam`` command that repeats this one (every option spelt out)."""
    words = ["python", "benchmarks/bench.py", "slam"]
    for key, value in vars(args).items():
        flag = "--" + key.replace("_", "-")
        if key.startswith("_") or key in ("command", "target") or value in (None, False, []):
            continue
        if key == "overrides":
            words += [w for name, v in value for w in ("--set", f"{name}={v if isinstance(v, str) else json.dumps(v)}")]
        elif key == "dataset":
            words += [w for spec in value for w in (flag, spec)]
        elif key == "size":
            words += [flag, f"{value[0]}x{value[1]}"]
        elif isinstance(value, list):
            words += [flag, *value]
        else:
            words += [flag] if value is True else [flag, str(value)]
    return shlex.join(words)


WHAT = ("`python benchmarks/bench.py slam`: GauSem's offline pipeline and the Open3D baselines over a suite's sequences "
        "x configurations, each run in a fresh process. fps = processed frames / wall time of the frame loop (reading "
        "frames included, evaluation and export excluded); peak CPU = maximum resident set of the run's own process; "
        "peak GPU = CUDA allocator peak (GauSem).")


def write_results(out: Path, name: str, document: dict) -> Path:
    """The suite's results record ``slam_<name>.json``: the paper-shaped tables (the per-run provenance stays in the
    record's data, with every run's parameters)."""
    env = document["environment"]
    report = markdown_report(document["runs"], f"`python benchmarks/bench.py slam`: {name}")
    tables = [t for t in results.markdown_tables(report) if t["title"] != "Runs"]
    machine = (f"{env['device_name']}, {os.cpu_count()} cores ({env['threads']} torch threads, "
               f"OMP_NUM_THREADS={env['omp_num_threads']})")
    data = {k: v for k, v in document.items() if k not in ("command", "created")}
    return results.write(out / f"slam_{name}.json", results.record(
        title=f"Suite {name}", what=WHAT, table=tables[0], tables=tables[1:],
        notes=[line for line in report.splitlines() if line.startswith(("†", "‡"))], command=document["command"],
        machine=machine, date=document["created"], data=data))


def main(args: argparse.Namespace) -> int:
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        return _run_suite(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_suite(args: argparse.Namespace) -> int:
    from gausem_bench.render import environment

    try:
        suite = build_suite(args)
        cases = plan(suite, args.work / suite.name, overrides=dict(args.overrides),
                     lpips_weights=str(args.lpips_weights) if args.lpips_weights else None, threads=args.threads,
                     progress=not args.quiet)
    except SuiteError as exc:
        print(f"python benchmarks/bench.py slam: error: {exc}", file=sys.stderr)
        return 2
    print(listing(cases), flush=True)
    if args.dry_run:
        print(f"{len(cases)} runs planned (dry run: nothing was run)")
        return 0
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    document = {"suite": suite.name, "suite_file": str(args.suite) if args.suite else None,
                "command": command_line(args),
                "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "environment": {**environment(device), "omp_num_threads": os.environ.get("OMP_NUM_THREADS")},
                "runs": []}
    for i, case in enumerate(cases, 1):
        print(f"[{i}/{len(cases)}] {case.label} ({case.method}, {case.frames} frames)", flush=True)
        record = run_in_fresh_process(case)
        document["runs"].append(record)
        print(f"[{i}/{len(cases)}] {case.label}: {summary(record)}", flush=True)
        write_results(args.out, suite.name, document)
    return 0 if all(r["status"] == "ok" for r in document["runs"]) else 1
