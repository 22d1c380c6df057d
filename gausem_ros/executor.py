"""The executor every GauSem entry point spins its nodes on, and how such a process ends."""
from __future__ import annotations

import os
import sys

from rclpy.executors import MultiThreadedExecutor


class NodeExecutor(MultiThreadedExecutor):
    """A multi-threaded executor (each node's callback groups decide what runs in parallel: a node's inputs keep
    arriving while it processes a frame, and nodes never wait for each other) whose ``shutdown`` returns only once
    the callbacks in progress and queued are done, so nodes can be destroyed and maps saved safely. rclpy 7.1's does
    not wait for its worker threads, and destroys its guard condition under them: a queued callback's handler then
    fails on it ('cannot use Destroyable because destruction was requested', printed when the task is collected).
    Call it once nothing spins the executor any more."""

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        self._executor.shutdown(wait=True)  # the worker pool: its running and queued callbacks run to their end
        return super().shutdown(timeout_sec)


def exit_now(code: int) -> None:
    """End a command-line process whose nodes are destroyed and outputs written: the interpreter's own teardown of
    torch and DDS takes seconds, which a Ctrl-C should not wait for."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
