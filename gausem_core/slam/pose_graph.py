"""Pose3 graphs with GTSAM (paper §III-C): intra-submap (keyframes) and inter-submap (anchors) loop correction.

Nodes carry cam_to_world (world-from-node) poses. An edge (a, b) measures the relative pose a^-1 b, GTSAM's
``BetweenFactorPose3`` convention. For an inter-submap loop found by registration, T_{s->t} (source-submap to
target-submap coordinates) equals A_t^-1 A_s for the anchors A_s, A_t, so it is the edge (target anchor, source anchor).

A chain may be broken into disconnected segments (a tracker that lost the map for good started a new one, with no
odometry to the old): :func:`optimise_chain` holds each segment that no loop joins to the first where it is, and moves
one that a loop joins onto it rigidly before optimising, as ORB-SLAM3's Atlas merges maps.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

ROBUST_KERNELS = {"huber": 1.345, "cauchy": 1.0, "none": None}  # name -> default kernel width (whitened units)


def _import_gtsam():
    try:
        import gtsam
    except ImportError as err:
        raise ImportError("pose graph optimisation needs gtsam>=4.3.0: pip install 'gausem[loop]'") from err
    return gtsam


@dataclass(frozen=True)
class PoseGraphResult:
    """Optimised cam_to_world poses (4x4 float64 numpy) by node key, and the graph error before and after."""

    poses: dict[int, np.ndarray]
    error_before: float
    error_after: float
    iterations: int


class PoseGraph:
    """A Pose3 graph: nodes with initial poses, odometry edges, robust loop edges, a prior on the first node.

    Sigmas are standard deviations of the relative-pose error, rotation in radians and translation in metres.
    ``robust_kernel``: "huber" (default), "cauchy" or "none", applied to loop edges with width ``robust_width``
    (default per kernel: Huber 1.345, Cauchy 1.0, in whitened units). Cauchy all but ignores loop edges whose
    initial residual is many sigmas (e.g. a drifted loop before closure), so it only suits loop sigmas as large as
    the expected drift; Huber closes such loops and still bounds an outlier's pull.
    """

    def __init__(self, *, odometry_sigmas: tuple[float, float] = (0.005, 0.02),
                 loop_sigmas: tuple[float, float] = (0.01, 0.05), robust_kernel: str = "huber",
                 robust_width: float | None = None, prior_sigmas: tuple[float, float] = (1e-6, 1e-6)):
        if robust_kernel not in ROBUST_KERNELS:
            raise ValueError(f"PoseGraph: robust_kernel must be one of {sorted(ROBUST_KERNELS)}, got {robust_kernel!r}")
        for name, sigmas in (("odometry_sigmas", odometry_sigmas), ("loop_sigmas", loop_sigmas),
                             ("prior_sigmas", prior_sigmas)):
            if len(sigmas) != 2 or min(sigmas) <= 0:
                raise ValueError(f"PoseGraph: {name} must be two positive values (rotation, translation), got {sigmas}")
        self._gtsam = gtsam = _import_gtsam()
        self._odometry_noise = self._diagonal(odometry_sigmas)
        self._prior_noise = self._diagonal(prior_sigmas)
        self._estimator = None
        if robust_kernel != "none":
            width = ROBUST_KERNELS[robust_kernel] if robust_width is None else robust_width
            if width <= 0:
                raise ValueError(f"PoseGraph: robust_width must be positive, got {width}")
            self._estimator = {"huber": gtsam.noiseModel.mEstimator.Huber,
                               "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust_kernel].Create(width)
        self._loop_noise = self._robust(loop_sigmas)
        self._graph = gtsam.NonlinearFactorGraph()
        self._initial = gtsam.Values()
        self._keys: list[int] = []

    def _diagonal(self, sigmas: tuple[float, float]):
        rot, trans = sigmas  # GTSAM's Pose3 tangent order is (rotation, translation)
        return self._gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [trans] * 3, dtype=np.float64))

    @staticmethod
    def _checked(sigmas, where: str) -> tuple[float, float]:
        if len(sigmas) != 2 or min(sigmas) <= 0:
            raise ValueError(f"PoseGraph.{where}: sigmas must be two positive values, got {sigmas}")
        return float(sigmas[0]), float(sigmas[1])

    def _robust(self, sigmas: tuple[float, float]):
        """The loop noise model: diagonal ``sigmas`` under the robust kernel (if any)."""
        noise = self._diagonal(sigmas)
        return noise if self._estimator is None else self._gtsam.noiseModel.Robust.Create(self._estimator, noise)

    @property
    def keys(self) -> list[int]:
        return list(self._keys)

    def add_node(self, key: int, cam_to_world) -> None:
        """A node with its initial world-from-node pose (4x4); the first node added is fixed by a prior."""
        if key in self._keys:
            raise ValueError(f"PoseGraph.add_node: node {key} already exists")
        pose = self._pose3(cam_to_world, f"node {key}")
        self._initial.insert(key, pose)
        if not self._keys:
            self._graph.add(self._gtsam.PriorFactorPose3(key, pose, self._prior_noise))
        self._keys.append(key)

    def fix(self, key: int) -> None:
        """Hold a node at its initial pose (a prior, as on the first node)."""
        if key not in self._keys:
            raise ValueError(f"PoseGraph.fix: unknown node {key}")
        self._graph.add(self._gtsam.PriorFactorPose3(key, self._initial.atPose3(key), self._prior_noise))

    def add_odometry(self, a: int, b: int, sigmas: tuple[float, float] | None = None) -> None:
        """An odometry edge a -> b measuring their current relative pose a^-1 b; ``sigmas`` (rotation, translation)
        replaces the graph's odometry sigmas for this edge (e.g. grown with the distance between the nodes)."""
        self._check_keys(a, b, "add_odometry")
        relative = self._initial.atPose3(a).between(self._initial.atPose3(b))
        noise = self._odometry_noise if sigmas is None else self._diagonal(self._checked(sigmas, "add_odometry"))
        self._graph.add(self._gtsam.BetweenFactorPose3(a, b, relative, noise))

    def add_loop(self, a: int, b: int, relative, sigmas: tuple[float, float] | None = None) -> None:
        """A loop edge a -> b with measured relative pose a^-1 b (4x4) under the robust loop noise; ``sigmas``
        (rotation, translation) replaces the graph's loop sigmas for this edge (e.g. a registration's uncertainty)."""
        self._check_keys(a, b, "add_loop")
        measured = self._pose3(relative, f"loop {a}->{b}")
        noise = self._loop_noise if sigmas is None else self._robust(self._checked(sigmas, "add_loop"))
        self._graph.add(self._gtsam.BetweenFactorPose3(a, b, measured, noise))

    def optimize(self, max_iterations: int = 100) -> PoseGraphResult:
        """Levenberg-Marquardt from the initial poses."""
        if not self._keys:
            raise ValueError("PoseGraph.optimize: the graph has no nodes")
        params = self._gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        optimizer = self._gtsam.LevenbergMarquardtOptimizer(self._graph, self._initial, params)
        result = optimizer.optimize()
        poses = {key: result.atPose3(key).matrix() for key in self._keys}
        return PoseGraphResult(poses, self._graph.error(self._initial), self._graph.error(result),
                               optimizer.iterations())

    def _check_keys(self, a: int, b: int, where: str) -> None:
        for key in (a, b):
            if key not in self._keys:
                raise ValueError(f"PoseGraph.{where}: unknown node {key}")
        if a == b:
            raise ValueError(f"PoseGraph.{where}: an edge needs two different nodes, got {a} twice")

    def _pose3(self, matrix, what: str):
        m = np.asarray(matrix.detach().cpu() if hasattr(matrix, "detach") else matrix, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ValueError(f"PoseGraph: {what} must be a finite 4x4 pose, got shape {m.shape}")
        if not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-5) or not np.allclose(m[3], [0, 0, 0, 1]):
            raise ValueError(f"PoseGraph: {what} is not a rigid transform")
        return self._gtsam.Pose3(m)


