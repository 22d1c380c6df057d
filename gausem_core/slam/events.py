"""What happened in a frame, as :meth:`GauSemSLAM.process <gausem_core.slam.system.GauSemSLAM.process>` reports it:
callers (the ROS node, the pipeline) learn of keyframes, submaps opened and closed, loops and map corrections from
these events instead of inspecting the system's state. Poses are the stored ones as float64 4x4 tensors on the CPU,
not projected onto SE(3) again: a pose graph elsewhere (the ROS pose_graph node) starts from exactly the poses the
core's own would (:meth:`LoopClosure.correct <gausem_core.slam.loop_closure.LoopClosure.correct>`), and tracking
amplifies differences of 1e-8 into millimetres within a few frames."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:  # loop_closure imports this module
    from gausem_core.slam.loop import PlaceSignature
    from gausem_core.slam.loop_closure import LoopOutcome


@dataclass(frozen=True)
class KeyframeState:
    """A keyframe with its current pose in its submap's frame and the submap's anchor (world-from-submap)."""

    frame_id: int
    submap_id: int
    timestamp: float
    pose: torch.Tensor
    anchor: torch.Tensor


@dataclass(frozen=True)
class SubmapChange:
    """A submap opened (``opened``) or closed (offloaded), with its first keyframe and its anchor."""

    submap_id: int
    first_keyframe: int
    anchor: torch.Tensor
    opened: bool


@dataclass(frozen=True)
class Correction:
    """A pose-graph answer applied to the map: how many anchors and keyframes moved, and the submaps whose keyframes
    moved (each re-mapped when a keyframe moved beyond the loop edges' sigma floors)."""

    anchors: int
    keyframes: int
    submaps: tuple[int, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.anchors or self.keyframes)


@dataclass(frozen=True)
class FrameEvents:
    """The events of one processed frame: the keyframe it made (if any), the submaps closed and opened (in that
    order) and the loop closure's outcome (detected, registered, accepted or not, the correction applied); when loops
    are detected elsewhere, instead, a loop keyframe's place signature (what that detector takes)."""

    keyframe: KeyframeState | None = None
    submaps: tuple[SubmapChange, ...] = ()
    loop: LoopOutcome | None = None
    place: PlaceSignature | None = None

