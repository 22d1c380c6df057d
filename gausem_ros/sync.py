"""Approximate-time synchronisation of N stamped inputs (e.g. rgb, depth and optional labels), with every dropped
message accounted for.

``ApproximateTimeSync`` is pure Python and independent of rclpy: feed it ``(input index, stamp, msg)`` and it calls
``callback(*msgs)`` with one message per input whose stamps lie within ``slop`` seconds of each other. Like
``message_filters.ApproximateTimeSynchronizer`` (Python), each new message is matched against the other inputs'
queues (at most ``queue_size`` each, oldest evicted) and every message takes part in at most one match. Unlike it,
among several valid sets the one with the smallest stamp spread wins, after a match everything at or before the
matched stamps is dropped (so late, out-of-order arrivals cannot produce a match that goes back in time), and no
message disappears silently: each one is either matched, still queued (``pending``) or dropped, and every drop is
counted in ``dropped[(input name, reason)]`` and reported to ``on_drop(index, reason, detail, stamp)`` (the dropped
message's stamp in seconds; None for one never received). Reasons:

- ``backwards``: stamped at or before the last matched stamp of its input (out of order, or a replay restarted
  without :meth:`ApproximateTimeSync.reset`);
- ``duplicate``: a stamp already queued on the same input (the first is kept);
- ``unmatched``: left behind by a later match, evicted from a full queue or, by :meth:`ApproximateTimeSync.flush`,
  still waiting for its partners ``max_age`` seconds after it arrived (a lock-step replay sends no later match); the
  detail gives the nearest stamp offset seen on each other input, or ``no_<input>`` when that input has sent nothing;
- ``lost_in_transport``: never received, seen as a gap in the publisher's sequence numbers (``add``'s ``sequence``:
  the DDS publication sequence number of the message info, which rclpy hands to a two-argument callback); a
  subscription whose queue overflowed before the node took its messages loses them this way. Counted in ``lost``.

``lock``: a caller's reentrant lock held through each :meth:`~ApproximateTimeSync.add` and
:meth:`~ApproximateTimeSync.flush`, the callbacks included, so that a caller reading its own counts and these under
it sees every message in one place (received, queued, matched and handed on, or dropped).

``message_filters`` (not on PyPI) is not used: its synchroniser drops without telling.
"""
from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

from msg_adapters.stamps import header_seconds

from .qos import INPUT_QOS_HINT, subscribe_camera


