"""Whole-system speed of two commits, interleaved: for each sequence of a suite, GauSem at BASE, then at HEAD.

The machines behind this repository change speed by 10-20 % within the hour and by up to 2x between days, so a
speed-up is only measured by runs that alternate. BASE is checked out into a temporary worktree (with its own
extension cache, so the two compiled renderers do not rebuild each other); each run is one `gausem bench slam` of
that tree, run inside it (its own params files); HEAD runs from this checkout. Writes
benchmarks/results/speed_ab_<name>.{json,md} (default name: 160x120_<HEAD>, the paper suite's size). Run from the
repository root:
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed_ab.py BASE [--suite S] [--sequences A B] [--name N]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def tree_env(tree: Path, work: Path) -> dict:
    """The environment that runs ``tree``'s code, with its own compiled-renderer cache."""
    return {**os.environ, "PYTHONPATH": str(tree), "TORCH_EXTENSIONS_DIR": str(work / "extensions" / tree.name)}


def bench_run(tree: Path, sequence: str, suite: Path, work: Path, threads: int) -> dict:
    """One GauSem run of ``sequence`` with the code of ``tree``; its `gausem bench slam` record."""
    env = tree_env(tree, work)
    name = f"{tree.name}_{sequence}"
    subprocess.run([sys.executable, "-m", "gausem_core.cli", "bench", "slam", "--suite", str(suite), "--configs",
                    "gausem", "--sequences", sequence, "--threads", str(threads), "--name", name, "--out",
                    str(work), "--work", str(work / "runs"), "--quiet"], cwd=tree, env=env, check=True)
    (record,) = json.loads((work / f"slam_{name}.json").read_text())["runs"]
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", help="the commit to compare HEAD with")
    parser.add_argument("--suite", type=Path, default=Path("benchmarks/suites/paper.yaml"))
    parser.add_argument("--sequences", nargs="+",
                        default=["synthetic_default", "synthetic_loop", "tum_fr1_rpy", "7scenes_redkitchen"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--name", help="results name (default: 160x120_<HEAD short>)")
    args = parser.parse_args()
    base, head = git("rev-parse", args.base), git("rev-parse", "HEAD")
    name = args.name or f"160x120_{head[:7]}"
    rows = []
    with tempfile.TemporaryDirectory(prefix="gausem-ab-") as tmp:
        work = Path(tmp)
        base_tree = work / "base"
        git("worktree", "add", "--detach", str(base_tree), base)
        (work / "shared").symlink_to(ROOT.parent / "shared")  # the suites name their data ../shared/data/...
        try:
            for tree in (base_tree, ROOT):  # compile both renderers before any timed run (`gausem info` builds it)
                subprocess.run([sys.executable, "-m", "gausem_core.cli", "info"], cwd=tree, env=tree_env(tree, work),
                               check=True, capture_output=True)
            for sequence in args.sequences:
                runs = {label: bench_run(tree, sequence, (ROOT / args.suite).resolve(), work, args.threads)
                        for label, tree in (("base", base_tree), ("head", ROOT))}
                rows.append({"sequence": sequence, **{label: {"commit": r["git_commit"], "fps": r["metrics"]["fps"],
                                                               "ate_rmse_cm": r["metrics"]["ate_rmse_cm"],
                                                               "psnr": r["metrics"]["rendering"]["psnr"],
                                                               "device": r["device"]}
                                                      for label, r in runs.items()}})
                print(f"{sequence}: base {rows[-1]['base']['fps']:.2f} fps, head {rows[-1]['head']['fps']:.2f} fps")
        finally:
            git("worktree", "remove", "--force", str(base_tree))
    document = {"base": base, "head": head, "threads": args.threads, "suite": str(args.suite),
                "load_average": os.getloadavg(), "rows": rows}
    OUT.mkdir(exist_ok=True)
    (OUT / f"speed_ab_{name}.json").write_text(json.dumps(document, indent=2) + "\n")
    (OUT / f"speed_ab_{name}.md").write_text(markdown(document))
    print(markdown(document))


def markdown(doc: dict) -> str:
    lines = [f"# Whole-system speed, {doc['base'][:10]} (base) vs {doc['head'][:10]} (head), interleaved", "",
             f"`benchmarks/speed_ab.py` with the GauSem configuration of `{doc['suite']}`, {doc['threads']} threads, "
             f"{doc['rows'][0]['head']['device'] if doc['rows'] else ''}; per sequence the base run, then the head "
             "run. fps as in `gausem bench slam` (frames over the frame loop and the global refinement).", "",
             "| sequence | fps base | fps head | head / base | ATE cm base | ATE cm head | PSNR base | PSNR head |",
             "|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        b, h = r["base"], r["head"]
        lines.append(f"| {r['sequence']} | {b['fps']:.2f} | {h['fps']:.2f} | {h['fps'] / b['fps']:.2f}x | "
                     f"{b['ate_rmse_cm']:.2f} | {h['ate_rmse_cm']:.2f} | {b['psnr']:.2f} | {h['psnr']:.2f} |")
    if doc["rows"]:
        ratio = statistics.median(r["head"]["fps"] / r["base"]["fps"] for r in doc["rows"])
        lines += ["", f"Median speed ratio head / base: {ratio:.2f}x."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
