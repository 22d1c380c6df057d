"""The executor every GauSem entry point spins its nodes on, and how such a process ends."""
from __future__ import annotations

import os
import sys

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


def exit_now(code: int) -> None:
    """End a command-line process whose nodes are destroyed and outputs written: the interpreter's own teardown of
    torch and DDS takes seconds, which a Ctrl-C should not wait for."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