def optimise_chain(poses: Mapping[int, object], loops: Iterable[tuple[int, int, object, tuple[float, float]]],
                   odometry_sigmas: Callable[[int], tuple[float, float]], robust_kernel: str = "huber",
                   max_iterations: int = 100, breaks: Iterable[int] = ()) -> PoseGraphResult:
    """The graph of both loop-closure levels (keyframes of one submap, or submap anchors): ``poses`` (world-from-node
    by key) in key order, an odometry edge from each node to the next with ``odometry_sigmas(key of the first)``
    except into the ``breaks`` (nodes that start a disconnected segment), and the ``loops`` (a, b, measured a^-1 b,
    (rotation, translation) sigmas) as robust edges. The first node is fixed, and so is the first node of every
    segment that no loop joins to it; a segment a loop joins starts where that loop puts it (:func:`joined`)."""
    graph = PoseGraph(robust_kernel=robust_kernel)
    keys = sorted(poses)
    links = chain_links(keys, breaks)
    loops = list(loops)
    initial = joined(poses, links, loops)
    for key in keys:
        graph.add_node(key, initial[key])
    for a, b in links:
        graph.add_odometry(a, b, odometry_sigmas(a))
    for a, b, relative, sigmas in loops:
        graph.add_loop(a, b, relative, sigmas)
    groups = components(keys, links + [(a, b) for a, b, _, _ in loops])
    for group in groups[1:]:
        graph.fix(min(group))
    return graph.optimize(max_iterations)


