"""What tracking_mapping waits for, in ``loop_closure: nodes``, before it processes its next frame: loop_detection's
candidates for the loop keyframe it described last, then pose_graph's answer to the loop it registered from them.

Applying those answers before the next frame is what ``gausem run`` does within one call, so a lock-step replay gives
its loops and trajectory. An answer is awaited only while someone subscribes to the topic its question goes out on
(a helper node that is down is not waited for) and at most ``timeout`` seconds (0: never: answers are applied when
they arrive, which then depends on timing).
"""
from __future__ import annotations

import time
from collections.abc import Callable

_STAMP_TOLERANCE = 1e-6  # seconds: a stamp read back from a header


class LoopAnswers:
    """The answers awaited; ``detector_listens`` / ``graph_listens`` say whether loop_detection and pose_graph
    subscribe; ``on_timeout(what)`` is called when an answer is given up."""

    def __init__(self, timeout: float, detector_listens: Callable[[], bool], graph_listens: Callable[[], bool],
                 on_timeout: Callable[[str], None]):
        if timeout < 0:
            raise ValueError(f"loop_answer_timeout must be >= 0, got {timeout}")
        self.timeout = timeout
        self._listens = {"candidates": detector_listens, "pose_graph": graph_listens}
        self._on_timeout = on_timeout
        self.clear()

    def clear(self) -> None:
        """Await nothing (a new map)."""
        self._awaited = {"candidates": False, "pose_graph": False}
        self._keyframe_stamp = 0.0  # the keyframe whose candidates are awaited
        self._since = 0.0

    def expect_candidates(self, stamp: float) -> None:
        """A loop keyframe's place signature is about to go out."""
        self._expect("candidates")
        self._keyframe_stamp = stamp

    def candidates_arrived(self, stamp: float) -> None:
        """Candidates for the keyframe stamped ``stamp`` were handled."""
        if stamp >= self._keyframe_stamp - _STAMP_TOLERANCE:
            self._awaited["candidates"] = False

    def expect_pose_graph(self) -> None:
        """An accepted loop is about to go out to pose_graph."""
        self._expect("pose_graph")

    def pose_graph_arrived(self) -> None:
        self._awaited["pose_graph"] = False

    def settled(self) -> bool:
        """Whether nothing is awaited any more (an answer whose listener left, or past the timeout, is given up)."""
        for what in [w for w, awaited in self._awaited.items() if awaited]:
            if time.monotonic() - self._since > self.timeout:
                self._on_timeout(what)
            elif self._listens[what]():
                return False
            self._awaited[what] = False
        return True

    def _expect(self, what: str) -> None:
        self._awaited[what] = self.timeout > 0 and self._listens[what]()
        self._since = time.monotonic()
