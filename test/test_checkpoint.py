"""When a running session is checkpointed (slam.checkpoint): after new keyframes, after a period with new frames."""
import time
from types import SimpleNamespace

import pytest

from gausem_core.slam.checkpoint import Checkpointer


class Session(SimpleNamespace):
    """What the checkpointer reads of a system: submaps' keyframes, frames, save."""

    def __init__(self):
        super().__init__(submaps=[SimpleNamespace(keyframes=[0])], frames=[0], saved=[])

    def save(self, folder):
        self.saved.append((folder, len(self.frames)))


def test_a_checkpoint_is_due_after_enough_new_keyframes_and_counts_from_the_last_one(tmp_path):
    slam = Session()
    checkpoints = Checkpointer(tmp_path, every_keyframes=2, period=0.0)
    checkpoints.start(slam)
    slam.frames += [1, 2]
    slam.submaps[0].keyframes.append(2)
    assert not checkpoints.due(slam)
    slam.submaps.append(SimpleNamespace(keyframes=[3]))
    assert checkpoints.due(slam)
    assert checkpoints.write(slam) >= 0 and slam.saved == [(tmp_path, 3)]
    assert checkpoints.stats.written == 1 and checkpoints.stats.frames == 3 and not checkpoints.due(slam)


def test_a_period_checkpoint_needs_new_frames(tmp_path):
    slam = Session()
    checkpoints = Checkpointer(tmp_path, every_keyframes=0, period=0.05)
    checkpoints.start(slam)
    time.sleep(0.06)
    assert not checkpoints.due(slam)  # nothing new
    slam.frames.append(1)
    assert checkpoints.due(slam)


def test_negative_intervals_are_named():
    with pytest.raises(ValueError, match="checkpoint_keyframes and checkpoint_period"):
        Checkpointer("x", every_keyframes=-1, period=0.0)
