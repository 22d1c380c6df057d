"""Evaluating a ROS run like ``gausem run``: the outputs of the README's table through :mod:`gausem_core.report`.

The tracking node's :class:`GauSemSLAM` holds the estimate; ground truth and labels come from a *reference* dataset
(the dataset that was replayed, or the one a bag was made from with ``gausem-bag``), whose frames are matched to the
processed frames by timestamp. Like ``report.py`` this is evaluation code: besides the player, the only place in
gausem_ros that reads ground truth.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from gausem_core.config import SlamConfig
from gausem_core.data import Frame
from gausem_core.pipeline import RunResult
from gausem_core.report import write_outputs
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.system import GauSemSLAM

STAMP_TOLERANCE = 1e-6  # seconds; replayed stamps survive float -> Time -> float exactly (msg_adapters.stamps)


class ProcessedFrames:
    """The reference frames that were processed, in processing order: the dataset view ``write_outputs`` evaluates."""

    def __init__(self, frames: Sequence[Frame], name: str | None, class_table):
        self.frames, self.name, self.class_table = list(frames), name, class_table

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Frame:
        return self.frames[index]


def match_frames(reference: Iterable[Frame], stamps: Sequence[float],
                 tolerance: float = STAMP_TOLERANCE) -> list[Frame]:
    """The reference frame of every stamp, in the order of ``stamps``; reads ``reference`` only as far as needed.
    A ValueError names the stamps without a reference frame (a different dataset, size or frame range)."""
    wanted = np.asarray(stamps, dtype=np.float64)
    found: dict[int, Frame] = {}
    if len(wanted):
        for frame in reference:
            hits = np.flatnonzero(np.abs(wanted - frame.timestamp) <= tolerance)
            found.update({int(i): frame for i in hits})
            if len(found) == len(wanted):
                break
    missing = [float(wanted[i]) for i in range(len(wanted)) if i not in found]
    if missing:
        raise ValueError(f"{len(missing)} of {len(wanted)} processed frames have no reference frame within "
                         f"{tolerance} s (first stamps: {', '.join(f'{s:.6f}' for s in missing[:3])}); is the "
                         "reference the dataset the frames came from?")
    return [found[i] for i in range(len(wanted))]


def run_result(slam: GauSemSLAM, reference, seconds: float,
               health: Sequence[tuple[int, float, TrackingHealth]] = ()) -> tuple[RunResult, ProcessedFrames]:
    """The offline pipeline's :class:`RunResult` of a ROS run (``health``: (frame, stamp, health) of every frame
    given to the system), and the processed reference frames it refers to."""
    trajectory = slam.trajectory()
    stamps = [t for t, _ in trajectory]
    frames = ProcessedFrames(match_frames(reference, stamps), getattr(reference, "name", None),
                             getattr(reference, "class_table", None))
    poses = np.array([p.detach().cpu().double().numpy() for _, p in trajectory]).reshape(-1, 4, 4)
    return RunResult(slam, stamps, poses, [f.gt_pose for f in frames], [f.index for f in frames],
                     list(range(len(frames))), seconds, health=list(health)), frames


def write_report(slam: GauSemSLAM, cfg: SlamConfig, reference, out: str | Path, seconds: float, *,
                 health: Sequence[tuple[int, float, TrackingHealth]] = (), eval_every: int = 5,
                 params_file: str | None = None) -> dict:
    """Write the run's outputs (trajectories, keyframes, map PLY, metrics JSON, montage, plot, tracking status) to
    ``out``; the metrics. ``seconds``: the processing time behind the reported fps (``TrackingMappingNode.seconds``);
    ``health``: the per-frame tracking health (``TrackingMappingNode.health_log``)."""
    result, frames = run_result(slam, reference, seconds, health)
    return write_outputs(result, frames, cfg, out, eval_every=eval_every, params_file=params_file)
