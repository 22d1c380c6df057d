"""``gausem bench``: the benchmark harness ``gausem_bench`` of a source checkout (``benchmarks/gausem_bench``).

The harness is not installed with the library: the command finds it next to the ``gausem_core`` it runs from (an
editable install or ``PYTHONPATH`` pointing at a checkout) or on the Python path, and says so when it cannot.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"  # the checkout's folder holding gausem_bench


def harness():
    """The ``gausem_bench.cli`` module, or None when it is neither in the checkout nor on the Python path."""
    if (BENCHMARKS / "gausem_bench").is_dir() and str(BENCHMARKS) not in sys.path:
        sys.path.append(str(BENCHMARKS))
    try:
        return importlib.import_module("gausem_bench.cli")
    except ModuleNotFoundError as exc:
        if exc.name != "gausem_bench":
            raise
        return None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    cli = harness()
    if cli is None:
        parser.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    else:
        cli.add_arguments(parser)


def main(args: argparse.Namespace) -> int:
    cli = harness()
    if cli is None:
        print(f"gausem bench: the benchmark harness (benchmarks/gausem_bench) comes with a source checkout of GauSem "
              f"and is not installed with the library; none at {BENCHMARKS}. Run `gausem bench` from a checkout "
              "installed with `pip install -e .` (or with the checkout on PYTHONPATH).", file=sys.stderr)
        return 2
    return cli.main(args)
