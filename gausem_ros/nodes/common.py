"""What every GauSem node shares: parameter declaration (the SLAM configuration as ROS parameters), class tables,
dropped-input reporting (and the guard that turns an exception on one input into a drop), a one-slot newest-frame
queue and the ``main`` runner."""
from __future__ import annotations

import functools
import time
import traceback
from collections import Counter
from collections.abc import Callable
from types import SimpleNamespace

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException

from gausem_core.config import SlamConfig, flatten, from_flat
from gausem_core.data.classes import NYU40_CLASSES, SCANNET20_CLASSES, SYNTHETIC_CLASSES, ClassTable
from msg_adapters import make_header

from ..qos import EVENT_QOS

CLASS_TABLES = {"synthetic": SYNTHETIC_CLASSES, "nyu40": NYU40_CLASSES, "scannet20": SCANNET20_CLASSES}
DIAGNOSTICS_TOPIC = "gausem/diagnostics"
LAST_FRAME_KEY = "last_frame_stamp_ns"  # tracking_mapping's diagnostics: stamp of the last frame it handled, in ns
_DYNAMIC = ParameterDescriptor(dynamic_typing=True)


def declare_slam_config(node) -> SlamConfig:
    """Declare every SLAM parameter (dotted names of ``flatten(SlamConfig())``) and build the configuration from
    their values, so ``--params-file params/<dataset>.yaml`` configures a node like ``gausem run --params``.
    Types are checked by ``from_flat`` (an integer given for a float parameter is accepted)."""
    values = {name: node.declare_parameter(name, default, _DYNAMIC).value
              for name, default in flatten(SlamConfig()).items()}
    return from_flat(values)


def declare_parameters(node, defaults: dict) -> SimpleNamespace:
    """Declare node parameters with defaults (their types fix the parameter types); the values as attributes."""
    return SimpleNamespace(**{name: node.declare_parameter(name, default).value for name, default in defaults.items()})


def class_table(name: str) -> ClassTable:
    """A built-in table (synthetic, nyu40, scannet20) or a class-table file (``id name r g b`` lines)."""
    if name in CLASS_TABLES:
        return CLASS_TABLES[name]
    try:
        return ClassTable.load(name)
    except FileNotFoundError:
        raise ValueError(f"classes {name!r} is neither a built-in table ({', '.join(CLASS_TABLES)}) "
                         "nor an existing class-table file") from None


class FrameRejected(ValueError):
    """An input frame that a node drops: ``reason`` is a short counter key, the message says what was wrong."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


def survives_errors(handler: Callable) -> Callable:
    """Decorator for a node method that handles one input: an exception it raises is logged (the traceback at debug
    level) and counted on the node's ``drops`` as ``processing_error``, and the node goes on with the next input."""

    @functools.wraps(handler)
    def guarded(node, *args):
        try:
            return handler(node, *args)
        except Exception as err:  # noqa: BLE001 -- one input must never end the node
            node.get_logger().debug(f"{handler.__name__} failed:\n{traceback.format_exc()}")
            node.drops.drop("processing_error", f"{handler.__name__}: {type(err).__name__}: {err}")
    return guarded


class DropReport:
    """Counts dropped inputs by reason, logs each reason's first drop and then at most one per ``log_period`` s, and
    publishes the counts (plus the node's ``status()`` values) as ``diagnostic_msgs/DiagnosticArray`` on
    gausem/diagnostics, after every drop and whenever the node calls ``publish``."""

    def __init__(self, node, log_period: float = 5.0, status: Callable[[], dict] = dict):
        self._node = node
        self._status = status
        self._pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, EVENT_QOS)
        self._last_logged: dict[str, float] = {}
        self._log_period = log_period
        self.counts: Counter[str] = Counter()

    def drop(self, reason: str, detail: str) -> None:
        self.counts[reason] += 1
        now = time.monotonic()
        if now - self._last_logged.get(reason, -float("inf")) >= self._log_period:
            self._last_logged[reason] = now
            self._node.get_logger().warning(f"dropped input ({reason}, {self.counts[reason]} so far): {detail}")
        self.publish()

    def publish(self) -> None:
        values = {**{f"dropped.{k}": v for k, v in sorted(self.counts.items())}, **self._status()}
        level = DiagnosticStatus.WARN if self.counts else DiagnosticStatus.OK
        status = DiagnosticStatus(level=level, name=self._node.get_fully_qualified_name(),
                                  message=f"{sum(self.counts.values())} inputs dropped",
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        stamp = self._node.get_clock().now().nanoseconds / 1e9
        self._pub.publish(DiagnosticArray(header=make_header(stamp, ""), status=[status]))


class NewestFrameQueue:
    """One pending frame: a newer one replaces it (``on_superseded`` is called with the old one). Processing runs
    from a guard condition, so the executor delivers the messages that arrived meanwhile before the next frame is
    processed, and a node that falls behind skips to the newest synchronised frame instead of queueing."""

    def __init__(self, node, process: Callable, on_superseded: Callable):
        self._process, self._on_superseded = process, on_superseded
        self._pending = None
        self._guard = node.create_guard_condition(self._run)

    def put(self, item) -> None:
        if self._pending is not None:
            self._on_superseded(self._pending)
        self._pending = item
        self._guard.trigger()

    def clear(self) -> None:
        self._pending = None

    def _run(self) -> None:
        item, self._pending = self._pending, None
        if item is not None:
            self._process(item)


def run_node(factory: Callable, args=None) -> int:
    """``rclpy.init(args)``, build the node, spin until Ctrl-C or shutdown; 1 when the node cannot be built."""
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as err:  # a configuration the node cannot run with; the message says which
        rclpy.logging.get_logger("gausem").error(str(err))
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
