"""The node suite under ``gausem-launch`` as the ROS benchmarks run it (``soak.py``, ``chaos.py``): a bag of the
source for the player, the launcher's command, start and stop, its processes as ``/proc`` shows them, the tracking
node's input accounting read from ``gausem/diagnostics`` and the scan of the nodes' log."""
from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from gausem_core.options import parse_size
from gausem_ros.convert import convert
from gausem_ros.nodes import NODE_MODULES
from gausem_ros.nodes.common import DIAGNOSTICS_TOPIC
from gausem_ros.player import is_bag, open_source
from gausem_ros.preflight import TRACKING_NODE
from gausem_ros.qos import EVENT_QOS

REPO = Path(__file__).resolve().parents[2]


def source_bag(source: str, size: str, folder: str | Path) -> str:
    """``source`` itself when it is a bag, else a bag of the dataset written into ``folder``: the player then reads
    frames as a driver hands them over (rendering the synthetic room costs 26 ms a frame, and a player doing so beside
    the node on a 2-core machine sent 11 frames a second, not 30)."""
    if is_bag(source):
        return source
    bag = str(Path(folder) / "source")
    convert(open_source(source, size=parse_size(size)), bag, "mcap")
    return bag


def local_domain(default: int) -> int:
    """``ROS_DOMAIN_ID`` (``default`` when unset), set with localhost-only discovery for the launch and this
    process's listener."""
    domain = int(os.environ.get("ROS_DOMAIN_ID", str(default)))
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return domain


def log_file(name: str) -> Path:
    """``out/<name>.log``, its folder made."""
    path = REPO / "out" / f"{name}.log"
    path.parent.mkdir(exist_ok=True)
    return path


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """A benchmark's own arguments and the ROS arguments after ``--`` (for every node)."""
    return (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])


def add_launch_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """The source, its size and pace, the params file, nodes, device and grace of the launch; the record's name."""
    parser.add_argument("--source", default="synthetic:loop", help="a dataset spec (written to a bag first) or a bag")
    parser.add_argument("--size", default="160x120", help="a dataset's frame size")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed (1: the recorded pace)")
    parser.add_argument("--params", type=Path, help="params file (default params/<source kind>.yaml)")
    parser.add_argument("--nodes", default=TRACKING_NODE, help="gausem-launch --nodes")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--grace", type=float, default=10.0, help="seconds the processes get to exit after SIGINT")
    parser.add_argument("--name", default=name, help="record name")


