"""``gausem run``: the offline SLAM pipeline on a dataset, writing trajectory, metrics, montage and map."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from gausem_core.config import SlamConfig, from_flat, load_config
from gausem_core.options import DATASET_HELP, default_params_file, parse_override, parse_size
from gausem_core.viewer import COLORINGS, MODES, RECORDING


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by every command that runs the pipeline."""
    parser.add_argument("--dataset", default="synthetic", help=f"{DATASET_HELP} (default: %(default)s)")
    parser.add_argument("--params", type=Path, help="ROS-format parameter YAML (default: params/<dataset kind>.yaml)")
    parser.add_argument("--set", dest="overrides", type=parse_override, action="append", default=[],
                        metavar="NAME=VALUE", help="override one parameter, e.g. --set mapping.iterations=20")
    parser.add_argument("--frames", type=int, help="process at most this many frames")
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame (default: 1)")
    parser.add_argument("--start", type=int, default=0, help="first frame of the sequence (default: 0)")
    parser.add_argument("--size", type=parse_size, help="resize input to WxH, e.g. 160x120")
    parser.add_argument("--eval-every", type=int, default=5, help="evaluate rendering on every n-th frame")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--resume", type=Path, metavar="FOLDER",
                        help="go on with the session saved in FOLDER, with its parameters (--set still applies); "
                             "the first frame is relocalised against its map")
    parser.add_argument("--save-session", type=Path, metavar="FOLDER",
                        help="save the session into FOLDER after the last frame (before the global refinement)")
    parser.add_argument("--realtime", type=float, metavar="RATE",
                        help="play the frames as a live camera at RATE times their recorded pace (1: as recorded), "
                             "processing the newest each time and skipping the rest; the mapping runs on its own "
                             "thread (worker.mode async) unless --set worker.mode=sync")
    parser.add_argument("--viewer", nargs="?", const="record", choices=MODES,
                        help="a live 3D view in Rerun (needs rerun-sdk): record (what --viewer alone means) saves "
                             "the recording, web also serves it to a browser (and after the run, until Ctrl-C), "
                             "native opens the desktop viewer")
    parser.add_argument("--viewer-out", type=Path, metavar="FILE", help=f"the recording (default: OUT/{RECORDING})")
    parser.add_argument("--viewer-colors", choices=COLORINGS, default="rgb",
                        help="the map's points coloured by their RGB or their class (default: %(default)s)")
    parser.add_argument("--viewer-map-every", type=int, default=10, metavar="N",
                        help="log the map every N frames (default: %(default)s)")
    parser.add_argument("--viewer-port", type=int, default=9090, metavar="PORT",
                        help="the web viewer's port (default: %(default)s)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("out/run"), help="output folder (default: %(default)s)")


def session_config(folder: Path, overrides: dict) -> SlamConfig:
    """The parameters of the session saved in ``folder`` with dotted-name ``overrides`` on top."""
    from gausem_core.slam.persistence import read_document, saved_config

    return from_flat(overrides, saved_config(read_document(folder)))


def live_defaults(args: argparse.Namespace) -> dict:
    """The ``--set`` overrides, with ``worker.mode: async`` first under ``--realtime`` (a live run's default)."""
    live = {"worker.mode": "async"} if getattr(args, "realtime", None) is not None else {}
    return {**live, **dict(args.overrides)}


def run_pipeline(args: argparse.Namespace, out: Path) -> dict:
    """Open the dataset, run the pipeline, write the outputs; returns the metrics."""
    from gausem_core.data import open_dataset
    from gausem_core.pipeline import Pipeline
    from gausem_core.report import write_outputs
    from gausem_core.slam.system import GauSemSLAM

    if args.resume is not None and args.params is not None:
        raise ValueError("--resume goes on with the session's parameters; --params cannot change them (--set can)")
    if args.resume is None:
        params = args.params or default_params_file(args.dataset)
        cfg = load_config(params, live_defaults(args))
    else:
        params, cfg = None, session_config(args.resume, live_defaults(args))
    dataset = open_dataset(args.dataset, size=args.size, stride=args.stride, max_frames=args.frames,
                           start=args.start)
    if getattr(dataset, "description", None):
        print(dataset.description)  # where intrinsics and labels came from, what was assumed
    pipeline = Pipeline(dataset, cfg, progress=not args.quiet)
    if pipeline.semantics.notice:
        print(pipeline.semantics.notice)
    slam = GauSemSLAM.load(args.resume, pipeline.device, cfg) if args.resume else None
    viewer = open_viewer(args, out, pipeline) if args.viewer else None
    try:
        result = pipeline.run(slam, args.save_session, getattr(args, "realtime", None), viewer)
        metrics = write_outputs(result, dataset, cfg, out, eval_every=args.eval_every, params_file=params)
        if viewer is not None and viewer.url:
            serve_until_interrupted(viewer, out)
    finally:
        if viewer is not None:
            viewer.close()
    return metrics


def open_viewer(args: argparse.Namespace, out: Path, pipeline):
    """The run's :class:`~gausem_core.viewer.Viewer` (``--viewer``), saying where to watch it."""
    from gausem_core.viewer import Viewer

    table = pipeline.semantics.class_table
    viewer = Viewer(args.viewer_out or out / RECORDING, pipeline.palette, table.names if table else None,
                    args.viewer, args.viewer_colors, args.viewer_map_every, web_port=args.viewer_port)
    print(f"viewer: recording to {viewer.path} (reopen it with `rerun {viewer.path}`)"
          + (f"; web viewer at {viewer.url}" if viewer.url else ""), flush=True)
    return viewer


def serve_until_interrupted(viewer, out: Path) -> None:
    """``--viewer web``: go on serving the finished run until Ctrl-C."""
    print(f"outputs written to {out}/; serving the web viewer at {viewer.url} until Ctrl-C", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def main(args: argparse.Namespace) -> int:
    metrics = run_pipeline(args, args.out)
    from gausem_core.report import format_summary

    print(format_summary(metrics))
    print(f"outputs written to {args.out}/")
    return 0
