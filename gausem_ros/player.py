"""Replays a dataset or a bag onto GauSem's input topics (entry point ``gausem-player``).

Sources: a dataset spec of :func:`gausem_core.data.open_dataset` (``synthetic[:SEQ]``, ``tum:PATH``, ``scannet:PATH``,
``replica:PATH``), a ROS 1 ``.bag`` file or a ROS 2 bag folder (sqlite3 or mcap). Bags may use the TUM RGB-D topic
names (``/camera/rgb/image_color``, ``/camera/depth/image``, ``/camera/rgb/camera_info``) or GauSem's
(``/rgb/image``, ``/depth/image``, ``/rgb/camera_info``, ``/semantic/labels``, as ``gausem-bag`` writes them); an input
under another name is mapped with ``--topic INPUT=TOPIC`` (e.g. ``--topic labels=/camera/labels``); every other topic
(``/tf`` with motion-capture ground truth, ...) is not replayed, and named in a log line.
Published (relative names, remappable): ``rgb/image``, ``depth/image``, ``rgb/camera_info``, ``semantic/labels``
(only when the data has labels) with reliable QoS, and ``/clock`` (the replayed stamps, for ``use_sim_time``).
Ground truth is never published; ``--gt-out FILE`` writes the dataset's ground-truth poses of the replayed frames as a
TUM trajectory for evaluation. ``--loop`` replays the source again and again until stopped (a soak test): each pass
is read anew and restamped to follow the last one by one frame interval, so stamps keep increasing (the nodes drop
stale and duplicate ones); no ground truth then, so neither ``--gt-out`` nor ``--finish``.

Timing: frames follow their recorded stamps scaled by ``--rate`` (0 = as fast as possible), on the wall clock: the
player is the source of ``/clock``, so it never runs on sim time itself (``use_sim_time`` is forced off for it, also
when ``-p use_sim_time:=true`` is given for the nodes it feeds). Frames are published from the player's own thread,
which sleeps until the next frame is due (or a lock-step answer wakes it), so an executor busy with a slow frame in
the same process does not hold playback back. ``--lockstep`` publishes
frame k+1 only after ``gausem/odometry`` for frame k arrived, or tracking_mapping's ``gausem/diagnostics`` said it
dropped frame k (bad input, a diverged estimate, unmatched inputs), or ``--timeout`` seconds passed (which is
logged).
``--finish`` calls tracking_mapping's ``gausem/finish`` service (the global refinement) after the last frame (in
lock-step, after its answer) and waits for it (``--finish-timeout`` s at most), so that the path published then is
the final trajectory. A frame is the messages from one rgb image up to the next; the player first waits
(``--wait-subscribers`` s at most) until every topic it publishes has a subscriber, so that no frame is lost to
discovery.
A bag found corrupt or truncated (on opening or part-way) ends playback with a logged error (``Player.error``; the
command exits with 1) after the frames read so far; the player never dies in a callback.
"""
from __future__ import annotations

import argparse
import functools
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger

import msg_adapters as ma
from gausem_core.data import Dataset, open_dataset
from gausem_core.data.spec import SPEC_HELP
from gausem_core.io.trajectory import Trajectory, write_tum_trajectory
from gausem_core.options import parse_size

from .bags import TUM_TOPICS, BagError, read_bag
from .nodes.common import DIAGNOSTICS_TOPIC, LAST_FRAME_KEY
from .qos import EVENT_QOS, IMAGE_QOS

# input key -> (message type, published topic)
OUTPUTS = {"rgb": (Image, "rgb/image"), "depth": (Image, "depth/image"),
           "camera_info": (CameraInfo, "rgb/camera_info"), "labels": (Image, "semantic/labels")}
GAUSEM_BAG_TOPICS = {key: "/" + topic for key, (_, topic) in OUTPUTS.items()}
BAG_TOPIC_KEYS = {**{TUM_TOPICS[key]: key for key in ("rgb", "depth", "camera_info")},
                  **{topic: key for key, topic in GAUSEM_BAG_TOPICS.items()}}
_STAMP_TOLERANCE_NS = 1000  # float-seconds round trips of stamps are exact to well below 1 us
_LOOP_INTERVAL_NS = 33_333_333  # --loop: the gap after a pass of a single frame (a 30 Hz camera's)


