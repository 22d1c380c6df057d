"""Resuming: with ``map_path`` set, the tracking node starts from the session saved there, or, when the folder holds
none yet, starts a new map there; either way it checkpoints the session into it (crash-safe, ``slam.checkpoint``)
every ``checkpoint_keyframes`` new keyframes or ``checkpoint_period`` seconds, so a tracker killed and respawned
(``gausem-launch --respawn``) goes on with the map of its last checkpoint, in the same ``map`` frame. The diagnostics
add ``checkpoint.written``, ``checkpoint.frames`` and ``checkpoint.seconds_last`` (what writing it cost)."""
from __future__ import annotations

from types import SimpleNamespace

from gausem_core.slam.checkpoint import Checkpointer, CheckpointStats
from gausem_core.slam.system import GauSemSLAM


class SessionCheckpoints:
    """Checkpoints of one map at a time (:meth:`reset` when the map changes hands) into ``map_path``."""

    def __init__(self, logger, params: SimpleNamespace):
        self._logger, self._folder = logger, params.map_path
        self._checkpointer = Checkpointer(params.map_path, params.checkpoint_keyframes, params.checkpoint_period)

    @property
    def stats(self) -> CheckpointStats:
        return self._checkpointer.stats

    def reset(self, slam: GauSemSLAM) -> None:
        """A new or loaded map: nothing in it is new yet."""
        self._slam = slam
        self._checkpointer.start(slam)

    def after_frame(self) -> None:
        """Write the session when a checkpoint is due; a failure is logged, the node goes on."""
        if not self._checkpointer.due(self._slam):
            return
        try:
            seconds = self._checkpointer.write(self._slam)
        except OSError as err:
            self._checkpointer.start(self._slam)  # tried again at the next interval, not at every frame
            self._logger.error(f"checkpoint: could not write to {self._folder}: {err}")
        else:
            self._logger.debug(f"checkpoint of {len(self._slam.frames)} frames in {seconds:.2f} s")

    def status(self) -> dict:
        """Checkpoints written, frames in the last one and what writing it cost."""
        stats = self.stats
        return {"checkpoint.written": stats.written, "checkpoint.frames": stats.frames,
                "checkpoint.seconds_last": stats.seconds_last}
