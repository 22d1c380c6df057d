"""All GauSem nodes in one process on a SingleThreadedExecutor (entry point ``gausem-ros``), optionally with the
player: ``gausem-ros [SOURCE --lockstep ...] [--save DIR] --ros-args --params-file params/synthetic.yaml``.

Which nodes: tracking_mapping always; segmentation unless ``semantics.segmenter`` is ``labels`` (then the labels come
with the data); loop_detection (needs labels) and pose_graph when ``loop.enabled``. The ROS arguments (params file,
``-p``, remappings) apply to every node. With a SOURCE the process ends when the player is done (after ``--save``);
without, it runs until Ctrl-C.
"""
from __future__ import annotations

import argparse
import sys
import time

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.utilities import remove_ros_args

from .nodes.loop_detection import LoopDetectionNode
from .nodes.pose_graph import PoseGraphNode
from .nodes.segmentation import SegmentationNode
from .nodes.tracking_mapping import TrackingMappingNode
from .player import add_player_arguments, player_from_args


def build_nodes(**node_kwargs) -> list:
    """The node set the parameters call for; the tracking node first."""
    tracking = TrackingMappingNode(**node_kwargs)
    nodes = [tracking]
    if tracking.cfg.semantics.segmenter != "labels":
        nodes.append(SegmentationNode(**node_kwargs))
    if tracking.cfg.loop.enabled:
        if tracking.params.use_labels:
            nodes.append(LoopDetectionNode(**node_kwargs))
        nodes.append(PoseGraphNode(**node_kwargs))
    return nodes


def spin_until_done(executor, player, linger: float = 1.0) -> None:
    """Spin until the player is done (then ``linger`` s more for the last outputs), or forever without one."""
    while rclpy.ok(context=executor.context) and (player is None or not player.done):
        executor.spin_once(timeout_sec=0.1)
    end = time.monotonic() + linger
    while rclpy.ok(context=executor.context) and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)


def main(args=None) -> int:
    argv = sys.argv if args is None else ["gausem-ros", *args]
    parser = argparse.ArgumentParser(prog="gausem-ros", description=__doc__.split("\n")[0])
    add_player_arguments(parser, required=False)
    parser.add_argument("--save", help="after playback, write map.ply and trajectory.txt to this folder")
    ns = parser.parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    nodes, executor = [], SingleThreadedExecutor()
    try:
        nodes = build_nodes()
        player = player_from_args(ns) if ns.source else None
        for node in nodes + ([player] if player else []):
            executor.add_node(node)
        spin_until_done(executor, player)
        if ns.save:
            ply, trajectory = nodes[0].save_map(ns.save)
            nodes[0].get_logger().info(f"wrote {ply} and {trajectory}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as err:
        rclpy.logging.get_logger("gausem").error(str(err))
        return 1
    finally:
        executor.shutdown()
        for node in executor.get_nodes() or nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
