"""The offline pipeline: owns IO, timing, progress, evaluation and export around :class:`GauSemSLAM`.

The CLI (``gausem run``) and the benchmarks use it; the ROS nodes use the same SLAM classes with messages as IO.
"""
from __future__ import annotations

import resource
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from tqdm import tqdm

from gausem_core.config import SlamConfig
from gausem_core.live import LiveCamera
from gausem_core.runtime import resolve_device
from gausem_core.semantics.source import FrameSemantics
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import FrameResult, GauSemSLAM


class RunObserver(Protocol):
    """Watches a run (e.g. :class:`gausem_core.viewer.Viewer`): each processed frame, then the end."""

    def frame(self, obs: Observation, result: FrameResult, slam: GauSemSLAM) -> None: ...

    def finish(self, slam: GauSemSLAM) -> None: ...


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class RunResult:
    slam: GauSemSLAM
    timestamps: list[float]
    poses: np.ndarray  # (N, 4, 4) cam_to_world estimates (final: after loop closure and the global refinement)
    gt_poses: list[np.ndarray | None]
    frame_ids: list[int]
    dataset_positions: list[int]  # each frame's i in ``dataset[i]`` (dropped frames leave gaps)
    seconds: float
    stats: list[dict] = field(default_factory=list)
    health: list[tuple[int, float, TrackingHealth]] = field(default_factory=list)  # (frame, timestamp, health) of
    # every frame given to the system, dropped ones included
    first_frame: int = 0  # the system's frame id of the first frame here, the next ones' counting on by one (dropped
    # frames get none); a resumed run's loaded session holds the ids before it
    tracked_poses: np.ndarray | None = None  # (N, 4, 4) each frame's pose as tracked, before later corrections moved it
    # (what a live subscriber got on gausem/odometry; what the frame's health judged, except at corrected_frames)
    corrected_frames: list[int] = field(default_factory=list)  # frames whose loop closure corrected the map: their
    # tracked pose above is already the corrected one
    frame_seconds: list[float] = field(default_factory=list)  # each processed frame's ``process`` call (wall time)
    map_ages: list[int] = field(default_factory=list)  # each processed frame's ``FrameResult.map_age``
    live: dict | None = None  # ``--realtime``: the camera's figures (released, superseded, latency; see live_summary)

    @property
    def fps(self) -> float:
        return len(self.frame_ids) / self.seconds if self.seconds > 0 else float("nan")


