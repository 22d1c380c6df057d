"""What every GauSem node shares: parameter declaration (the SLAM configuration as ROS parameters), class tables,
dropped-input reporting (and the guard that turns an exception on one input into a drop), a one-slot newest-frame
queue and the ``main`` runner."""
from __future__ import annotations

import contextlib
import functools
import signal
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from types import SimpleNamespace

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions

from gausem_core.config import RENAMED, SlamConfig, flatten, from_flat
from gausem_core.data.classes import (NYU40_CLASSES, SCANNET20_CLASSES, SYNTHETIC_CLASSES, ClassTable,
                                      load_class_table)
from msg_adapters import make_header

from ..executor import NodeExecutor, exit_now
from ..qos import EVENT_QOS

CLASS_TABLES = {"synthetic": SYNTHETIC_CLASSES, "nyu40": NYU40_CLASSES, "scannet20": SCANNET20_CLASSES}
DIAGNOSTICS_TOPIC = "gausem/diagnostics"
LAST_FRAME_KEY = "last_frame_stamp_ns"  # tracking_mapping's diagnostics: stamp of the last frame it handled, in ns
_DYNAMIC = ParameterDescriptor(dynamic_typing=True)


def declare_slam_config(node, defaults: dict | None = None) -> SlamConfig:
    """Declare every SLAM parameter (dotted names of ``flatten(SlamConfig())``; ``defaults`` replaces some of their
    defaults, e.g. a live node's ``worker.mode``) and build the configuration from their values, so ``--params-file
    params/<dataset>.yaml`` configures a node like ``gausem run --params``.
    Types are checked by ``from_flat`` (an integer given for a float parameter is accepted), and so are old names
    (``config.RENAMED``): given one, the node fails naming the new name."""
    values = {name: node.declare_parameter(name, default, _DYNAMIC).value
              for name, default in {**flatten(SlamConfig()), **(defaults or {})}.items()}
    return from_flat({**values, **_given_old_names(node)})


def _given_old_names(node) -> dict:
    """The old names of renamed SLAM parameters that the node was given (a value set for them), with their values:
    each is declared only to be read, then undeclared."""
    given = {}
    for name in RENAMED:
        value = node.declare_parameter(name, None, _DYNAMIC).value
        node.undeclare_parameter(name)
        if value is not None:
            given[name] = value
    return given


def declare_parameters(node, defaults: dict) -> SimpleNamespace:
    """Declare node parameters with defaults (their types fix the parameter types); the values as attributes."""
    return SimpleNamespace(**{name: node.declare_parameter(name, default).value for name, default in defaults.items()})


def class_table(name: str) -> ClassTable:
    """A built-in table (synthetic, nyu40, scannet20) or a class-table file in any format the datasets read
    (:func:`~gausem_core.data.classes.load_class_table`: ``id name r g b`` lines, JSON, a palette)."""
    if name in CLASS_TABLES:
        return CLASS_TABLES[name]
    try:
        return load_class_table(name)
    except FileNotFoundError:
        raise ValueError(f"classes {name!r} is neither a built-in table ({', '.join(CLASS_TABLES)}) "
                         "nor an existing class-table file") from None


