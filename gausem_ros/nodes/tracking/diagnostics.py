"""What the tracking node adds to its ``gausem/diagnostics`` besides the drop counts (``dropped.<reason>``,
:class:`~gausem_ros.nodes.common.DropReport`).

Input accounting: ``frames_in``, ``frames_processed``, ``frames_pending``, the stamp of the last frame handled
(``last_frame_stamp_ns``: a lock-step player takes it as the answer for a frame that produced no odometry), the
latency from a synchronised frame's arrival to its pose's publication (``latency_ms.median`` / ``.p95`` over the last
100 frames; :meth:`TrackingMappingNode.summary` gives them for the whole run) and the depth and label messages the
synchroniser dropped (``sync.<input>.<reason>``). Tracking health (``gausem_core.slam.health``): the last frame's
``tracking.status`` (ok / degraded / lost) and signals (``tracking.inlier_fraction``, ...), which raise the level
(WARN degraded, ERROR lost). The camera: the estimated vignetting (``camera.vignetting_corner_gain``, brightness in
the image corners relative to the centre) and whether the frames are undistorted (``camera.undistorted``). The
mapping worker: ``worker.mode``, ``worker.queue_depth`` (keyframes waiting), ``worker.lag_frames`` (frames tracked
while the last keyframe was being mapped), ``worker.keyframes_superseded`` and ``worker.map_age_frames`` (frames
between the last frame and the newest keyframe of the map it was tracked against)."""
from __future__ import annotations

import math
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus

from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.system import FrameResult, GauSemSLAM

from ...sync import ApproximateTimeSync
from ..common import LAST_FRAME_KEY, AccountingLock, DropReport, NewestFrameQueue

HEALTH_LEVELS = {"ok": (DiagnosticStatus.OK, ""), "degraded": (DiagnosticStatus.WARN, "tracking degraded"),
                 "lost": (DiagnosticStatus.ERROR, "tracking lost")}


class FrameAccounting:
    """Every rgb image received: processed (a pose published; the latency from its arrival kept), pending (unmatched
    in the synchroniser, queued or in progress) or dropped (counted on the node's ``drops``). ``lock``: the one
    :class:`~gausem_ros.nodes.common.AccountingLock` that the synchroniser, the queue and ``drops`` were made with,
    held by every change of a count and by each reading of them, so that the counts read always add up."""

    def __init__(self, sync: ApproximateTimeSync, queue: NewestFrameQueue, drops: DropReport,
                 lock: AccountingLock):
        self._sync, self._queue, self._drops, self.lock = sync, queue, drops, lock
        self.processed = 0  # kept across load_map, cleared by gausem/reset
        self.latencies: list[float] = []  # seconds from a frame's arrival to its pose's publication
        self.handled_ns = -1  # stamp of the last synchronised frame handled (processed or dropped)

    def published(self, arrived: float) -> None:
        """The frame in progress had its pose published; it arrived at ``arrived`` (``time.monotonic``)."""
        with self.lock:
            self.processed += 1
            self._queue.settle()
            self.latencies.append(time.monotonic() - arrived)

    def dropped(self, reason: str, detail: str) -> None:
        """The frame in progress is dropped for ``reason``."""
        with self.lock:
            self._queue.settle()
            self._drops.drop(reason, detail)

    def clear(self) -> None:
        with self.lock:
            self.processed = 0
            self.latencies.clear()

    def pending(self) -> int:
        """Frames received and not yet processed or dropped: unmatched in the synchroniser, queued, in progress."""
        with self.lock:
            return self._sync.pending(0) + self._queue.pending + self._queue.in_progress

    def status(self, state: dict) -> dict:
        """The diagnostics' values: the counts, ``state`` (the core's and the checkpoints'), the latency over the last
        100 frames and the depth and label messages the synchroniser dropped."""
        with self.lock:
            return {"frames_in": self._frames_in(), "frames_processed": self.processed,
                    "frames_pending": self.pending(), LAST_FRAME_KEY: self.handled_ns, **state,
                    **latency_stats(self.latencies[-100:]),
                    **{f"sync.{name}.{reason}": n for (name, reason), n in sorted(self._sync.dropped.items())
                       if name != self._sync.names[0]}}

    def summary(self) -> dict:
        """The whole run's: frames in = processed + dropped (by reason) + pending; latency."""
        with self.lock:
            return {"frames_in": self._frames_in(), "frames_processed": self.processed,
                    "dropped": dict(sorted(self._drops.counts.items())), "frames_pending": self.pending(),
                    **latency_stats(self.latencies)}

    def _frames_in(self) -> int:
        """The rgb images received or lost in transport."""
        return self._sync.received[0] + self._sync.lost[0]


def latency_stats(latencies: list[float]) -> dict:
    """Median and 95th percentile of latencies in seconds, as ms (empty without any)."""
    if not latencies:
        return {}
    median, p95 = np.percentile(latencies, [50, 95])
    return {"latency_ms.median": round(1e3 * float(median), 1), "latency_ms.p95": round(1e3 * float(p95), 1)}


def core_status(slam: GauSemSLAM, health: TrackingHealth, map_age: int, undistorted: bool) -> dict:
    """The last frame's tracking health, the camera's vignetting and undistortion, the mapping worker's state, the
    map's separate tracking segments (1 once merged)."""
    status = {"tracking.status": health.status, **{f"tracking.{name}": v for name, v in health.signals().items()},
              "camera.vignetting_corner_gain": math.exp(slam.vignetting.a), "camera.undistorted": undistorted,
              "worker.mode": slam.cfg.worker.mode, "worker.map_age_frames": map_age,
              "map.segments": len(slam.segments())}
    worker = slam.worker
    if worker is not None:
        lags = worker.stats.lag_frames
        status.update({"worker.queue_depth": worker.depth, "worker.lag_frames": lags[-1] if lags else 0,
                       "worker.keyframes_superseded": worker.stats.superseded})
    return status


def unpublished(result: FrameResult, pose: np.ndarray, stamp: float) -> tuple[str, str] | None:
    """Why a frame the core took publishes nothing (the drop's reason and detail), None when it publishes its pose
    (float64 map-from-camera)."""
    reloc = result.relocalisation
    if reloc is not None and not reloc.accepted:
        return "relocalisation_failed", (f"frame stamped {stamp:.6f} s could not be placed against the map (inlier "
                                         f"fraction {reloc.inlier_fraction:.2f}); the next frame tries again")
    if result.health.status == "lost":
        return "tracking_lost", (f"frame stamped {stamp:.6f} s: tracking lost ({', '.join(result.health.reasons)}); "
                                 "not mapped, nothing published, the next frames are relocalised")
    if not np.isfinite(pose).all():
        return "tracking_diverged", (f"frame stamped {stamp:.6f} s: the estimated pose is not finite; nothing is "
                                     "published for it (reset with gausem/reset)")
    return None
