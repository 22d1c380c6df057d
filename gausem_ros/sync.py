"""Approximate-time synchronisation of N stamped inputs (e.g. rgb, depth and optional labels).

``ApproximateTimeSync`` is pure Python and independent of rclpy: feed it ``(input index, stamp, msg)`` and it calls
``callback(*msgs)`` with one message per input whose stamps lie within ``slop`` seconds of each other. Like
``message_filters.ApproximateTimeSynchronizer`` (Python), each new message is matched against the other inputs'
queues (at most ``queue_size`` each, oldest evicted) and every message takes part in at most one match. Unlike it,
among several valid sets the one with the smallest stamp spread wins, and after a match everything at or before the
matched stamps is dropped as stale (so late, out-of-order arrivals cannot produce a match that goes back in time).
A second message with a stamp already queued on the same input is dropped (the first is kept). Drops are counted by
reason in ``dropped``: ``stale``, ``duplicate``, ``overflow``.

``make_synchronizer`` subscribes a node to the inputs and uses ``message_filters`` when it is importable (it is not
on PyPI), otherwise ``ApproximateTimeSync``.
"""
from __future__ import annotations

import itertools
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

from msg_adapters.stamps import header_seconds


class ApproximateTimeSync:
    def __init__(self, num_inputs: int, callback: Callable[..., None], queue_size: int = 10, slop: float = 0.02):
        if num_inputs < 1 or queue_size < 1 or not slop >= 0:
            raise ValueError(f"ApproximateTimeSync needs num_inputs >= 1, queue_size >= 1 and slop >= 0, "
                             f"got {num_inputs}, {queue_size}, {slop}")
        self.callback, self.queue_size, self.slop = callback, queue_size, slop
        self._queues: list[dict[float, object]] = [{} for _ in range(num_inputs)]
        self._last_matched = [float("-inf")] * num_inputs
        self._lock = threading.Lock()
        self.dropped: Counter[str] = Counter()
        self.matched = 0

    def add(self, index: int, stamp: float, msg) -> None:
        """Queue ``msg`` stamped ``stamp`` seconds on input ``index``; emit a match if it completes one."""
        with self._lock:
            match = self._add(index, stamp, msg)
        if match is not None:
            self.callback(*match)

    def _add(self, index: int, stamp: float, msg):
        if not 0 <= index < len(self._queues):
            raise ValueError(f"input index {index} out of range 0..{len(self._queues) - 1}")
        queue = self._queues[index]
        if stamp <= self._last_matched[index]:
            self.dropped["stale"] += 1
            return None
        if stamp in queue:
            self.dropped["duplicate"] += 1
            return None
        queue[stamp] = msg
        if len(queue) > self.queue_size:
            del queue[min(queue)]
            self.dropped["overflow"] += 1
            if stamp not in queue:
                return None
        stamps = self._best_match(index, stamp)
        return None if stamps is None else self._take(stamps)

    def _best_match(self, index: int, stamp: float) -> tuple[float, ...] | None:
        candidates = [[stamp] if i == index else [s for s in q if abs(s - stamp) <= self.slop]
                      for i, q in enumerate(self._queues)]
        best = min(itertools.product(*candidates), key=lambda c: max(c) - min(c), default=None)
        return best if best is not None and max(best) - min(best) <= self.slop else None

    def _take(self, stamps: tuple[float, ...]) -> list:
        msgs = []
        for i, (queue, matched) in enumerate(zip(self._queues, stamps)):
            msgs.append(queue.pop(matched))
            for s in [s for s in queue if s <= matched]:
                del queue[s]
                self.dropped["stale"] += 1
            self._last_matched[i] = matched
        self.matched += 1
        return msgs


@dataclass
class SynchronizedInputs:
    """Keeps the subscriptions and the synchroniser of ``make_synchronizer`` alive."""

    synchronizer: object
    subscriptions: list


def _feed(sync: ApproximateTimeSync, index: int, msg) -> None:
    sync.add(index, header_seconds(msg.header), msg)


def make_synchronizer(node, inputs: Sequence[tuple[type, str]], callback: Callable[..., None], qos, *,
                      queue_size: int = 10, slop: float = 0.02, prefer_message_filters: bool = True
                      ) -> SynchronizedInputs:
    """Subscribe ``node`` to ``inputs`` ((msg type, topic) pairs, stamped messages) and call ``callback(*msgs)``
    with approximately synchronised messages, in the order of ``inputs``."""
    if prefer_message_filters:
        try:
            import message_filters
        except ImportError:
            pass
        else:
            subs = [message_filters.Subscriber(node, msg_type, topic, qos_profile=qos) for msg_type, topic in inputs]
            sync = message_filters.ApproximateTimeSynchronizer(subs, queue_size, slop)
            sync.registerCallback(callback)
            return SynchronizedInputs(sync, subs)
    sync = ApproximateTimeSync(len(inputs), callback, queue_size, slop)
    subs = [node.create_subscription(msg_type, topic, partial(_feed, sync, i), qos)
            for i, (msg_type, topic) in enumerate(inputs)]
    return SynchronizedInputs(sync, subs)
