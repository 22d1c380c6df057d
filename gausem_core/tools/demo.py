"""``gausem demo``: the most end-to-end run the project can do (grows with the project)."""
from __future__ import annotations

from pathlib import Path

from gausem_core.tools import info


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: %(default)s)")


def main(args) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    return info.main(args)
