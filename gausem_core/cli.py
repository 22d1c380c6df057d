"""The ``gausem`` command line: one sub-command per module, each module exposing ``add_arguments`` and ``main``."""
from __future__ import annotations

import argparse
import importlib
import sys

# sub-command -> (module, one-line help). Modules are imported only when their command runs.
COMMANDS = {
    "info": ("gausem_core.tools.info", "show versions and which optional back-ends are usable"),
    "demo": ("gausem_core.tools.demo", "run the end-to-end demo on the embedded synthetic sequence"),
    "run": ("gausem_core.tools.run", "run the offline SLAM pipeline on a dataset and write its outputs"),
    "train-head": ("gausem_core.tools.train_head", "train the linear segmentation head on DINOv2 patch tokens"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every sub-command, with the arguments of ``command`` only: its module alone is imported (the
    slowest take seconds to import)."""
    parser = argparse.ArgumentParser(prog="gausem", description="GauSem: semantic Gaussian-splatting RGB-D SLAM.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name == command:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((arg for arg in argv if not arg.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    return int(importlib.import_module(args._module).main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