@dataclass
class PlayerFrame:
    """The messages of one frame, keyed like ``OUTPUTS``, published together at ``stamp_ns``."""

    stamp_ns: int
    messages: list[tuple[str, object]] = field(default_factory=list)
    gt_pose: np.ndarray | None = None


def dataset_frames(dataset: Dataset, frame_id: str = "camera", depth_encoding: str = "32FC1"
                   ) -> Iterator[PlayerFrame]:
    """rgb8, depth (32FC1 m or 16UC1 mm), CameraInfo and, when present, mono16 labels of every frame."""
    for frame in dataset:
        header = ma.make_header(frame.timestamp, frame_id)
        messages = [("rgb", ma.rgb_to_image(frame.rgb, header)),
                    ("depth", ma.depth_to_image(frame.depth, header, depth_encoding)),
                    ("camera_info", ma.camera_to_camera_info(frame.camera, header))]
        if frame.labels is not None:
            messages.append(("labels", ma.labels_to_image(frame.labels, header)))
        yield PlayerFrame(ma.seconds_to_ns(frame.timestamp), messages, frame.gt_pose)


def bag_frames(path: str | Path, topics: dict[str, str] | None = None) -> Iterator[PlayerFrame]:
    """Frames of a bag: each rgb image opens a frame; messages before the first rgb image join the first frame.
    ``topics``: input key -> bag topic, besides the known names (e.g. ``{"labels": "/camera/labels"}``); every other
    topic is named once in a log line as not replayed."""
    keys = {**BAG_TOPIC_KEYS, **{topic: key for key, topic in (topics or {}).items()}}
    frame = None
    leading: list[tuple[str, object]] = []
    skipped: set[str] = set()
    for item in read_bag(path):
        key = keys.get(item.topic)
        if key is None:
            if item.topic not in skipped:
                skipped.add(item.topic)
                rclpy.logging.get_logger("gausem_player").info(
                    f"bag topic {item.topic} is not replayed (an input it carries: --topic INPUT={item.topic}, "
                    f"INPUT one of {', '.join(OUTPUTS)})")
            continue
        if key == "rgb":
            if frame is not None:
                yield frame
            frame = PlayerFrame(item.stamp_ns, leading)
            leading = []
        (leading if frame is None else frame.messages).append((key, item.msg))
    if frame is not None:
        yield frame


def looped(frames: Iterable[PlayerFrame], reopen: Callable[[], Iterable[PlayerFrame]]) -> Iterator[PlayerFrame]:
    """``frames``, then ``reopen()``'s again and again (until one yields nothing), each pass's stamps and headers
    shifted to follow the last frame by the last frame interval; without ground truth."""
    offset, last, interval = 0, None, _LOOP_INTERVAL_NS
    while True:
        passed = 0
        for frame in frames:
            if not passed and last is not None:  # a pass starts one interval after the last one's end
                offset = last + interval - frame.stamp_ns
            for _, msg in frame.messages:  # a new header each: a frame's messages may share one
                msg.header = Header(stamp=ma.ns_to_time(ma.time_to_ns(msg.header.stamp) + offset),
                                    frame_id=msg.header.frame_id)
            stamp = frame.stamp_ns + offset
            if last is not None:
                interval = stamp - last
            last, passed = stamp, passed + 1
            yield replace(frame, stamp_ns=stamp, gt_pose=None)
        if not passed:
            return
        frames = reopen()


def parse_topics(pairs: list[str]) -> dict[str, str]:
    """``INPUT=TOPIC`` pairs (``--topic``) as a dict; ValueError naming a bad one."""
    topics = {}
    for pair in pairs:
        key, _, topic = pair.partition("=")
        if key not in OUTPUTS or not topic:
            raise ValueError(f"--topic {pair!r}: expected INPUT=TOPIC with INPUT one of {', '.join(OUTPUTS)}")
        topics[key] = topic
    return topics


def is_bag(source: str) -> bool:
    path = Path(source)
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


