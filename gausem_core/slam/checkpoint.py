"""Periodic, crash-safe saves of a running session (``slam.persistence``): a tracker killed at any moment restarts
from its last checkpoint instead of an empty map.

A checkpoint is due once ``every_keyframes`` new keyframes were mapped since the last one, or ``period`` seconds
passed with new frames (either 0: that trigger is off). Writing one waits for the mapping worker (``save`` drains it)
and replaces the previous checkpoint atomically.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from gausem_core.slam.system import GauSemSLAM


def keyframe_count(slam: GauSemSLAM) -> int:
    return sum(len(submap.keyframes) for submap in slam.submaps)


@dataclass
class CheckpointStats:
    written: int = 0
    frames: int = 0  # frames in the last checkpoint
    seconds_last: float = 0.0  # what writing the last checkpoint cost
    seconds_total: float = 0.0


class Checkpointer:
    """Checkpoints one session folder; :meth:`start` after the map changes hands (a new or loaded map)."""

    def __init__(self, folder: str | Path, every_keyframes: int, period: float):
        if every_keyframes < 0 or period < 0:
            raise ValueError(f"checkpoint_keyframes and checkpoint_period must be >= 0 (0: off), got "
                             f"{every_keyframes} and {period}")
        self.folder = Path(folder)
        self.every_keyframes, self.period = every_keyframes, period
        self.stats = CheckpointStats()
        self._last = (0, 0, time.monotonic())  # keyframes and frames at the last checkpoint (or start), and when

    def start(self, slam: GauSemSLAM) -> None:
        """Count from ``slam``'s present state (nothing of it is new)."""
        self._last = (keyframe_count(slam), len(slam.frames), time.monotonic())

    def due(self, slam: GauSemSLAM) -> bool:
        keyframes, frames, when = self._last
        new_keyframes = keyframe_count(slam) - keyframes
        return bool((self.every_keyframes and new_keyframes >= self.every_keyframes)
                    or (self.period and len(slam.frames) > frames and time.monotonic() - when >= self.period))

    def write(self, slam: GauSemSLAM) -> float:
        """Save ``slam`` into the folder (crash-safe); the seconds it took."""
        begin = time.perf_counter()
        slam.save(self.folder)
        seconds = time.perf_counter() - begin
        self.start(slam)
        self.stats.written += 1
        self.stats.frames = len(slam.frames)
        self.stats.seconds_last = seconds
        self.stats.seconds_total += seconds
        return seconds
