"""The loop-closure pose graphs of both levels (paper §III-C), one implementation for the core's loop closure and
the pose_graph node.

:class:`LoopGraphs` keeps the latest pose of every keyframe (in its submap's frame) and every submap anchor
(world-from-submap), and every accepted loop. Adding a loop re-optimises its level with GTSAM
(:func:`~gausem_core.slam.pose_graph.optimise_chain`): an intra-submap loop the keyframes of its submap, an
inter-submap loop the anchors, each with odometry edges between consecutive nodes (``loop.odometry_sigma_*``, grown
with the keyframes in between), the first node fixed, and every loop of that level so far as a robust edge
(``loop.robust_kernel``) with its registration's sigmas. The optimised poses replace the kept ones and come back as a
:class:`PoseGraphUpdate`, which the map applies (``GauSemSLAM.apply_pose_graph``). A submap that starts a new tracking
segment (the tracker lost the map for good) has no odometry edge to the one before: its segment is disconnected until
an inter-submap loop merges it (:meth:`LoopGraphs.connected`).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from gausem_core.config import LoopConfig
from gausem_core.slam.pose_graph import PoseGraph, as_matrix, chain_links, components, optimise_chain


@dataclass(frozen=True)
class PoseGraphUpdate:
    """Corrected poses (4x4 float64 arrays): ``keyframes`` in their submap's frame by frame id, ``anchors``
    (world-from-submap) by submap id."""

    keyframes: dict[int, np.ndarray] = field(default_factory=dict)
    anchors: dict[int, np.ndarray] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.keyframes or self.anchors)


def odometry_sigmas(cfg: LoopConfig, keyframes: int) -> tuple[float, float]:
    """Pose-graph odometry standard deviations (rotation, translation) over ``keyframes`` keyframe steps (random-walk
    growth from ``odometry_sigma_rotation`` / ``odometry_sigma_translation`` per step)."""
    scale = max(keyframes, 1) ** 0.5
    return cfg.odometry_sigma_rotation * scale, cfg.odometry_sigma_translation * scale


class LoopGraphs:
    """The keyframe graphs (one per submap) and the anchor graph, over the poses last given and the loops accepted.

    ``constraints``: the accepted loops (``LoopConstraint``), both levels, in order. Raises ValueError at
    construction on bad odometry sigmas or robust kernel.
    """

    def __init__(self, cfg: LoopConfig, max_iterations: int = 100):
        PoseGraph(odometry_sigmas=odometry_sigmas(cfg, 1), robust_kernel=cfg.robust_kernel)  # validates cfg now
        self.cfg = cfg
        self.max_iterations = max_iterations
        self.constraints: list = []
        self.keyframes: dict[int, tuple[int, np.ndarray]] = {}  # frame id -> (submap id, pose in the submap frame)
        self.anchors: dict[int, np.ndarray] = {}  # submap id -> world-from-submap
        self.breaks: set[int] = set()  # submaps that start a disconnected segment (no odometry edge from the previous)
        self.last_error: tuple[float, float] | None = None  # graph error before and after the last optimisation

    def set_keyframe(self, frame_id: int, submap_id: int, pose) -> None:
        """The latest pose of a keyframe in its submap's frame."""
        self.keyframes[int(frame_id)] = (int(submap_id), as_matrix(pose))

    def set_anchor(self, submap_id: int, anchor, starts_segment: bool = False) -> None:
        """The latest anchor (world-from-submap) of a submap, and whether it starts a disconnected segment."""
        self.anchors[int(submap_id)] = as_matrix(anchor)
        (self.breaks.add if starts_segment else self.breaks.discard)(int(submap_id))

    def segments(self) -> list[set[int]]:
        """The submaps in groups that odometry and accepted loops connect (one group once every segment is merged)."""
        keys = sorted(self.anchors)
        loops = [(c.submap_a, c.submap_b) for c in self.constraints if not c.intra]
        return components(keys, chain_links(keys, self.breaks) + loops)

    def connected(self, a: int, b: int) -> bool:
        """Whether submaps ``a`` and ``b`` are in one segment (or merged ones): a loop between them can be judged
        against their current relative pose; between unmerged segments that pose is only a guess."""
        return any(a in group and b in group for group in self.segments())

    def missing(self, constraint) -> list[str]:
        """The nodes of a loop this graph does not know (e.g. ``keyframe 12``, ``submap 3``)."""
        if constraint.intra:
            return [f"keyframe {k}" for k in (constraint.keyframe_a, constraint.keyframe_b)
                    if self.keyframes.get(k, (None,))[0] != constraint.submap_a]
        return [f"submap {s}" for s in (constraint.submap_a, constraint.submap_b) if s not in self.anchors]

    def add(self, constraint) -> PoseGraphUpdate:
        """Add an accepted loop, re-optimise its level and return the corrected poses (kept here too). Raises
        ValueError, keeping nothing, for a loop naming unknown nodes or one that the graph cannot take."""
        missing = self.missing(constraint)
        if missing:
            raise ValueError(f"loop {constraint.keyframe_a}-{constraint.keyframe_b}: unknown {', '.join(missing)}")
        self.constraints.append(constraint)
        try:
            if constraint.intra:
                submap = constraint.submap_a
                poses = {k: pose for k, (s, pose) in self.keyframes.items() if s == submap}
                optimised = self._optimise(poses, lambda _: odometry_sigmas(self.cfg, 1), True, submap)
                self.keyframes.update({k: (submap, pose) for k, pose in optimised.items()})
                return PoseGraphUpdate(keyframes=optimised)
            counts = Counter(s for s, _ in self.keyframes.values())
            optimised = self._optimise(self.anchors, lambda s: odometry_sigmas(self.cfg, counts[s]), False,
                                       breaks=self.breaks)
            self.anchors.update(optimised)
            return PoseGraphUpdate(anchors=optimised)
        except ValueError:
            self.constraints.pop()
            raise

    def _optimise(self, poses: dict, sigmas, intra: bool, submap: int | None = None,
                  breaks: set[int] = frozenset()) -> dict[int, np.ndarray]:
        loops = [c.edge for c in self.constraints if c.intra == intra and (not intra or c.submap_a == submap)]
        result = optimise_chain(poses, loops, sigmas, self.cfg.robust_kernel, self.max_iterations, breaks)
        self.last_error = (result.error_before, result.error_after)
        return result.poses