def open_source(source: str, *, size=None, stride: int = 1, max_frames: int | None = None, frame_id: str = "camera",
                depth_encoding: str = "32FC1", topics: dict[str, str] | None = None) -> Iterator[PlayerFrame]:
    """Frames of a bag (path; ``topics``: see :func:`bag_frames`) or of a dataset spec (resized/strided/capped by the
    options; bags are replayed as recorded and accept none of them)."""
    if is_bag(source):
        if size is not None or stride != 1 or max_frames is not None:
            raise ValueError("--size, --stride and --max-frames apply to datasets, not to bags")
        return bag_frames(source, topics)
    if topics:
        raise ValueError("--topic applies to bags, not to datasets")
    return dataset_frames(open_dataset(source, size=size, stride=stride, max_frames=max_frames), frame_id,
                          depth_encoding)


class Player(Node):
    """Publishes ``frames`` on the input topics from a timer; ``done`` once all are out (in lock-step, the last one
    answered or timed out; with ``finish``, the ``gausem/finish`` call answered or timed out)."""

    def __init__(self, frames: Iterable[PlayerFrame], *, rate: float = 1.0, lockstep: bool = False,
                 timeout: float = 10.0, wait_subscribers: float = 5.0, finish: bool = False,
                 finish_timeout: float = 600.0, period: float = 0.05, **kwargs):
        overrides = [*kwargs.pop("parameter_overrides", []), Parameter("use_sim_time", value=False)]
        super().__init__("player", parameter_overrides=overrides, **kwargs)
        if rate < 0 or timeout <= 0 or wait_subscribers < 0 or finish_timeout <= 0:
            raise ValueError(f"player: rate must be >= 0, timeout and finish_timeout > 0 and wait_subscribers >= 0, "
                             f"got {rate}, {timeout}, {finish_timeout}, {wait_subscribers}")
        self.rate, self.lockstep, self.timeout, self.wait_subscribers = rate, lockstep, timeout, wait_subscribers
        self.error: str | None = None  # why playback stopped early (a corrupt or truncated bag)
        self.published = 0
        self._frames = iter(frames)
        self._next = self._read_next()
        self._pubs = {key: self.create_publisher(cls, topic, IMAGE_QOS) for key, (cls, topic) in OUTPUTS.items()}
        self._clock_pub = self.create_publisher(Clock, "/clock", IMAGE_QOS)
        self.create_subscription(Odometry, "gausem/odometry", self._on_odometry, EVENT_QOS)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, EVENT_QOS)
        self.odometry_received = 0
        self.timeouts = 0
        self.ground_truth: list[tuple[float, np.ndarray]] = []
        self._awaiting: int | None = None  # stamp (ns) whose odometry lock-step waits for
        self._waiting_since = time.monotonic()
        self._start: tuple[float, int] | None = None  # (wall time, stamp ns) of the first frame
        self._last_published = 0.0  # wall time of the last frame
        self._finish = self.create_client(Trigger, "gausem/finish") if finish else None
        self._finish_timeout = finish_timeout
        self._finish_call = None  # (future, wall time of the call)
        self.finished: bool | None = None  # with finish: whether gausem/finish answered with success
        self._period = period  # longest sleep of the playback thread (subscriber and lock-step timeouts)
        self._wake, self._stop = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._play, name="gausem-player", daemon=True)
        self._thread.start()

    def _read_next(self) -> PlayerFrame | None:
        """The next frame; None at the end or, logged and kept in ``error``, when the source cannot be read on."""
        try:
            return next(self._frames, None)
        except BagError as err:
            self.error = f"playback stopped after {self.published} frames: {err}"
            self.get_logger().error(self.error)
            return None

    @property
    def playback_seconds(self) -> float:
        """Wall time from the first frame published to the last."""
        return self._last_published - self._start[0] if self._start else 0.0

    @property
    def done(self) -> bool:
        return self._next is None and self._awaiting is None and (self._finish is None or self.finished is not None)

    def _on_odometry(self, msg: Odometry) -> None:
        self.odometry_received += 1
        self._answered(ma.time_to_ns(msg.header.stamp))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            handled = next((kv.value for kv in status.values if kv.key == LAST_FRAME_KEY), None)
            if handled is not None:
                self._answered(int(handled))

    def _answered(self, stamp_ns: int) -> None:
        """Lock-step: the tracker is done with the frame stamped ``stamp_ns``."""
        if self._awaiting is not None and stamp_ns >= self._awaiting - _STAMP_TOLERANCE_NS:
            self._awaiting = None
            self._wake.set()

    def _play(self) -> None:
        """The playback thread: publish what is due, sleep until the next frame is due or an answer arrives."""
        while not self._stop.is_set() and not self.done:
            self._wake.clear()
            try:
                self._tick()
            except Exception:  # noqa: BLE001 (rclpy's RCLError) a publish racing a shutdown (Ctrl-C) ends playback
                if self.context.ok():
                    raise
                return
            self._wake.wait(self._sleep())

    def _sleep(self) -> float:
        """Seconds until the next frame is due (at most the polling period)."""
        if self._awaiting is not None or self._next is None or self._start is None:
            return self._period
        if self.rate == 0:
            return 0.0
        wall0, stamp0 = self._start
        due = wall0 + ma.ns_to_seconds(self._next.stamp_ns - stamp0) / self.rate
        return min(max(due - time.monotonic(), 0.0), self._period)

    def destroy_node(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join()
        super().destroy_node()

    def _tick(self) -> None:
        now = time.monotonic()
        if self._awaiting is not None:
            if now - self._waiting_since < self.timeout:
                return
            self.timeouts += 1
            self.get_logger().warning(f"lock-step: no gausem/odometry for the frame stamped "
                                      f"{ma.ns_to_seconds(self._awaiting):.6f} s within {self.timeout} s; going on")
            self._awaiting = None
        if self._next is None:
            if self._finish is not None and self.finished is None:
                self._call_finish(now)
            return
        if not self._ready(now):
            return
        frame = self._next
        if self._start is None:
            self._start = (now, frame.stamp_ns)
        for key, msg in frame.messages:
            self._pubs[key].publish(msg)
        self._clock_pub.publish(Clock(clock=ma.ns_to_time(frame.stamp_ns)))
        self.published += 1
        self._last_published = time.monotonic()
        if frame.gt_pose is not None:
            self.ground_truth.append((ma.ns_to_seconds(frame.stamp_ns), frame.gt_pose))
        if self.lockstep:
            self._awaiting, self._waiting_since = frame.stamp_ns, now
        self._next = self._read_next()

    def _call_finish(self, now: float) -> None:
        """Call gausem/finish once the service is there (``timeout`` s at most), then wait for its answer."""
        if self._finish_call is None:
            if self._finish.service_is_ready():
                self._finish_call = (self._finish.call_async(Trigger.Request()), now)
            elif now - self._waiting_since >= self.timeout:
                self.get_logger().warning(f"no gausem/finish service within {self.timeout} s; not finishing")
                self.finished = False
            return
        future, called = self._finish_call
        if future.done():
            response = future.result()
            self.finished = bool(response and response.success)
            self.get_logger().info(f"gausem/finish: {response.message if response else 'no answer'}")
        elif now - called >= self._finish_timeout:
            self.get_logger().warning(f"gausem/finish did not answer within {self._finish_timeout} s")
            self.finished = False

    def _ready(self, now: float) -> bool:
        if self._start is None:  # the first frame waits for subscribers on every topic it carries
            keys = {key for key, _ in self._next.messages}
            subscribed = all(self._pubs[key].get_subscription_count() > 0 for key in keys)
            return subscribed or now - self._waiting_since >= self.wait_subscribers
        if self.rate == 0:
            return True
        wall0, stamp0 = self._start
        return (now - wall0) * self.rate >= ma.ns_to_seconds(self._next.stamp_ns - stamp0)

    def write_ground_truth(self, path: str | Path) -> int:
        """Write the replayed frames' ground-truth poses (TUM format); returns how many."""
        write_tum_trajectory(path, Trajectory([t for t, _ in self.ground_truth],
                                              np.array([p for _, p in self.ground_truth]).reshape(-1, 4, 4)))
        return len(self.ground_truth)


def add_source_arguments(parser: argparse.ArgumentParser, required: bool = True) -> None:
    parser.add_argument("source", nargs=None if required else "?",
                        help=f"a ROS 1 .bag file, a ROS 2 bag folder or a dataset spec: {SPEC_HELP}")
    parser.add_argument("--size", type=parse_size, help="resize dataset frames to WIDTHxHEIGHT")
    parser.add_argument("--stride", type=int, default=1, help="keep every n-th dataset frame")
    parser.add_argument("--max-frames", type=int, help="at most this many dataset frames")
    parser.add_argument("--frame-id", default="camera", help="camera frame id of dataset frames")
    parser.add_argument("--depth-encoding", choices=("32FC1", "16UC1"), default="32FC1")
    parser.add_argument("--topic", action="append", default=[], metavar="INPUT=TOPIC",
                        help=f"replay a bag topic of another name as an input ({', '.join(OUTPUTS)}), e.g. "
                             "labels=/camera/labels; repeatable")


def add_player_arguments(parser: argparse.ArgumentParser, required: bool = True, finish: bool = True) -> None:
    """The player's options; ``finish``: offer --finish (not where the caller finishes the tracking node itself)."""
    add_source_arguments(parser, required)
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor; 0 = as fast as possible")
    parser.add_argument("--lockstep", action="store_true", help="wait for gausem/odometry of each frame")
    parser.add_argument("--timeout", type=float, default=60.0, help="lock-step wait per frame (s; covers a first "
                        "frame's map initialisation on a CPU)")
    parser.add_argument("--wait-subscribers", type=float, default=5.0, help="wait for subscribers at most (s)")
    if finish:
        parser.add_argument("--finish", action="store_true",
                            help="after the last frame, call gausem/finish (global refinement) and wait for it")
        parser.add_argument("--finish-timeout", type=float, default=600.0, help="wait for gausem/finish at most (s)")
    parser.add_argument("--gt-out", help="write the replayed frames' ground truth here (TUM format)")
    parser.add_argument("--loop", action="store_true", help="replay the source again and again, restamped to follow "
                        "on, until stopped (no ground truth)")


def source_from_args(ns: argparse.Namespace) -> Iterator[PlayerFrame]:
    """The frames :func:`add_source_arguments`' options name (a dataset opens now, a bag is read as iterated), looped
    with ``--loop``."""
    source = functools.partial(open_source, ns.source, size=ns.size, stride=ns.stride, max_frames=ns.max_frames,
                               frame_id=ns.frame_id, depth_encoding=ns.depth_encoding,
                               topics=parse_topics(getattr(ns, "topic", [])))
    if not getattr(ns, "loop", False):
        return source()
    if getattr(ns, "gt_out", None) or getattr(ns, "finish", False):
        raise ValueError("--loop replays until stopped: --gt-out and --finish need an end")
    return looped(source(), source)


def player_from_args(ns: argparse.Namespace, **node_kwargs) -> Player:
    return Player(source_from_args(ns), rate=ns.rate, lockstep=ns.lockstep, timeout=ns.timeout,
                  wait_subscribers=ns.wait_subscribers, finish=getattr(ns, "finish", False),
                  finish_timeout=getattr(ns, "finish_timeout", 600.0), **node_kwargs)


def main(args=None) -> int:
    argv = sys.argv if args is None else ["gausem-player", *args]
    parser = argparse.ArgumentParser(prog="gausem-player", description=__doc__.split("\n")[0])
    add_player_arguments(parser)
    ns = parser.parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    player = None
    try:
        player = player_from_args(ns)
        while rclpy.ok() and not player.done:
            rclpy.spin_once(player, timeout_sec=0.1)
        linger_end = time.monotonic() + 1.0  # let reliable QoS deliver the last frame before the node goes
        while rclpy.ok() and time.monotonic() < linger_end:
            rclpy.spin_once(player, timeout_sec=0.1)
        player.get_logger().info(f"published {player.published} frames in {player.playback_seconds:.1f} s, "
                                 f"{player.odometry_received} odometry "
                                 f"messages received, {player.timeouts} lock-step timeouts")
        if ns.gt_out:
            player.get_logger().info(f"wrote {player.write_ground_truth(ns.gt_out)} ground-truth poses to {ns.gt_out}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as err:
        rclpy.logging.get_logger("gausem_player").error(str(err))
        return 1
    finally:
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown()
    return 1 if player is not None and player.error else 0


if __name__ == "__main__":
    raise SystemExit(main())