def chain_links(keys: Sequence[int], breaks: Iterable[int]) -> list[tuple[int, int]]:
    """The odometry links of a chain of ``keys`` (in order): each node to the next, except into the ``breaks``."""
    breaks = set(breaks)
    return [(a, b) for a, b in zip(keys, keys[1:]) if b not in breaks]


def components(keys: Iterable[int], edges: Iterable[tuple[int, int]]) -> list[set[int]]:
    """The connected sets of ``keys`` under ``edges``, ordered by their smallest key."""
    parent = {key: key for key in keys}

    def root(key: int) -> int:
        while parent[key] != key:
            parent[key] = parent[parent[key]]
            key = parent[key]
        return key

    for a, b in edges:
        parent[root(a)] = root(b)
    groups: dict[int, set[int]] = {}
    for key in parent:
        groups.setdefault(root(key), set()).add(key)
    return sorted(groups.values(), key=min)


def joined(poses: Mapping[int, object], links: Iterable[tuple[int, int]],
           loops: Sequence[tuple[int, int, object, tuple[float, float]]]) -> dict[int, np.ndarray]:
    """``poses`` (float64 4x4) with each segment (nodes joined by ``links``) that a loop joins to the first node's
    moved rigidly so that the first such loop holds exactly; segments no loop reaches stay where they are."""
    out = {key: as_matrix(pose) for key, pose in poses.items()}
    segments = components(sorted(out), links)
    segment_of = {key: i for i, group in enumerate(segments) for key in group}
    placed = {segment_of[min(out)]} if out else set()
    moved = True
    while moved:
        moved = False
        for a, b, relative, _ in loops:
            relative = as_matrix(relative)
            if (segment_of[a] in placed) == (segment_of[b] in placed):
                continue
            if segment_of[a] in placed:  # b's segment goes where a^-1 b = relative
                change, other = out[a] @ relative @ np.linalg.inv(out[b]), segment_of[b]
            else:
                change, other = out[b] @ np.linalg.inv(relative) @ np.linalg.inv(out[a]), segment_of[a]
            for key in segments[other]:
                out[key] = change @ out[key]
            placed.add(other)
            moved = True
    return out


def as_matrix(pose) -> np.ndarray:
    """A pose (torch tensor or array) as a float64 4x4 array."""
    if hasattr(pose, "detach"):
        pose = pose.detach().cpu().double().numpy()
    return np.array(pose, dtype=np.float64)
