"""Loop-detection precision, recall and F1 with the ground-truth-loop protocol of the paper (§IV-C-2).

Frames are numbered as the camera took them and cut into consecutive intervals of ``interval`` (10) camera frames.
For two distinct intervals I and J, the admissible set is P = {(i, j) : i in I, j in J, |n_i - n_j| >
min_frame_gap} (Δt_min, camera frames n). The pair (I, J) is a ground-truth loop when P is not empty and max over P
of ||p_i - p_j|| < tau_loop (τ_loop, metres), p being ground-truth camera positions. A detected loop (k, j) is a
true positive when the intervals of k and j form a ground-truth loop (frames of one interval never do).

The paper counts the frames of 30 Hz cameras. A run that processes every 3rd frame (or a live node that drops
frames) would otherwise stretch each interval over three times the motion: with the frames' timestamps, a frame's
number is its time since the first frame times ``frame_rate``; without them, its index.

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


# the paper gives no values for Δt_min and τ_loop; these are ours (camera frames, metres); frame_rate: the camera's
DEFAULT_PROTOCOL = {"interval": 10, "min_frame_gap": 30, "tau_loop": 1.0, "frame_rate": 30.0}


def _check_positions(gt_positions) -> np.ndarray:
    positions = np.asarray(gt_positions, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or not np.isfinite(positions).all():
        raise ValueError(f"gt_positions must be a finite (N, 3) array, got shape {positions.shape}")
    return positions


def camera_frames(count: int, timestamps=None, frame_rate: float = 30.0) -> np.ndarray:
    """Each frame's number in the camera's own count: ``round((t - t_0) * frame_rate)``, or its index without
    timestamps."""
    if timestamps is None:
        return np.arange(count)
    stamps = np.asarray(timestamps, np.float64)
    if stamps.shape != (count,) or not np.isfinite(stamps).all() or (np.diff(stamps) < 0).any():
        raise ValueError(f"timestamps must be {count} finite, non-decreasing seconds, got shape {stamps.shape}")
    if frame_rate <= 0:
        raise ValueError(f"frame_rate must be > 0, got {frame_rate}")
    return np.rint((stamps - stamps[0]) * frame_rate).astype(np.int64) if count else np.zeros(0, np.int64)


def ground_truth_loops(gt_positions, *, min_frame_gap: int, tau_loop: float, interval: int = 10,
                       timestamps=None, frame_rate: float = 30.0) -> set[tuple[int, int]]:
    """Interval index pairs (a, b), a < b, that form ground-truth loops (interval a: camera frames a*interval ..
    a*interval+interval-1)."""
    positions = _check_positions(gt_positions)
    return _interval_loops(positions, camera_frames(len(positions), timestamps, frame_rate), min_frame_gap, tau_loop,
                           interval)


def _interval_loops(positions: np.ndarray, numbers: np.ndarray, min_frame_gap: int, tau_loop: float,
                    interval: int) -> set[tuple[int, int]]:
    """:func:`ground_truth_loops` of checked positions and their camera frame numbers."""
    if interval < 1 or min_frame_gap < 0 or tau_loop <= 0:
        raise ValueError(f"need interval >= 1, min_frame_gap >= 0, tau_loop > 0; got {interval}, "
                         f"{min_frame_gap}, {tau_loop}")
    groups = numbers // interval
    loops = set()
    for a in np.unique(groups):
        mine, later = groups == a, groups > a
        if not later.any():
            continue
        dist = np.linalg.norm(positions[mine][:, None] - positions[later][None], axis=-1)
        admissible = np.abs(numbers[mine][:, None] - numbers[later][None]) > min_frame_gap
        later_groups = groups[later]
        starts = np.flatnonzero(np.r_[True, later_groups[1:] != later_groups[:-1]])  # groups are sorted
        farthest = np.maximum.reduceat(np.where(admissible, dist, -np.inf).max(axis=0), starts)
        for b, far in zip(later_groups[starts], farthest):
            if np.isfinite(far) and far < tau_loop:  # -inf: no admissible pair
                loops.add((int(a), int(b)))
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


def loop_scores(detections, gt_positions, *, min_frame_gap: int, tau_loop: float, interval: int = 10,
                timestamps=None, frame_rate: float = 30.0) -> LoopScores:
    """Score detected loop frame pairs ``(k, j)`` (indices into ``gt_positions`` (N, 3) and ``timestamps``) against
    the ground truth."""
    positions = _check_positions(gt_positions)
    numbers = camera_frames(len(positions), timestamps, frame_rate)
    truth = _interval_loops(positions, numbers, min_frame_gap, tau_loop, interval)
    groups = numbers // interval
    pairs = [(int(k), int(j)) for k, j in detections]
    for k, j in pairs:
        if not (0 <= k < len(positions) and 0 <= j < len(positions)):
            raise ValueError(f"detected loop ({k}, {j}) refers to a frame outside 0..{len(positions) - 1}")
    hit = [(int(groups[min(k, j)]), int(groups[max(k, j)])) for k, j in pairs]
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