class Pipeline:
    """Run GauSem over a dataset (anything with ``__len__``, ``__getitem__`` -> Frame and ``class_table``).

    The class ids of each frame come from :attr:`semantics` (``semantics.segmenter``: the dataset's labels, or a
    segmenter that runs on every frame); a missing weights file is an error here, before any frame."""

    def __init__(self, dataset, cfg: SlamConfig, progress: bool = True):
        self.dataset = dataset
        self.cfg = cfg
        self.progress = progress
        self.device = resolve_device(cfg.device)
        self.semantics = FrameSemantics(dataset, cfg.semantics, self.device)
        self.palette = self.semantics.palette
        torch.manual_seed(cfg.seed)

    def observation(self, frame) -> Observation:
        return Observation.from_arrays(frame.rgb, frame.depth, self.semantics.labels(frame), frame.camera,
                                       self.palette, frame.timestamp, self.device)

    def run(self, slam: GauSemSLAM | None = None, save_session: Path | None = None,
            realtime: float | None = None, observer: RunObserver | None = None) -> RunResult:
        """Process the dataset with ``slam`` (a loaded session to go on with; default: a new system). The result
        holds this run's frames, less those a loaded system could not relocalise (dropped). ``save_session``: the
        session is saved there after the last frame, before the global refinement (not timed). Source frames that the
        dataset leaves out beyond its stride (e.g. a view of the frames a live node would see) reach the system as
        skipped ones. ``realtime``: the frames come from a :class:`~gausem_core.live.LiveCamera` at that rate, the
        newest each time, the superseded ones skipped (``RunResult.live``). ``observer``: told of every frame after the
        system processed it (its time counts in the run's), and of the end after the global refinement."""
        slam = slam or GauSemSLAM(self.cfg, self.device, num_classes=len(self.palette))
        first = len(slam.frames)
        gt, ids, dataset_positions, stats, health, tracked, corrected = [], [], [], [], [], [], []
        frame_seconds, map_ages, latencies = [], [], []
        camera = LiveCamera(self.dataset, realtime) if realtime is not None else None
        if camera is not None:
            camera.start()  # reads the frames it can hold first: the run's time starts with the camera's clock
        start = time.perf_counter()
        bar = tqdm(total=len(self.dataset), desc="gausem", unit="frame", disable=not self.progress)
        stride, last_index = getattr(self.dataset, "stride", 1), None
        for count, (i, frame, released_at) in enumerate(self._frames(camera), start=1):
            skipped = 0 if last_index is None else max((frame.index - last_index) // stride - 1, 0)
            last_index = frame.index
            began = time.perf_counter()
            obs = self.observation(frame)
            result = slam.process(obs, skipped)
            if observer is not None:
                observer.frame(obs, result, slam)
            done = time.perf_counter()
            frame_seconds.append(done - began)
            latencies.append(done - (began if released_at is None else released_at))
            health.append((frame.index, frame.timestamp, result.health))
            bar.update(i + 1 - bar.n)
            bar.set_postfix(fps=f"{count / (done - start):.2f}", loss=f"{result.tracking_loss:.4f}",
                            gaussians=result.num_gaussians, tracking=result.health.status)
            if any(events.loop is not None and events.loop.correction for events in (result.events, *result.mapped)):
                corrected.append(frame.index)  # its own or a finished keyframe's loop moved anchors or keyframes
            if result.relocalisation is not None and not result.relocalisation.accepted:
                continue
            map_ages.append(result.map_age)
            gt.append(frame.gt_pose)
            tracked.append(result.cam_to_world.detach().cpu().double().numpy())
            ids.append(frame.index)
            dataset_positions.append(i)
            stats.append({"frame": frame.index, "tracking_loss": result.tracking_loss,
                          "tracking_iterations": result.tracking_iterations, "mapping_loss": result.mapping_loss,
                          "gaussians": result.num_gaussians})
        bar.close()
        live = None if camera is None else live_summary(camera, latencies, ids)
        if save_session is not None:
            saving = time.perf_counter()
            slam.save(save_session)
            start += time.perf_counter() - saving
        slam.finish()  # global refinement after the last frame (part of the system's time)
        seconds = time.perf_counter() - start
        if observer is not None:
            observer.finish(slam)
        trajectory = slam.trajectory()[first:]
        poses = np.stack([p.detach().cpu().double().numpy() for _, p in trajectory])
        return RunResult(slam, [t for t, _ in trajectory], poses, gt, ids, dataset_positions, seconds, stats,
                         health, first, np.stack(tracked) if tracked else np.zeros((0, 4, 4)), corrected,
                         frame_seconds, map_ages, live)

    def _frames(self, camera: LiveCamera | None):
        """(dataset position, frame, release time or None) of each frame to process: every one in order, or the
        live camera's newest each time."""
        if camera is None:
            for i in range(len(self.dataset)):
                yield i, self.dataset[i], None
            return
        try:
            while (item := camera.take()) is not None:
                yield item.position, item.frame, item.released_at
        finally:
            camera.stop()


def percentile(values: Iterable[float], q: float) -> float | None:
    """The ``q``-quantile (0..1, nearest rank) of ``values``; None when empty."""
    ordered = sorted(values)
    return ordered[min(int(q * len(ordered)), len(ordered) - 1)] if ordered else None


def live_summary(camera: LiveCamera, latencies: list[float], processed: list[int]) -> dict:
    """A live replay's figures: frames released, processed, superseded; latency (release to pose) median and p95 in
    ms; the replay's duration; the camera's worst lateness (reading slower than its rate); the frames it read before
    its clock started."""
    duration = (camera.ended_at or time.perf_counter()) - camera.started_at
    return {"rate": camera.rate, "frames_released": camera.released, "frames_processed": len(processed),
            "frames_superseded": camera.superseded, "duration_s": duration,
            "latency_ms_median": 1e3 * percentile(latencies, 0.5) if latencies else None,
            "latency_ms_p95": 1e3 * percentile(latencies, 0.95) if latencies else None,
            "camera_late_ms_max": 1e3 * camera.late_seconds, "frames_preloaded": camera.preloaded}
