"""Starts GauSem's nodes as separate processes (entry point ``gausem-launch``), for process isolation; the default is
one process (``gausem-ros``). Without ROS ``launch`` (not on PyPI), this is a small supervisor:

``gausem-launch [--params-file F] [--nodes tracking_mapping,pose_graph] [--play "SOURCE --lockstep ..."]
[-- ROS_ARGS...]``

Each node runs as ``python -m gausem_ros.nodes.<name> --ros-args --params-file F ROS_ARGS``; with ``--play`` the
player runs too and, once it exits, the nodes are stopped with SIGINT. SIGINT/SIGTERM to the launcher are forwarded
to every child; children still running ``--grace`` s later are killed. The exit code is the worst of the children's
(a child ended by signal N counts as 128 + N).
"""
from __future__ import annotations

import argparse
import shlex
import signal
import subprocess
import sys
import time

from .nodes import NODE_MODULES

DEFAULT_NODES = ("tracking_mapping", "loop_detection", "pose_graph")


def node_command(name: str, params_file: str | None, ros_args: list[str]) -> list[str]:
    if name not in NODE_MODULES:
        raise ValueError(f"unknown node {name!r}; choose from {', '.join(NODE_MODULES)}")
    return [sys.executable, "-m", f"gausem_ros.nodes.{name}", *_ros_args(params_file, ros_args)]


def player_command(player_args: str, ros_args: list[str]) -> list[str]:
    return [sys.executable, "-m", "gausem_ros.player", *shlex.split(player_args), *_ros_args(None, ros_args)]


def _ros_args(params_file: str | None, ros_args: list[str]) -> list[str]:
    args = ["--params-file", params_file] if params_file else []
    args += [a for a in ros_args if a != "--ros-args"]
    return ["--ros-args", *args] if args else []


def exit_code(returncode: int) -> int:
    return 128 - returncode if returncode < 0 else returncode


class Launcher:
    """Runs ``nodes`` (commands) and an optional ``player`` command; see the module docstring."""

    def __init__(self, nodes: list[list[str]], player: list[str] | None = None, grace: float = 10.0):
        self.grace = grace
        self.nodes = [subprocess.Popen(cmd) for cmd in nodes]
        self.player = subprocess.Popen(player) if player else None
        self._stopping = False

    @property
    def children(self) -> list[subprocess.Popen]:
        return self.nodes + ([self.player] if self.player else [])

    def signal_all(self, signum: int, children=None) -> None:
        for child in children if children is not None else self.children:
            if child.poll() is None:
                child.send_signal(signum)

    def _forward(self, signum, frame) -> None:
        del frame
        self._stopping = True
        self.signal_all(signum)

    def wait(self) -> int:
        """Until the player exits (then stop the nodes), a node exits, or a signal arrives; the worst exit code."""
        previous = {s: signal.signal(s, self._forward) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            while not self._stopping:
                if self.player is not None and self.player.poll() is not None:
                    break
                if any(node.poll() is not None for node in self.nodes):
                    break
                time.sleep(0.1)
            if not self._stopping:  # a forwarded signal already reached every child; a second SIGINT interrupts
                self.signal_all(signal.SIGINT)  # rclpy's shutdown (exit 130)
            deadline = time.monotonic() + self.grace
            for child in self.children:
                try:
                    child.wait(max(deadline - time.monotonic(), 0.1))
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        return max(exit_code(child.returncode) for child in self.children)


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(prog="gausem-launch", description=__doc__.split("\n")[0])
    parser.add_argument("--params-file", help="ROS parameter file for every node (e.g. params/synthetic.yaml)")
    parser.add_argument("--nodes", default=",".join(DEFAULT_NODES), help="comma-separated node names")
    parser.add_argument("--play", help="player arguments, quoted: 'SOURCE --lockstep --size 80x60'")
    parser.add_argument("--grace", type=float, default=10.0, help="seconds children get to exit after SIGINT")
    ns = parser.parse_args(own)
    try:
        nodes = [node_command(name, ns.params_file, ros_args) for name in ns.nodes.split(",") if name]
    except ValueError as err:
        parser.error(str(err))
    player = player_command(ns.play, ros_args) if ns.play else None
    return Launcher(nodes, player, ns.grace).wait()


if __name__ == "__main__":
    raise SystemExit(main())
