"""A recorded sequence played as a live camera (``gausem run --realtime RATE``): frames released on the wall clock at
RATE times their recorded rate, the consumer taking the newest one, the frames it never took counted as superseded.

The camera is a thread: it waits for each frame's release time and puts it into a one-frame slot, overwriting a frame
nobody took. So the tracker's cost alone decides how many frames it processes, as with a real camera. A camera hands
over decoded images, so the frames are read from the dataset before the clock starts, as many as fit in
``preload_bytes``; the rest are read by the camera's thread ahead of their release, where decoding and resizing them
(some 20 ms a frame at 160x120 on a 2-core CPU, most of a core at 30 Hz) competes with the system for the cores.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

PRELOAD_BYTES = 1 << 30  # frames read before the clock starts: 1 GiB, some 3000 frames at 160x120, 200 at 640x480


@dataclass
class Released:
    """A frame as the camera released it: its position in the dataset, the frame, the wall-clock release time
    (``time.perf_counter``) and how many frames were superseded (released, never taken) just before it."""

    position: int
    frame: object
    released_at: float
    superseded: int


class LiveCamera:
    """Releases ``dataset``'s frames at ``rate`` times their stamps' pace (2: twice as fast) from :meth:`start`;
    :meth:`take` returns the newest unseen frame, waiting for one, or None once the sequence has ended. :meth:`start`
    first reads the frames that fit in ``preload_bytes`` (before the clock starts; ``preloaded`` counts them)."""

    def __init__(self, dataset, rate: float, preload_bytes: int = PRELOAD_BYTES):
        if not rate > 0:
            raise ValueError(f"--realtime takes a positive rate (1: the recorded pace), got {rate}")
        self.dataset = dataset
        self.rate = rate
        self.preload_bytes = preload_bytes
        self._preloaded: list = []
        self.released = 0
        self.superseded = 0
        self.late_seconds = 0.0  # the most a frame was released after its time (reading slower than the camera)
        self._slot: Released | None = None
        self._ended = False
        self._stop = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._play, name="gausem-camera", daemon=True)
        self.started_at: float | None = None
        self.ended_at: float | None = None

    @property
    def preloaded(self) -> int:
        return len(self._preloaded)

    def start(self) -> None:
        self._preload()
        self.started_at = time.perf_counter()
        self._thread.start()

    def take(self) -> Released | None:
        """The newest released frame not yet taken (waiting for the next release), None after the last frame."""
        with self._cond:
            self._cond.wait_for(lambda: self._slot is not None or self._ended)
            item, self._slot = self._slot, None
            return item

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join()

    def _preload(self) -> None:
        for position in range(len(self.dataset)):
            frame = self.dataset[position]
            if (position + 1) * frame_bytes(frame) > self.preload_bytes:
                break
            self._preloaded.append(frame)

    def _play(self) -> None:
        first_stamp = None
        for position in range(len(self.dataset)):
            frame = self._preloaded[position] if position < self.preloaded else self.dataset[position]
            first_stamp = frame.timestamp if first_stamp is None else first_stamp
            due = self.started_at + (frame.timestamp - first_stamp) / self.rate
            with self._cond:
                if self._cond.wait_for(lambda: self._stop, max(due - time.perf_counter(), 0.0)):
                    break
                now = time.perf_counter()
                self.late_seconds = max(self.late_seconds, now - due)
                prior = self._slot
                self.superseded += prior is not None
                self._slot = Released(position, frame, now, 0 if prior is None else prior.superseded + 1)
                self.released += 1
                self._cond.notify_all()
        with self._cond:
            self._ended = True
            self.ended_at = time.perf_counter()
            self._cond.notify_all()


def frame_bytes(frame) -> int:
    """The memory a frame's images hold."""
    return sum(a.nbytes for a in (frame.rgb, frame.depth, frame.labels) if a is not None)
