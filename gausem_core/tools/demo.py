"""``gausem demo``: the offline end-to-end run on the embedded synthetic sequence (a minute or two on 2 CPU cores).

Takes every ``gausem run`` option, with demo defaults: 30 frames of ``synthetic`` at 160x120 with
``params/synthetic.yaml``, written to ``out/demo``.
"""
from __future__ import annotations

import time
from pathlib import Path

from gausem_core.tools import run

DEMO_FRAMES = 30
DEMO_SIZE = (160, 120)


def add_arguments(parser) -> None:
    run.add_run_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: %(default)s)")
    parser.set_defaults(frames=DEMO_FRAMES, size=DEMO_SIZE)


def main(args) -> int:
    started = time.time()
    metrics = run.run_pipeline(args, args.out)
    from gausem_core.report import format_summary

    print(format_summary(metrics))
    written = sorted(p for p in args.out.iterdir() if p.is_file() and p.stat().st_mtime >= started)
    print(f"\nfiles written to {args.out}/:")
    for path in written:
        print(f"  {path.name:<18} {path.stat().st_size / 1024:8.1f} KiB")
    return 0
