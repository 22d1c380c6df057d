"""In-process ROS 2 test harness: one context per test on its own domain, bounded spinning, cleanup."""
from __future__ import annotations

import contextlib
import time

import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from gausem_ros.executor import NodeExecutor

# Few iterations, few Gaussians, one keyframe: a frame of 80x60 takes well under a second on a CPU core.
# a map of 3 initialisation iterations covers little of any view: without coverage_keyframes never, every frame after
# a gap would be a keyframe mapped in 2 iterations
FAST_SLAM = {"mapping.iterations": 2, "mapping.init_iterations": 3, "mapping.init_samples_fraction": 0.1,
             "mapping.every": 100, "mapping.coverage_keyframes": "never", "device": "cpu", "backend": "torch",
             "health.lost_coverage": 0.0}  # these maps are too thin to cover a view


def overrides(values: dict) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def ros_param_args(values: dict) -> list[str]:
    """The same values as ROS command-line arguments: ``-p name:=value`` pairs (to follow ``--ros-args``)."""
    return [arg for name, value in values.items() for arg in ("-p", f"{name}:={value}")]


@contextlib.contextmanager
def ros_session(domain_id: int):
    """(context, executor); every node added to the executor is destroyed before the context shuts down. The
    executor is multi-threaded, as in every GauSem entry point: nodes' callback groups run in parallel."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    executor = NodeExecutor(num_threads=4, context=ctx)
    try:
        yield ctx, executor
    finally:
        nodes = executor.get_nodes()
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


def spin_until(executor, condition, timeout: float) -> bool:
    """Spin until ``condition()`` holds or ``timeout`` s pass (or the context ends); whether it holds."""
    end = time.monotonic() + timeout
    while executor.context.ok() and not condition() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def spin_for(executor, seconds: float) -> None:
    spin_until(executor, lambda: False, seconds)


class Recorder:
    """A plain node that records every message on the given (type, topic, qos) subscriptions."""

    def __init__(self, ctx, subscriptions, name: str = "recorder"):
        self.node = rclpy.create_node(name, context=ctx)
        self.messages = {topic: [] for _, topic, _ in subscriptions}
        for msg_type, topic, qos in subscriptions:
            self.node.create_subscription(msg_type, topic, self.messages[topic].append, qos)
