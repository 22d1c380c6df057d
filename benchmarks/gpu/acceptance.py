"""The results record of ``benchmarks/gpu/acceptance.sh``: each acceptance criterion of the fast-steps work against
what the calls measured (a stage left out or failed reads "not measured").

    .venv/bin/python benchmarks/gpu/acceptance.py FOLDER [--name gpu_acceptance_h200]

FOLDER: what the calls wrote under $OUT (the device tool's files_at), copied into one folder.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gausem_bench import results  # noqa: E402

WHAT = ("`benchmarks/gpu/acceptance.sh` on the GPU machine: `gausem run` at 640x480 on the synthetic loop (360 frames) "
        "in sync mode with the defaults (the fused tracking step) and at the recorded pace (`--realtime 1`), its first "
        "90 frames with the torch tracking step, the same two runs on TUM fr1/rpy where carried; the CUDA tests; the "
        "tracking node fed at 30 Hz by the player in another process. Tracking: the median of a frame's tracking "
        "(health and keyframe decision included); mapping: the median of a keyframe's mapping (a new submap's "
        "opening and loop closure included).")


def metrics(folder: Path, stage: str) -> dict | None:
    path = folder / stage / "metrics.json"
    return json.loads(path.read_text())["metrics"] if path.is_file() else None


def live_line(folder: Path) -> tuple[int, int, float] | None:
    """(processed, sent, ATE cm) from live.sh's report line."""
    path = folder / "live.txt"
    text = path.read_text() if path.is_file() else ""
    found = re.search(r"processed (\d+) of (\d+) frames.*?ATE ([\d.]+) cm", text)
    return None if found is None else (int(found[1]), int(found[2]), float(found[3]))


def tests_line(folder: Path) -> str | None:
    path = folder / "tests.txt"
    if not path.is_file():
        return None
    summary = [line for line in path.read_text().splitlines() if re.search(r"\d+ (passed|failed|error)", line)]
    return summary[-1].strip("= ") if summary else None


def criteria(folder: Path) -> list[tuple[str, str, float | str | None, bool | None]]:
    """(criterion, target, measured, met) rows; measured None where the stage did not run or failed."""
    torch_step, sync, live = metrics(folder, "torch"), metrics(folder, "sync"), metrics(folder, "realtime")
    tum_sync, tum_live = metrics(folder, "tum_sync"), metrics(folder, "tum_realtime")
    get = lambda m, key: None if m is None else m.get(key)  # noqa: E731
    rows = []

    def add(name: str, target: str, value, check=None) -> None:
        rows.append((name, target, value, None if value is None or check is None else bool(check(value))))

    tests = tests_line(folder)
    add("CUDA tests", "all pass", tests, lambda t: "failed" not in t and "error" not in t)
    add("tracking a frame, torch step (ms)", "reference", get(torch_step, "tracking_ms_median"))
    add("tracking a frame (ms)", "<= 15", get(sync, "tracking_ms_median"), lambda v: v <= 15)
    add("mapping a keyframe (ms)", "<= 150", get(sync, "mapping_ms_median"), lambda v: v <= 150)
    add("sync fps, synthetic loop", ">= 10", get(sync, "fps"), lambda v: v >= 10)
    add("sync fps, TUM fr1/rpy", ">= 10", get(tum_sync, "fps"), lambda v: v >= 10)
    for name, real, lockstep in (("synthetic loop", live, sync), ("TUM fr1/rpy", tum_live, tum_sync)):
        share = None if real is None else real["live"]["frames_processed"] / real["live"]["frames_released"]
        add(f"--realtime 1 frames processed, {name}", ">= 0.9", share, lambda v: v >= 0.9)
        ratio = None if real is None or lockstep is None else real["ate_rmse_cm"] / lockstep["ate_rmse_cm"]
        add(f"--realtime 1 ATE / sync ATE, {name}", "<= 1.3", ratio, lambda v: v <= 1.3)
    node = live_line(folder)
    add("live node at 30 Hz: frames processed", ">= 0.9", None if node is None else node[0] / node[1],
        lambda v: v >= 0.9)
    add("live node at 30 Hz: ATE (cm)", "<= 2", None if node is None else node[2], lambda v: v <= 2)
    for stage, m in (("torch step", torch_step), ("defaults", sync)):
        add(f"Gaussians at the end, synthetic loop, {stage}", "reported", get(m, "num_gaussians"))
    return rows


def markdown(rows) -> str:
    def cell(value) -> str:
        if value is None:
            return "not measured"
        return f"{value:.3g}" if isinstance(value, float) else str(value)

    lines = ["| criterion | target | measured | met |", "|---|---|---|---|"]
    lines += [f"| {name} | {target} | {cell(value)} | {'-' if met is None else ('yes' if met else 'no')} |"
              for name, target, value, met in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path, help="what acceptance.sh wrote under $OUT")
    parser.add_argument("--name", default="gpu_acceptance", help="results file name (in benchmarks/results)")
    args = parser.parse_args(argv)
    rows = criteria(args.folder)
    read = lambda name: (args.folder / name).read_text().strip() if (args.folder / name).is_file() else None  # noqa
    results.write_report(results.RESULTS / args.name, title="Fast steps on a GPU: the acceptance checks", what=WHAT,
                         markdown=markdown(rows), data={"rows": rows},
                         command="bash benchmarks/gpu/acceptance.sh (device tool); "
                                 f"python benchmarks/gpu/acceptance.py FOLDER --name {args.name}",
                         machine=read("machine.txt"), commit=read("commit.txt"),
                         date=read("date.txt"))


if __name__ == "__main__":
    main()
