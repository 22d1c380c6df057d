"""``python benchmarks/bench.py TARGET ...``: the benchmark harness (``gausem_bench``) of a source checkout, run from
the repository root. The installed library does not know the harness; the harness imports the library."""
import sys

from gausem_bench.cli import main

if __name__ == "__main__":
    sys.exit(main())
