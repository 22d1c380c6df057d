"""The executor every GauSem entry point spins its nodes on, and how such a process ends."""
from __future__ import annotations

import os
import sys
import time

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

    def retire_node(self, node, timeout_sec: float = 10.0) -> bool:
        """Remove ``node`` from a running executor and destroy it once none of its callbacks is in progress or queued
        on the worker threads (waiting up to ``timeout_sec``): destroyed under a running callback, its publishers
        fail mid-callback ('cannot use Destroyable'). Whether its callbacks ended in time. Call it from the thread
        that spins, between spins."""
        self.remove_node(node)
        end = time.monotonic() + timeout_sec
        while self._callbacks_pending(node) and time.monotonic() < end:
            time.sleep(0.005)
        ended = not self._callbacks_pending(node)
        node.destroy_node()
        return ended

    def _callbacks_pending(self, node) -> bool:
        with self._tasks_lock:
            return any(owner is node and not task.done() for task, _, owner in self._tasks)


def exit_now(code: int) -> None:
    """End a command-line process whose nodes are destroyed and outputs written: the interpreter's own teardown of
    torch and DDS takes seconds, which a Ctrl-C should not wait for."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
