"""The mapping worker: the back end's keyframe jobs on a thread of their own, beside the tracker (``worker.mode:
async``).

Keyframes reach it through a bounded queue. When the queue is full, a new keyframe supersedes the newest one still
waiting (that frame stays a tracked frame; counted as ``superseded``), so the worker maps the freshest views instead
of falling ever further behind. While a newer keyframe waits, :attr:`pressure` is set: the mapper cuts the
optimisation in progress short (``worker.min_iteration_fraction``), the budget that keeps the worker level with the
keyframe rate. While none waits, the worker calls its ``idle`` work (anytime mapping: a short round of optimisation
over the newest keyframes' window) until that says it has nothing left to do, a new job arrives, or :meth:`drain`
holds it (until the next job: a caller that drained reads and changes the map undisturbed). Each job's result (the
keyframe's :class:`~gausem_core.slam.events.FrameEvents`) is collected for the tracker's caller (:meth:`take_events`),
with the worker's lag: frames the tracker processed between the keyframe's arrival and the end of its mapping.

A thread, not a process: the tracker reads the Gaussians the worker publishes without a copy (a cloud is replaced,
never edited in place, so a reference is a consistent snapshot), and the compiled kernels and torch's operators
release the interpreter lock. Each thread runs torch's intra-op work on its own share of the cores
(:func:`split_threads`).
"""
from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch


def split_threads(tracker: int, worker: int) -> tuple[int, int]:
    """Intra-op threads for the tracker and the worker: the values given, where 0 means half the cores each (the
    tracker's share rounded up, at least one each)."""
    cores = os.cpu_count() or 1
    return tracker or max(1, (cores + 1) // 2), worker or max(1, cores // 2)


@dataclass
class WorkerStats:
    """What the worker did: keyframes submitted, superseded in the queue and mapped; optimisations cut short under
    pressure; each mapped keyframe's lag (tracker frames between its arrival and its mapping's end)."""

    submitted: int = 0
    superseded: int = 0
    mapped: int = 0
    shortened: int = 0
    lag_frames: list[int] = field(default_factory=list)
    queue_peak: int = 0

    def summary(self) -> dict:
        lags = sorted(self.lag_frames)
        return {"keyframes_submitted": self.submitted, "keyframes_superseded": self.superseded,
                "keyframes_mapped": self.mapped, "optimisations_shortened": self.shortened,
                "queue_peak": self.queue_peak, "lag_frames_median": lags[len(lags) // 2] if lags else None,
                "lag_frames_max": lags[-1] if lags else None}


@dataclass
class Job:
    """One keyframe for the back end: ``run`` maps it and returns its events; ``frame`` is its frame id, ``kind`` says
    what it does ("open": a new map's first keyframe, which cannot be superseded; "keyframe")."""

    frame: int
    kind: str
    run: Callable[[], Any]


class MappingWorker:
    """A thread that runs :class:`Job` s in order from a queue of ``queue_size`` waiting jobs; ``frames()`` gives the
    tracker's current frame count (for the lag), ``threads`` the worker's intra-op threads; ``pressure`` is set while
    a newer job waits behind the one running (the mapper's, which then cuts its optimisations short)."""

    def __init__(self, frames: Callable[[], int], queue_size: int = 2, threads: int = 1,
                 pressure: threading.Event | None = None, idle: Callable[[], bool] | None = None):
        if queue_size < 1:
            raise ValueError(f"worker.queue_size must be >= 1, got {queue_size}")
        self.queue_size = queue_size
        self.stats = WorkerStats()
        self.pressure = pressure or threading.Event()  # a newer keyframe waits: cut the optimisation in progress short
        self._frames = frames
        self._threads = threads
        self._idle_work = idle  # a round of work between jobs; False when there is nothing left to do
        self._idle_done = True  # until the first job
        self._held = False  # drained: no idle work until the next job
        self._jobs: deque[Job] = deque()
        self._events: list = []
        self._error: BaseException | None = None
        self._busy = False
        self._stopping = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name="gausem-mapping", daemon=True)
        self._thread.start()

    def submit(self, job: Job) -> Job | None:
        """Queue ``job``; returns the waiting keyframe it superseded (the queue was full), if any."""
        self.raise_error()
        with self._cond:
            superseded = None
            if len(self._jobs) >= self.queue_size and self._jobs[-1].kind != "open":
                superseded = self._jobs.pop()
                self.stats.superseded += 1
            self._jobs.append(job)
            self._held, self._idle_done = False, self._idle_work is None
            self.stats.submitted += 1
            self.stats.queue_peak = max(self.stats.queue_peak, len(self._jobs))
            if self._busy:
                self.pressure.set()
            self._cond.notify_all()
            return superseded

    @property
    def depth(self) -> int:
        """Keyframes waiting (not counting the one being mapped)."""
        return len(self._jobs)

    @property
    def idle(self) -> bool:
        with self._cond:
            return not self._jobs and not self._busy

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every queued job is done (True), or ``timeout`` seconds pass (False), and hold idle work until
        the next job; re-raises a job's error."""
        with self._cond:
            self._held = True
            done = self._cond.wait_for(lambda: (not self._jobs and not self._busy) or self._error is not None,
                                       timeout)
        self.raise_error()
        return done

    def take_events(self) -> list:
        """The finished jobs' results since the last call, in order."""
        with self._cond:
            events, self._events = self._events, []
        return events

    def raise_error(self) -> None:
        """Re-raise (once) an error a job raised, in the caller's thread."""
        error, self._error = self._error, None
        if error is not None:
            raise RuntimeError(f"the mapping worker failed: {type(error).__name__}: {error}") from error

    def stop(self) -> None:
        """End the thread after the job in progress (queued jobs are dropped)."""
        with self._cond:
            self._stopping = True
            self._jobs.clear()
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    def _loop(self) -> None:
        torch.set_num_threads(self._threads)  # this thread's share (torch keeps the count per thread once set)
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._jobs or self._stopping or not (self._idle_done or self._held))
                if self._stopping:
                    return
                job = self._jobs.popleft() if self._jobs else None
                self._busy = True
                self.pressure.clear()
                if self._jobs:
                    self.pressure.set()
            if job is None:
                self._idle()
                continue
            events, error = _attempt(job.run)
            with self._cond:
                self._busy = False
                if error is not None:
                    self._error = error
                else:
                    self.stats.mapped += 1
                    self.stats.lag_frames.append(self._frames() - 1 - job.frame)
                    self._events.append(events)
                self._cond.notify_all()

    def _idle(self) -> None:
        """One round of idle work; an error is handed over as a job's is."""
        more, error = _attempt(self._idle_work)
        with self._cond:
            self._busy = False
            self._idle_done = not more
            if error is not None:
                self._error = error
            self._cond.notify_all()


def _attempt(run: Callable[[], Any]) -> tuple[Any, BaseException | None]:
    """``run()``'s result and None, or None and the error it raised (for the tracker's thread: raise_error)."""
    try:
        return run(), None
    except BaseException as exc:  # noqa: BLE001 -- handed over, not lost
        return None, exc
