"""Starts GauSem's nodes as separate processes (entry point ``gausem-launch``), for process isolation; the default is
one process (``gausem-ros``). Without ROS ``launch`` (not on PyPI), this is a small supervisor:

``gausem-launch [--params-file F] [--nodes tracking_mapping,pose_graph] [--play "SOURCE --lockstep ..."]
[--respawn] [-- ROS_ARGS...]``

Each node runs as ``python -m gausem_ros.nodes.<name> --ros-args --params-file F ROS_ARGS``; with ``--play`` the
player runs too (a ``--lockstep`` one makes tracking_mapping map each keyframe before it answers:
``-p worker.mode:=sync`` ahead of ROS_ARGS) and, once it exits, the nodes are stopped with SIGINT. A node that dies is reported (name, exit code
or signal) and the others go on; with ``--respawn`` it is started again after ``--respawn-delay`` s (doubled after
each crash within 10 s of its start, at most 32x) and every child talks over Fast DDS's UDP transport alone
(:func:`respawn_environment`). The launcher ends when the player is done, when every node has
ended, or on SIGINT/SIGTERM, which it forwards to every child; children still running ``--grace`` s later are killed.
The exit code is the worst of every child process that ended, crashed ones included (a child ended by signal N
counts as 128 + N). Before anything starts, the parameters, ``map_path`` and the player's source are checked
(``preflight``): a problem each node would meet (at every respawn) ends the launch with exit code 2 and names it.
"""
from __future__ import annotations

import argparse
import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field

from .nodes import NODE_MODULES
from .preflight import TRACKING_NODE, launch_problems

DEFAULT_NODES = ("tracking_mapping",)  # closes loops itself (loop_closure: core); add loop_detection,pose_graph
# for the distributed loop closure (-p loop_closure:=nodes)


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


def describe(returncode: int) -> str:
    if returncode < 0:
        return f"signal {signal.Signals(-returncode).name} (exit code {exit_code(returncode)})"
    return f"exit code {returncode}"


RESPAWN_ENVIRONMENT = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}


def respawn_environment(environ: dict[str, str]) -> dict[str, str]:
    """``environ`` with Fast DDS on UDP only, unless it sets ``FASTDDS_BUILTIN_TRANSPORTS`` itself: over shared memory
    a node killed with SIGKILL can leave the writers that fed it delivering to no one, its respawned self included
    (Fast DDS 2.14, eProsima/Fast-DDS#5469; ``benchmarks/chaos.py`` met it: after a kill the player's frames reached
    neither the new tracker nor a new listener)."""
    return {**RESPAWN_ENVIRONMENT, **environ}


QUICK_CRASH_S = 10.0  # a node that dies sooner after its start waits longer before its next respawn


@dataclass
class Child:
    """A supervised process: its command, the running process, when it started and how often it was restarted."""

    name: str
    command: list[str]
    env: dict[str, str] | None = None  # None: the launcher's
    process: subprocess.Popen = field(init=False)
    started: float = field(init=False)
    restarts: int = 0
    quick_crashes: int = 0
    restart_at: float | None = None  # when a dead node is due to be started again
    ended: bool = False  # dead and not to be started again

    def __post_init__(self):
        self.start()

    def start(self) -> None:
        self.process = subprocess.Popen(self.command, env=self.env)
        self.started, self.restart_at = time.monotonic(), None