class FrameRejected(ValueError):
    """An input frame that a node drops: ``reason`` is a short counter key, the message says what was wrong."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


def survives_errors(handler: Callable | None = None, *, frame: bool = True) -> Callable:
    """Decorator for a method that handles one input, of a node or of a part of one (anything with ``get_logger()``
    and ``drops``): an exception it raises is logged (the traceback at debug level) and counted on ``drops`` as
    ``processing_error`` (a dropped frame, or with ``frame=False`` a rejected message), and the node goes on with the
    next input. ``@survives_errors`` or ``@survives_errors(frame=False)``."""
    if handler is None:
        return functools.partial(survives_errors, frame=frame)

    @functools.wraps(handler)
    def guarded(node, *args):
        try:
            return handler(node, *args)
        except Exception as err:  # noqa: BLE001 -- one input must never end the node
            count_error(node, handler.__name__, err, frame)
    return guarded


def count_error(node, name: str, err: Exception, frame: bool = True) -> None:
    """Log the exception ``err`` that the handler ``name`` raised (the traceback at debug level) and count it on
    ``node.drops`` as ``processing_error`` (:func:`survives_errors`)."""
    node.get_logger().debug(f"{name} failed:\n{traceback.format_exc()}")
    node.drops.drop("processing_error", f"{name}: {type(err).__name__}: {err}", frame=frame)


class AccountingLock:
    """A reentrant lock for counts that change in several steps (a node's input accounting): held by ``with`` (or
    :meth:`acquire` / :meth:`release`); :meth:`defer` runs an action (a report of the counts) at once when no other
    change is under way, else as the outermost holder lets go, so that what it reads is finished changes only."""

    def __init__(self):
        self._lock = threading.RLock()
        self._depth = 0  # how many times the holder holds it
        self._owed: Callable[[], None] | None = None

    def acquire(self, blocking: bool = True) -> bool:
        if not self._lock.acquire(blocking):
            return False
        self._depth += 1
        return True

    def release(self) -> None:
        try:
            if self._depth == 1 and self._owed is not None:
                owed, self._owed = self._owed, None
                owed()
        finally:
            self._depth -= 1
            self._lock.release()

    def __enter__(self) -> "AccountingLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def defer(self, action: Callable[[], None]) -> None:
        """Run ``action`` now if the caller holds the lock once, else when it lets go of the outermost hold."""
        with self:
            if self._depth == 2:
                action()
            else:
                self._owed = action


class DropReport:
    """Counts dropped inputs by reason, logs each reason's first drop and then at most one per ``log_period`` s, and
    publishes the counts (plus the node's ``status()`` values) as ``diagnostic_msgs/DiagnosticArray`` on
    gausem/diagnostics, after every drop and whenever the node calls ``publish``. Dropped frames (``frame=True``:
    the node's main input, e.g. a synchronised rgb-d frame) are ``dropped.<reason>``; other rejected messages
    (camera_info, records) are ``rejected.<reason>``. The level is WARN after a drop, else OK, raised to what the
    node's ``level()`` says (a DiagnosticStatus level and a message, e.g. ERROR "tracking lost"). Thread-safe:
    ``lock`` is held while a count changes and while a message is assembled, and a drop inside a longer change of the
    counts (``with lock``) is published when that change ends; a node that shares it with the other counters
    ``status()`` reads publishes counts of finished changes only."""

    def __init__(self, node, log_period: float = 5.0, status: Callable[[], dict] = dict,
                 level: Callable[[], tuple[int, str]] = lambda: (DiagnosticStatus.OK, ""),
                 lock: AccountingLock | None = None):
        self._node = node
        self._status = status
        self._level = level
        self._pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, EVENT_QOS)
        self._last_logged: dict[str, float] = {}
        self._log_period = log_period
        self._lock = lock or AccountingLock()
        self.counts: Counter[str] = Counter()  # dropped frames by reason
        self.rejected: Counter[str] = Counter()  # other rejected messages by reason

    def drop(self, reason: str, detail: str, frame: bool = True) -> None:
        with self._lock:
            counter = self.counts if frame else self.rejected
            counter[reason] += 1
            now = time.monotonic()
            if now - self._last_logged.get(reason, -float("inf")) >= self._log_period:
                self._last_logged[reason] = now
                what = "input" if frame else "message"
                self._node.get_logger().warning(f"dropped {what} ({reason}, {counter[reason]} so far): {detail}")
            self._lock.defer(self.publish)

    def clear(self) -> None:
        with self._lock:
            self.counts.clear()
            self.rejected.clear()

    def values(self) -> dict:
        """The counts and the node's status values, as published."""
        with self._lock:
            return {**{f"dropped.{k}": v for k, v in sorted(self.counts.items())},
                    **{f"rejected.{k}": v for k, v in sorted(self.rejected.items())}, **self._status()}

    def publish(self) -> None:
        with self._lock:
            values = self.values()
            dropped = sum(self.counts.values()) + sum(self.rejected.values())
            node_level, node_message = self._level()
            level = max(DiagnosticStatus.WARN if dropped else DiagnosticStatus.OK, node_level, key=ord)
            message = "; ".join(filter(None, [f"{dropped} inputs dropped", node_message]))
            status = DiagnosticStatus(level=level, name=self._node.get_fully_qualified_name(), message=message,
                                      values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
            stamp = self._node.get_clock().now().nanoseconds / 1e9
            self._pub.publish(DiagnosticArray(header=make_header(stamp, ""), status=[status]))


class NewestFrameQueue:
    """One pending frame: a newer one replaces it (``on_superseded`` is called with the old one). ``put`` may be
    called from an input callback group while a frame is being processed in another: processing runs from a guard
    condition, so a node that falls behind skips to the newest synchronised frame instead of queueing.
    ``process(item, arrived, skipped)`` gets the monotonic time the item was put and how many frames were skipped
    since the last item it got: those superseded here and those the node reported with :meth:`skip` (frames dropped
    before they were put), counted under one lock as the item is taken, so a frame dropped while another is being
    processed counts towards the next one. A frame dropped with a stamp newer than the pending frame's counts towards
    the frame after that one (a synchroniser may drop a newer frame before the pending one is taken). While
    ``ready()`` is false the pending frame waits; call :meth:`wake` when it may have become true. An item taken is
    :attr:`in_progress` until ``process`` calls :meth:`settle` (or returns); ``lock``: the queue's lock, an
    :class:`AccountingLock` a node shares with its other counters to read them in one piece."""

    def __init__(self, node, process: Callable, on_superseded: Callable, callback_group=None,
                 ready: Callable[[], bool] = lambda: True, lock: AccountingLock | None = None):
        self._process, self._on_superseded, self._ready = process, on_superseded, ready
        self._pending: tuple[object, float] | None = None
        self._pending_stamp: float | None = None
        self._skipped = 0  # frames superseded or reported skipped since the last item taken, before the pending one
        self._skipped_after = 0  # reported skipped with a stamp after the pending one's
        self._running = 0
        self._taken = False  # an item handed to process and not yet settled
        self._lock = lock or threading.Lock()
        self._guard = node.create_guard_condition(self._run, callback_group=callback_group)

    @property
    def pending(self) -> int:
        """Frames waiting to be processed (not the one in progress)."""
        return int(self._pending is not None)

    @property
    def in_progress(self) -> int:
        """Items taken and not yet settled (0 or 1)."""
        return int(self._taken)

    def settle(self) -> None:
        """The item in progress is accounted for (processed or dropped): no longer :attr:`in_progress`."""
        with self._lock:
            self._taken = False

    @property
    def idle(self) -> bool:
        """No frame pending and none in progress."""
        with self._lock:
            return self._pending is None and not self._running

    def put(self, item, stamp: float | None = None) -> None:
        with self._lock:
            old, self._pending = self._pending, (item, time.monotonic())
            self._pending_stamp = stamp
            self._skipped += (old is not None) + self._skipped_after
            self._skipped_after = 0
            idle = not self._running
        if old is not None:
            self._on_superseded(old[0])
        if idle:  # else _run triggers when done: a guard condition ready in a busy group would spin the executor
            self._guard.trigger()

    def skip(self, count: int = 1, stamp: float | None = None) -> None:
        """Count frames dropped before they reached the queue: the next item taken hears of them, or the one after it
        when ``stamp`` is newer than the pending item's."""
        with self._lock:
            pending = None if self._pending is None else self._pending_stamp
            if None not in (stamp, pending) and stamp > pending:
                self._skipped_after += count
            else:
                self._skipped += count

    def clear(self) -> None:
        with self._lock:
            self._pending, self._skipped, self._skipped_after = None, 0, 0

    def wake(self) -> None:
        """Process the pending frame now if it is waiting for ``ready()``."""
        with self._lock:
            waiting = self._pending is not None and not self._running
        if waiting:
            self._guard.trigger()

    def _run(self) -> None:
        with self._lock:
            if not self._ready():
                return
            entry, self._pending = self._pending, None
            if entry is None:
                return
            self._running += 1
            self._taken = True
            skipped, self._skipped, self._skipped_after = self._skipped, self._skipped_after, 0
        try:
            self._process(*entry, skipped)
        finally:
            with self._lock:
                self._running -= 1
                self._taken = False
                again = self._pending is not None
            if again:
                self._guard.trigger()


def _interrupt(signum, frame) -> None:
    """SIGTERM ends a node like Ctrl-C does."""
    raise KeyboardInterrupt


@contextlib.contextmanager
def ros_process(args=None):
    """``rclpy.init(args)`` for a command-line process whose spin loop SIGINT and SIGTERM end (as KeyboardInterrupt),
    not rclpy's own signal handlers: those shut the context down at once, under the nodes' live entities and the
    callback in progress (a node so ended under the launcher now and then died of SIGSEGV in a DDS thread, or its
    spin raised RCLError "context is not valid"). The caller finishes the frame in progress, shuts the executor
    down and destroys its nodes inside the block; the context shuts down after it."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        rclpy.try_shutdown()


def run_node(factory: Callable, args=None) -> int:
    """Build the node in a :func:`ros_process` and spin it on a multi-threaded executor (its callback groups decide
    what runs in parallel) until SIGINT or SIGTERM (a normal end: 0); 1 when the node cannot be built. At the end
    the frame in progress finishes early, the executor waits for it, and the node is destroyed."""
    node = None
    with ros_process(args):
        executor = NodeExecutor(num_threads=3)  # a thread each for tracking_mapping's groups: inputs, frames, map
        try:
            node = factory()
            executor.add_node(node)
            while rclpy.ok():
                executor.spin_once(timeout_sec=0.1)  # a signal is seen within 0.1 s
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except ValueError as err:  # a configuration the node cannot run with; the message says which
            rclpy.logging.get_logger("gausem").error(str(err))
            return 1
        finally:
            if hasattr(node, "interrupt"):  # a frame in progress finishes early
                node.interrupt()
            executor.shutdown()  # waits for the callback in progress
            if node is not None:
                node.destroy_node()
    if args is None:  # a command line
        exit_now(0)
    return 0
