"""All GauSem nodes in one process (entry point ``gausem-ros``), optionally with the player:
``gausem-ros [SOURCE --lockstep ...] [--save DIR] [--report DIR] --ros-args --params-file FILE``.

One multi-threaded executor runs every node: each node's callbacks stay serialised in its own callback groups, but
the player, the tracker's inputs and its processing never wait for each other, so a real-time player is not starved
by a slow frame and the tracker always sees the newest frame.

Which nodes: tracking_mapping always; segmentation unless ``semantics.segmenter`` is ``labels`` (then the labels come
with the data); loop_detection and pose_graph when ``loop.enabled`` and tracking_mapping's
``loop_closure`` is ``nodes`` (by default, ``core``, the tracking node closes loops itself, as ``gausem run``). The ROS arguments
(params file, ``-p``, remappings) apply to every node. With a SOURCE the process ends when the player is done (after
``--save`` and ``--report``); without, it runs until Ctrl-C. On Ctrl-C or SIGTERM the frame in progress is
finished, ``--save`` still writes the map, and the input accounting (frames in, processed, dropped by reason,
latency) is logged. ``--report DIR`` evaluates the run like ``gausem run`` (ATE, PSNR, SSIM, mIoU, fps; trajectories,
map, metrics JSON, montage in DIR; the input accounting in ``input.json``) against a reference dataset: SOURCE when
it is a dataset, else ``--reference SPEC`` (for a bag from ``gausem-bag SPEC``: the same SPEC; opened at the
processed image size). A replay that cannot work stops at once: when ``UNWORKABLE_AFTER`` frames were dropped
because an input never arrived (labels, depth, camera_info) and none was processed, ``gausem-ros`` exits with code 2
and names the topic and the fix.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.utilities import remove_ros_args
from tqdm import tqdm

from gausem_core.data import open_dataset
from gausem_core.report import format_summary

from .evaluation import write_report
from .executor import NodeExecutor, exit_now
from .nodes.common import ros_process
from .nodes.loop_detection import LoopDetectionNode
from .nodes.pose_graph import PoseGraphNode
from .nodes.segmentation import SegmentationNode
from .nodes.tracking.frame_input import NO_LABELS_FIX
from .nodes.tracking.parameters import LOCKSTEP_DEFAULTS
from .nodes.tracking_mapping import TrackingMappingNode
from .player import add_player_arguments, is_bag, player_from_args


UNWORKABLE_AFTER = 5  # frames dropped for an input that never arrived, none processed: the replay cannot work
NEVER_ARRIVED = {
    "no_labels": NO_LABELS_FIX,
    "no_depth": "depth/image never arrived: a bag that records depth under another topic replays it with "
                "--topic depth=TOPIC",
    "no_camera_info": "rgb/camera_info never arrived: a bag that records it under another topic replays it with "
                      "--topic camera_info=TOPIC",
}


def unworkable(tracking: TrackingMappingNode) -> str | None:
    """Why the replay cannot work (an input that never arrived, :data:`NEVER_ARRIVED`), or None while it can."""
    if tracking.frames_processed:
        return None
    counts = tracking.drops.counts
    return next((f"{counts[reason]} frames dropped as {reason} and none processed: {fix}"
                 for reason, fix in NEVER_ARRIVED.items() if counts[reason] >= UNWORKABLE_AFTER), None)


def build_nodes(lockstep: bool = False, **node_kwargs) -> list:
    """The node set the parameters call for; the tracking node first (``lockstep``: mapping each keyframe before it
    answers, ``worker.mode: sync``, unless the parameters say otherwise)."""
    tracking = TrackingMappingNode(LOCKSTEP_DEFAULTS if lockstep else None, **node_kwargs)
    nodes = [tracking]
    if tracking.cfg.semantics.segmenter != "labels":
        nodes.append(SegmentationNode(**node_kwargs))
    if tracking.loop_nodes:
        nodes += [LoopDetectionNode(**node_kwargs), PoseGraphNode(**node_kwargs)]
    return nodes


def spin_until_done(executor, player, linger: float = 1.0, on_spin: Callable[[], None] = lambda: None,
                    drained: Callable[[], bool] = lambda: True, drain_timeout: float = 600.0,
                    give_up: Callable[[], str | None] = lambda: None) -> str | None:
    """Spin until the player is done, then at least ``linger`` s more for the last outputs and until ``drained()``
    (the tracker's pending frames processed; ``drain_timeout`` s at most); forever without a player. ``on_spin``
    after every spin. Returns at once with what ``give_up()`` says when it says something (else None)."""
    while rclpy.ok(context=executor.context) and (player is None or not player.done):
        executor.spin_once(timeout_sec=0.1)
        on_spin()
        if (reason := give_up()) is not None:
            return reason
    start = time.monotonic()
    while rclpy.ok(context=executor.context) and (time.monotonic() < start + linger or not drained()) \
            and time.monotonic() < start + drain_timeout:
        executor.spin_once(timeout_sec=0.1)
        on_spin()
    return None


def progress_bar(tracking: TrackingMappingNode, disable: bool) -> tuple[tqdm, Callable[[], None]]:
    """A terminal progress bar over the processed frames (fps, dropped inputs) and its update function."""
    bar = tqdm(desc="gausem-ros", unit="frame", disable=disable)

    def update() -> None:
        if tracking.frames_processed != bar.n:
            seconds = tracking.seconds
            bar.set_postfix(fps=f"{tracking.frames_processed / seconds:.2f}" if seconds else "-",
                            dropped=sum(tracking.drops.counts.values()), refresh=False)
            bar.update(tracking.frames_processed - bar.n)

    return bar, update


def params_file(argv: list[str]) -> str | None:
    """The last ``--params-file`` among the ROS arguments (for the report's provenance)."""
    files = [b for a, b in zip(argv, argv[1:]) if a == "--params-file"]
    return files[-1] if files else None


def report(tracking: TrackingMappingNode, player, ns: argparse.Namespace, argv: list[str]) -> None:
    """Evaluate the run against the reference dataset, write the outputs to ``ns.report`` (with the input accounting
    in ``input.json``) and print the summary."""
    if not tracking.frames_processed:
        raise ValueError("--report: no frame was processed, there is nothing to evaluate")
    camera = tracking.frame_input.camera
    reference = open_dataset(ns.reference or ns.source, size=(camera.width, camera.height))
    metrics = write_report(tracking.slam, tracking.cfg, reference, ns.report, tracking.seconds,
                           health=tracking.health_log, eval_every=ns.eval_every, params_file=params_file(argv))
    accounting = {**tracking.summary(), "player": {"published": player.published, "timeouts": player.timeouts,
                                                   "playback_seconds": round(player.playback_seconds, 3)}}
    (Path(ns.report) / "input.json").write_text(json.dumps(accounting, indent=2) + "\n")
    print(format_summary(metrics))
    print(f"outputs written to {ns.report}/")


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="gausem-ros", description=__doc__.split("\n")[0])
    add_player_arguments(parser, required=False, finish=False)  # finished below, in-process
    parser.add_argument("--save", help="after playback, write map.ply and trajectory.txt to this folder")
    parser.add_argument("--report", type=Path, metavar="DIR",
                        help="after playback, evaluate the run like `gausem run` and write its outputs to DIR")
    parser.add_argument("--reference", metavar="SPEC",
                        help="dataset with ground truth and labels for --report when SOURCE is a bag (default: SOURCE)")
    parser.add_argument("--eval-every", type=int, default=5, help="--report: evaluate rendering on every n-th frame")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    ns = parser.parse_args(remove_ros_args(argv)[1:])
    if ns.report and not ns.source:
        parser.error("--report needs a SOURCE to play")
    if ns.report and ns.loop:
        parser.error("--report needs the replay to end: not with --loop")
    if ns.report and not ns.reference and is_bag(ns.source):
        parser.error("--report with a bag needs --reference SPEC: the dataset the bag was made from")
    if ns.report:  # read the reference (its frames, class table) now, not after the replay
        try:
            open_dataset(ns.reference or ns.source)
        except (OSError, ValueError) as err:
            parser.error(f"--report: cannot read the reference {ns.reference or ns.source!r}: {err}")
    return ns


def accounting(tracking: TrackingMappingNode, player=None) -> str:
    """One line: frames in, processed, dropped by reason, pending, latency (and the player's timeouts)."""
    s = tracking.summary()
    dropped = f" {s['dropped']}" if s["dropped"] else ""
    line = (f"frames in {s['frames_in']}, processed {s['frames_processed']}, dropped {sum(s['dropped'].values())}"
            f"{dropped}, pending {s['frames_pending']}")
    if "latency_ms.median" in s:
        line += f"; latency median {s['latency_ms.median']} ms, p95 {s['latency_ms.p95']} ms"
    if player is not None:
        line += f"; player published {player.published} frames ({player.timeouts} lock-step timeouts)"
    return line


def main(args=None) -> int:
    argv = sys.argv if args is None else ["gausem-ros", *args]
    ns = parse_arguments(argv)
    nodes, player, code = [], None, 0
    with ros_process(argv):  # SIGINT and SIGTERM raise KeyboardInterrupt in the spin
        executor = NodeExecutor(num_threads=5)
        try:
            nodes = build_nodes(lockstep=bool(ns.source and ns.lockstep))
            player = player_from_args(ns) if ns.source else None
            for node in nodes + ([player] if player else []):
                executor.add_node(node)
            tracking = nodes[0]
            bar, update = progress_bar(tracking, disable=player is None or ns.quiet)
            interrupted, cannot_work = False, None
            try:
                cannot_work = spin_until_done(executor, player, on_spin=update,
                                              drained=lambda: tracking.summary()["frames_pending"] == 0,
                                              give_up=lambda: unworkable(tracking) if player is not None else None)
            except (KeyboardInterrupt, ExternalShutdownException):
                interrupted = True
            bar.close()
            if interrupted or cannot_work:
                tracking.interrupt()
            executor.shutdown()  # waits for the frame in progress
            tracking.get_logger().info(accounting(tracking, player))
            if cannot_work:
                tracking.get_logger().error(f"the replay cannot work, stopping: {cannot_work}")
                code = 2
            elif player is not None and not interrupted:
                tracking.finish()  # the sequence is over: global refinement, as the offline pipeline does
            if ns.save and tracking.frames_processed:
                ply, trajectory = tracking.save_map(ns.save)
                tracking.get_logger().info(f"wrote {ply} and {trajectory}")
            if ns.report and not (interrupted or cannot_work):
                report(tracking, player, ns, argv)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except ValueError as err:
            rclpy.logging.get_logger("gausem").error(str(err))
            code = 1
        finally:
            executor.shutdown()
            for node in nodes + ([player] if player else []):
                node.destroy_node()
    code = code or (1 if player is not None and player.error else 0)
    if args is None:  # a command line
        exit_now(code)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