class Launcher:
    """Runs ``nodes`` ({name: command}) and an optional ``player`` command; see the module docstring. ``env``: the
    children's environment (None: the launcher's)."""

    def __init__(self, nodes: dict[str, list[str]], player: list[str] | None = None, grace: float = 10.0,
                 respawn: bool = False, respawn_delay: float = 1.0, env: dict[str, str] | None = None):
        self.grace, self.respawn, self.respawn_delay = grace, respawn, respawn_delay
        self.nodes = [Child(name, cmd, env) for name, cmd in nodes.items()]
        self.player = Child("player", player, env) if player else None
        self.exit_codes: list[int] = []  # of every child process that ended
        self._stopping = False

    @property
    def children(self) -> list[Child]:
        return self.nodes + ([self.player] if self.player else [])

    def signal_all(self, signum: int) -> None:
        for child in self.children:
            if child.process.poll() is None:
                child.process.send_signal(signum)

    def _forward(self, signum, frame) -> None:
        del frame
        self._stopping = True
        self.signal_all(signum)

    def _log(self, text: str) -> None:
        print(f"[gausem-launch] {text}", file=sys.stderr, flush=True)

    def _supervise(self, now: float) -> None:
        """Report nodes that died and (with respawn) start them again when their delay has passed."""
        for child in self.nodes:
            code = child.process.poll()
            if code is None or child.ended:
                continue
            if child.restart_at is None:  # found dead just now
                self.exit_codes.append(exit_code(code))
                child.quick_crashes = child.quick_crashes + 1 if now - child.started < QUICK_CRASH_S else 0
                if self.respawn:
                    delay = self.respawn_delay * 2 ** min(child.quick_crashes, 5)
                    child.restart_at = now + delay
                    self._log(f"{child.name} ended with {describe(code)}; restarting it in {delay:.1f} s")
                else:
                    child.ended = True
                    self._log(f"{child.name} ended with {describe(code)}; the other nodes go on")
            elif now >= child.restart_at:
                child.restarts += 1
                child.start()
                self._log(f"{child.name} restarted ({child.restarts} so far)")

    def _all_nodes_ended(self) -> bool:
        return not self.respawn and all(child.process.poll() is not None for child in self.nodes)

    def wait(self) -> int:
        """Until the player exits (then stop the nodes), every node has ended, or a signal arrives; the worst exit
        code."""
        previous = {s: signal.signal(s, self._forward) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            while not self._stopping:
                if self.player is not None and self.player.process.poll() is not None:
                    break
                self._supervise(time.monotonic())
                if self._all_nodes_ended():
                    break
                time.sleep(0.1)
            if not self._stopping:  # a forwarded signal already reached every child; a second SIGINT interrupts
                self.signal_all(signal.SIGINT)  # rclpy's shutdown (exit 130)
            deadline = time.monotonic() + self.grace
            for child in self.children:
                try:
                    child.process.wait(max(deadline - time.monotonic(), 0.1))
                except subprocess.TimeoutExpired:
                    self._log(f"{child.name} still running {self.grace:.0f} s after SIGINT; killing it")
                    child.process.kill()
                    child.process.wait()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        final = [exit_code(c.process.returncode) for c in self.children if not c.ended and c.restart_at is None]
        for child in self.children:
            if not child.ended and child.restart_at is None and child.process.returncode:
                self._log(f"{child.name} ended with {describe(child.process.returncode)} on shutdown")
        return max(self.exit_codes + final, default=0)


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(prog="gausem-launch", description=__doc__.split("\n")[0])
    parser.add_argument("--params-file", help="ROS parameter file for every node (e.g. params/synthetic.yaml)")
    parser.add_argument("--nodes", default=",".join(DEFAULT_NODES), help="comma-separated node names")
    parser.add_argument("--play", help="player arguments, quoted: 'SOURCE --lockstep --size 80x60'")
    parser.add_argument("--grace", type=float, default=10.0, help="seconds children get to exit after SIGINT")
    parser.add_argument("--respawn", action="store_true", help="start a node that dies again")
    parser.add_argument("--respawn-delay", type=float, default=1.0, help="seconds before a respawn (doubles after "
                                                                         "quick crashes)")
    ns = parser.parse_args(own)
    lockstep = ["-p", "worker.mode:=sync"] if ns.play and "--lockstep" in shlex.split(ns.play) else []
    try:  # a lock-step replay maps each keyframe before answering (gausem run's results); a -p given wins
        nodes = {name: node_command(name, ns.params_file, lockstep + ros_args if name == "tracking_mapping"
                                    else ros_args) for name in ns.nodes.split(",") if name}
    except ValueError as err:
        parser.error(str(err))
    tracking = [name for name in nodes if name == TRACKING_NODE]
    problems = launch_problems(ns.params_file, lockstep + ros_args, ns.play) if tracking or ns.play else []
    if problems:  # before any node starts: each would fail the same way (and again at every respawn)
        parser.exit(2, "".join(f"gausem-launch: error: {problem}\n" for problem in problems))
    player = player_command(ns.play, ros_args) if ns.play else None
    env = respawn_environment(dict(os.environ)) if ns.respawn else None
    return Launcher(nodes, player, ns.grace, ns.respawn, ns.respawn_delay, env).wait()


if __name__ == "__main__":
    raise SystemExit(main())
