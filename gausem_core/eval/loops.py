"""Loop-detection precision, recall and F1 with the ground-truth-loop protocol of the paper (§IV-C-2).

Frames ``0..N-1`` are cut into consecutive intervals of ``interval`` (10) frames (the last may be shorter). For two
distinct intervals I and J, the admissible set is P = {(i, j) : i in I, j in J, |i - j| > min_frame_gap}
(Δt_min). The pair (I, J) is a ground-truth loop when P is not empty and max over P of ||p_i - p_j|| < tau_loop
(τ_loop, metres), p being ground-truth camera positions. A detected loop (k, j) is a true positive when the
intervals of k and j form a ground-truth loop (frames of one interval never do).

Precision = true-positive detections / detections; recall = ground-truth loops hit by at least one detection /
ground-truth loops. An undefined ratio (nothing detected, no ground-truth loop) is NaN, and so is F1 then.

The protocol judges positions only, by whole intervals: it misses revisits seen from afar and calls a revisit false
when the rest of its interval is far away. :func:`view_overlap` measures what a loop needs instead: how much of one
view the other sees, from the two depth images and the ground-truth poses.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from gausem_core.geometry import invert_pose
from gausem_core.slam.observation import Observation
from gausem_core.slam.registration import warp_agreement


# the paper gives no values for Δt_min and τ_loop; these are ours (frames of the processed sequence, metres)
DEFAULT_PROTOCOL = {"interval": 10, "min_frame_gap": 30, "tau_loop": 1.0}


def _check_positions(gt_positions) -> np.ndarray:
    positions = np.asarray(gt_positions, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or not np.isfinite(positions).all():
        raise ValueError(f"gt_positions must be a finite (N, 3) array, got shape {positions.shape}")
    return positions


def ground_truth_loops(gt_positions, *, min_frame_gap: int, tau_loop: float,
                       interval: int = 10) -> set[tuple[int, int]]:
    """Interval index pairs (a, b), a < b, that form ground-truth loops (frames a*interval .. a*interval+interval-1)."""
    positions = _check_positions(gt_positions)
    if interval < 1 or min_frame_gap < 0 or tau_loop <= 0:
        raise ValueError(f"need interval >= 1, min_frame_gap >= 0, tau_loop > 0; got {interval}, "
                         f"{min_frame_gap}, {tau_loop}")
    count = math.ceil(len(positions) / interval)
    frames = np.arange(count * interval).reshape(count, interval)
    padded = np.full((count * interval, 3), np.nan)
    padded[: len(positions)] = positions
    padded = padded.reshape(count, interval, 3)
    exists = frames < len(positions)
    loops = set()
    for a in range(count - 1):
        dist = np.linalg.norm(padded[a][None, :, None] - padded[a + 1:][:, None], axis=-1)
        admissible = ((np.abs(frames[a][None, :, None] - frames[a + 1:][:, None]) > min_frame_gap)
                      & exists[a][None, :, None] & exists[a + 1:][:, None])
        farthest = np.where(admissible, dist, -np.inf).max(axis=(1, 2))
        hits = admissible.any(axis=(1, 2)) & (farthest < tau_loop)
        loops.update((a, a + 1 + int(k)) for k in np.flatnonzero(hits))
    return loops


@dataclass(frozen=True)
class LoopScores:
    precision: float
    recall: float
    f1: float
    detections: int
    true_positives: int
    ground_truth_loops: int
    ground_truth_loops_detected: int

    def as_dict(self) -> dict:
        return asdict(self)


def _ratio(num: int, den: int) -> float:
    return num / den if den else float("nan")


def _f1(precision: float, recall: float) -> float:
    if math.isnan(precision) or math.isnan(recall):
        return float("nan")
    return 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0


def loop_scores(detections, gt_positions, *, min_frame_gap: int, tau_loop: float, interval: int = 10) -> LoopScores:
    """Score detected loop frame pairs ``(k, j)`` (indices into ``gt_positions`` (N, 3)) against the ground truth."""
    positions = _check_positions(gt_positions)
    truth = ground_truth_loops(positions, min_frame_gap=min_frame_gap, tau_loop=tau_loop, interval=interval)
    pairs = [(int(k), int(j)) for k, j in detections]
    for k, j in pairs:
        if not (0 <= k < len(positions) and 0 <= j < len(positions)):
            raise ValueError(f"detected loop ({k}, {j}) refers to a frame outside 0..{len(positions) - 1}")
    hit = [(min(k, j) // interval, max(k, j) // interval) for k, j in pairs]
    true_positives = sum(pair in truth for pair in hit)
    detected = len(truth.intersection(hit))
    precision, recall = _ratio(true_positives, len(pairs)), _ratio(detected, len(truth))
    return LoopScores(precision, recall, _f1(precision, recall), len(pairs), true_positives, len(truth), detected)


def view_overlap(reference: Observation, reference_pose, current: Observation, current_pose,
                 max_depth_residual: float = 0.1) -> float:
    """Ground-truth view overlap: the fraction of the reference's valid-depth pixels that, moved by the ground-truth
    poses (cam_to_world 4x4), land in the current image on a depth reading within ``max_depth_residual``."""
    motion = invert_pose(torch.as_tensor(np.asarray(current_pose), dtype=torch.float64)) @ torch.as_tensor(
        np.asarray(reference_pose), dtype=torch.float64)
    overlap, fitness = warp_agreement(reference, current, motion.float(), max_depth_residual)
    return overlap * fitness
