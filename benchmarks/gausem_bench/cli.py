"""``python benchmarks/bench.py <target>``: benchmarks written as JSON records (:mod:`gausem_bench.results`), one
module per target.

``render`` (:mod:`gausem_bench.render`): renderer timing and memory. ``slam`` (:mod:`gausem_bench.slam`): the offline
pipeline and the Open3D baselines over sequences x configurations. ``report`` (:mod:`gausem_bench.report`): the
results page from the records. Each target module exposes
``add_arguments(parser)`` and ``main(args)``; it is imported when the parser is built.
"""
from __future__ import annotations

import argparse
import importlib

TARGETS = {
    "render": ("gausem_bench.render", "renderer forward/backward time and peak memory"),
    "slam": ("gausem_bench.slam", "the offline pipeline and baselines over a suite (the paper's tables)"),
    "report": ("gausem_bench.report", "write docs/BENCHMARKS.md from the records in benchmarks/results"),
}


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="target", required=True, metavar="TARGET")
    for name, (module, help_text) in TARGETS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_bench_module=module)
        importlib.import_module(module).add_arguments(p)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks/bench.py", description="GauSem's benchmarks, written as JSON "
                                     "records in benchmarks/results; `report` writes docs/BENCHMARKS.md from them")
    add_arguments(parser)
    args = parser.parse_args(argv)
    return int(importlib.import_module(args._bench_module).main(args) or 0)
