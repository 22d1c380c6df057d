"""The executor every GauSem entry point spins its nodes on."""
from __future__ import annotations

from rclpy.executors import MultiThreadedExecutor


class NodeExecutor(MultiThreadedExecutor):
    """A multi-threaded executor (each node's callback groups decide what runs in parallel: a node's inputs keep
    arriving while it processes a frame, and nodes never wait for each other) whose ``shutdown`` returns only once
    the callbacks in progress are done, so nodes can be destroyed and maps saved safely (rclpy 7.1's does not
    wait for its worker threads)."""

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        done = super().shutdown(timeout_sec)
        self._executor.shutdown(wait=True)  # the worker pool: returns when the running callbacks have
        return done