class ApproximateTimeSync:
    def __init__(self, names: Sequence[str], callback: Callable[..., None], queue_size: int = 10,
                 slop: float = 0.02, on_drop: Callable[[int, str, str, float | None], None] = lambda *drop: None,
                 clock: Callable[[], float] = time.monotonic,
                 lock: contextlib.AbstractContextManager | None = None):
        if len(names) < 1 or queue_size < 1 or not slop >= 0:
            raise ValueError(f"ApproximateTimeSync needs at least one input, queue_size >= 1 and slop >= 0, "
                             f"got {list(names)}, {queue_size}, {slop}")
        self.names = list(names)
        self.callback, self.queue_size, self.slop, self.on_drop = callback, queue_size, slop, on_drop
        self.clock = clock  # when a message arrived (flush)
        self._lock = threading.Lock()
        self._outer = lock or contextlib.nullcontext()
        self.reset()

    def reset(self) -> None:
        """Forget every queued message, the stamp watermarks and the counts (a new sequence starts)."""
        with self._lock:
            self._queues: list[dict[float, tuple[object, float]]] = [{} for _ in self.names]  # stamp: (msg, arrival)
            self._last_matched = [float("-inf")] * len(self.names)
            self._first_arrival: float | None = None  # when the first message of any input arrived
            self.received = [0] * len(self.names)
            self.lost = [0] * len(self.names)  # messages never received (sequence-number gaps)
            self._sequences: list[int | None] = [None] * len(self.names)
            self.dropped: Counter[tuple[str, str]] = Counter()
            self.matched = 0

    def pending(self, index: int) -> int:
        """Messages of input ``index`` queued, waiting for a match."""
        return len(self._queues[index])

    def add(self, index: int, stamp: float, msg, sequence: int | None = None) -> None:
        """Queue ``msg`` stamped ``stamp`` seconds on input ``index`` (``sequence``: its publication sequence number,
        when known); emit a match if it completes one."""
        if not 0 <= index < len(self._queues):
            raise ValueError(f"input index {index} out of range 0..{len(self._queues) - 1}")
        drops: list[tuple[int, str, str, float | None]] = []
        with self._outer:
            with self._lock:
                self.received[index] += 1
                self._count_lost(index, sequence, drops)
                match = self._add(index, stamp, msg, drops)
                self._count(drops)
            for drop in drops:
                self.on_drop(*drop)
            if match is not None:
                self.callback(*match)

    def flush(self, max_age: float) -> None:
        """Drop, as unmatched, every message that arrived more than ``max_age`` seconds ago and is still waiting; and
        every waiting message while an input has delivered nothing in the ``max_age`` s since the first message of
        any arrived (a silent input: waiting for it would only delay each message by ``max_age``)."""
        drops: list[tuple[int, str, str, float | None]] = []
        with self._outer:
            with self._lock:
                now = self.clock()
                silent = not all(self.received) and self._first_arrival is not None and \
                    now - self._first_arrival >= max_age
                oldest = now if silent else now - max_age
                for index, queue in enumerate(self._queues):
                    for stamp in sorted(s for s, (_, arrived) in queue.items() if arrived < oldest or silent):
                        self._evict(index, stamp, drops)
                self._count(drops)
            for drop in drops:
                self.on_drop(*drop)

    def _count(self, drops: list) -> None:
        for i, reason, _, _ in drops:
            self.dropped[(self.names[i], reason)] += 1

    def _count_lost(self, index: int, sequence: int | None, drops: list) -> None:
        """Messages skipped in the publisher's sequence since the last one received (none after a restart of the
        sequence, e.g. a new publisher)."""
        last, self._sequences[index] = self._sequences[index], sequence
        if sequence is None or last is None or sequence <= last + 1:
            return
        gap = sequence - last - 1
        self.lost[index] += gap
        detail = (f"{gap} {self.names[index]} message(s) never arrived (publication sequence {last} -> {sequence}): "
                  "the subscription queue overflowed before they were taken, or the network lost them")
        drops.extend([(index, "lost_in_transport", detail, None)] * gap)

    def _add(self, index: int, stamp: float, msg, drops: list):
        queue, name = self._queues[index], self.names[index]
        if stamp <= self._last_matched[index]:
            drops.append((index, "backwards", f"{name} stamped {stamp:.6f} s is not after the last matched one "
                                              f"({self._last_matched[index]:.6f} s)", stamp))
            return None
        if stamp in queue:
            drops.append((index, "duplicate", f"{name} stamped {stamp:.6f} s arrived twice; the first is kept",
                          stamp))
            return None
        queue[stamp] = msg, self.clock()
        if self._first_arrival is None:
            self._first_arrival = queue[stamp][1]
        if len(queue) > self.queue_size:
            self._evict(index, min(queue), drops)
            if stamp not in queue:
                return None
        stamps = self._best_match(index, stamp)
        return None if stamps is None else self._take(stamps, drops)

    def _best_match(self, index: int, stamp: float) -> tuple[float, ...] | None:
        candidates = [[stamp] if i == index else [s for s in q if abs(s - stamp) <= self.slop]
                      for i, q in enumerate(self._queues)]
        best = min(itertools.product(*candidates), key=lambda c: max(c) - min(c), default=None)
        return best if best is not None and max(best) - min(best) <= self.slop else None

    def _take(self, stamps: tuple[float, ...], drops: list) -> list:
        msgs = []
        for i, (queue, matched) in enumerate(zip(self._queues, stamps)):
            msgs.append(queue.pop(matched)[0])
            for s in sorted(s for s in queue if s <= matched):
                self._evict(i, s, drops)
            self._last_matched[i] = matched
        self.matched += 1
        return msgs

    def _evict(self, index: int, stamp: float, drops: list) -> None:
        del self._queues[index][stamp]
        drops.append((index, "unmatched", f"{self.names[index]} stamped {stamp:.6f} s: {self._nearest(index, stamp)}",
                      stamp))

    def _nearest(self, index: int, stamp: float) -> str:
        """The nearest stamp offset seen on every other input (a silent input is named)."""
        parts = []
        for i, (name, queue) in enumerate(zip(self.names, self._queues)):
            if i == index:
                continue
            if not self.received[i]:
                parts.append(f"no {name} received at all")
                continue
            seen = list(queue) + [self._last_matched[i]]
            offset = min(abs(s - stamp) for s in seen)
            parts.append(f"nearest {name} {offset:.3f} s away")
        return ", ".join(parts) + f" (slop {self.slop} s)"


@dataclass
class SynchronizedInputs:
    """Keeps the subscriptions and the synchroniser of ``make_synchronizer`` alive."""

    synchronizer: ApproximateTimeSync
    subscriptions: list


def _feed(sync: ApproximateTimeSync, index: int, msg, info: dict) -> None:
    sync.add(index, header_seconds(msg.header), msg, info.get("publication_sequence_number"))


def make_synchronizer(node, inputs: Sequence[tuple[str, type, str]], callback: Callable[..., None], qos, *,
                      queue_size: int = 10, slop: float = 0.02,
                      on_drop: Callable[[int, str, str, float | None], None] = lambda *drop: None,
                      callback_group=None, lock: contextlib.AbstractContextManager | None = None
                      ) -> SynchronizedInputs:
    """Subscribe ``node`` to ``inputs`` ((name, msg type, topic), stamped messages) and call ``callback(*msgs)``
    with approximately synchronised messages, in the order of ``inputs`` (subscribed with :func:`subscribe_camera`);
    ``lock``: :class:`ApproximateTimeSync`'s."""
    sync = ApproximateTimeSync([name for name, _, _ in inputs], callback, queue_size, slop, on_drop, lock=lock)
    subs = [subscribe_camera(node, msg_type, topic, partial(_feed, sync, i), qos, callback_group, INPUT_QOS_HINT)
            for i, (_, msg_type, topic) in enumerate(inputs)]
    return SynchronizedInputs(sync, subs)