def parse_launch_arguments(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """The parsed arguments (``params`` defaulted from the source's kind) and the ROS arguments."""
    own, ros_args = split_ros_args(argv)
    args = parser.parse_args(own)
    args.params = args.params or REPO / "params" / f"{args.source.partition(':')[0]}.yaml"
    return args, ros_args


def launch_command(args, bag: str, ros_args: list[str], options: tuple[str, ...] = ()) -> list[str]:
    """``gausem-launch`` playing ``bag`` on a loop at ``args.rate`` with ``args``' params file, nodes, grace and device;
    ``options``: further launcher options (``--respawn``)."""
    play = f"{shlex.quote(bag)} --rate {args.rate:g} --loop --wait-subscribers 60"
    return [sys.executable, "-m", "gausem_ros.launcher", "--params-file", str(args.params), "--nodes", args.nodes,
            "--play", play, "--grace", str(args.grace), *options, "--", "-p", f"device:={args.device}", *ros_args]


def start_launcher(command: list[str], log_path: Path) -> subprocess.Popen:
    """The launcher in a session of its own (so :func:`stop` can kill what is left of it), its output in
    ``log_path``."""
    with log_path.open("w") as log:
        return subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop(launcher: subprocess.Popen, wait: float) -> list[str]:
    """SIGINT to the launcher (it stops its children and kills what is left after its grace), then SIGKILL to its
    process group if anything of it is left ``wait`` s later; what was killed so."""
    if launcher.poll() is None:
        launcher.send_signal(signal.SIGINT)
        try:
            launcher.wait(wait)
        except subprocess.TimeoutExpired:
            pass
    left = [f"{process_name(int(p.name)) or p.name} (pid {p.name})" for p in Path("/proc").iterdir()
            if p.name.isdigit() and _group(int(p.name)) == launcher.pid]
    if left:
        os.killpg(launcher.pid, signal.SIGKILL)
    launcher.wait()
    return left


def _group(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except OSError:
        return None


def process_name(pid: int) -> str | None:
    """``player``, a node's name or ``launcher`` from the process's command line; None when it is gone."""
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return None
    module = next((b for a, b in zip(words, words[1:]) if a == "-m"), "")
    return module.rpartition(".")[2] or None


def children(pid: int) -> dict[str, int]:
    """The node and player processes among the children of ``pid``, by name (not one forked and not yet started)."""
    found = {}
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and int((entry / "stat").read_text().rpartition(")")[2].split()[1]) == pid:
                found[process_name(int(entry.name))] = int(entry.name)
        except (OSError, IndexError, ValueError):
            continue
    return {name: child for name, child in found.items() if name in (*NODE_MODULES, "player")}


def process_stats(pid: int) -> dict | None:
    """Resident set (MB), threads and open files of a process; None when it is gone."""
    try:
        status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
        return {"rss_mb": round(int(status["VmRSS"].split()[0]) / 1024, 1), "threads": int(status["Threads"]),
                "files": len(os.listdir(f"/proc/{pid}/fd"))}
    except (OSError, KeyError):  # gone, or a zombie (no VmRSS)
        return None


def counts(values: dict[str, str]) -> dict[str, int]:
    """frames in, processed, dropped (every reason) and pending of a tracking node's diagnostics values."""
    return {"frames_in": int(values["frames_in"]), "frames_processed": int(values["frames_processed"]),
            "dropped": sum(int(v) for k, v in values.items() if k.startswith("dropped.")),
            "frames_pending": int(values["frames_pending"])}


def adds_up(c: dict[str, int]) -> bool:
    return c["frames_in"] == c["frames_processed"] + c["dropped"] + c["frames_pending"]


class DiagnosticsListener:
    """The tracking node's latest input accounting from ``gausem/diagnostics`` (its own context on ``domain``; more
    subscriptions may go on :attr:`node`), its latest values, and how many of the messages added up."""

    def __init__(self, domain: int, name: str = "bench_listener"):
        self.context = Context()
        rclpy.init(args=[], context=self.context, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.context)
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, EVENT_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.latest: dict[str, int] | None = None
        self.values: dict[str, str] = {}  # the latest message's, every key
        self.dropped: dict[str, int] = {}  # by reason
        self.received_at = 0.0
        self.messages = self.mismatches = 0
        self.first_mismatch: dict | None = None

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name.rpartition("/")[2] != TRACKING_NODE or "frames_in" not in values:
                continue
            self.values, self.latest, self.received_at = values, counts(values), time.monotonic()
            self.dropped = {k.removeprefix("dropped."): int(v) for k, v in values.items() if k.startswith("dropped.")}
            self.messages += 1
            if not adds_up(self.latest):
                self.mismatches += 1
                self.first_mismatch = self.first_mismatch or self.latest

    def spin(self, seconds: float) -> None:
        """Take the messages that arrive within ``seconds``."""
        end = time.monotonic() + seconds
        while self.context.ok() and (left := end - time.monotonic()) > 0:
            self.executor.spin_once(timeout_sec=left)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def scan_log(text: str) -> dict[str, list[str]]:
    """The exceptions (each traceback's last line), error log lines and the launcher's reports of dead processes."""
    lines = text.splitlines()
    exceptions = []
    for i, line in enumerate(lines):
        if line.startswith("Traceback (most recent call last)"):
            exceptions.append(next((x for x in lines[i + 1:] if x and not x[0].isspace()), "(traceback cut short)"))
    return {"exceptions": exceptions,
            "errors": [line for line in lines if re.search(r"\[(ERROR|FATAL)\]", line)],
            "launcher": [line for line in lines if line.startswith("[gausem-launch]") and " ended with " in line]}
