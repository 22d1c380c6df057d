"""End to end: GauSemSLAM with loop closure on the synthetic loop sequence with drifting odometry.

The tracker is replaced by odometry that integrates the true frame-to-frame motion with a constant bias (2 mm and
0.08 degrees per frame), so the drift is known and deterministic; mapping keeps the poses it is given, so the run
without loop closure is exactly that integration (checked on the first submap, which loop closure holds fixed). The
camera walks the loop (every 3rd frame, 80x60, stamped at 10 Hz) and then its first 60 frames again, revisiting where
it started: 20 processed frames, 6 intervals of the ground-truth-loop protocol, which counts the 30 Hz camera's frames.
"""
import math

import numpy as np
import pytest
import torch

from gausem_core.config import from_flat
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.data.frame import Frame
from gausem_core.eval.loops import DEFAULT_PROTOCOL, loop_scores, view_overlap
from gausem_core.eval.trajectory import absolute_trajectory_error
from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.io.trajectory import Trajectory
from gausem_core.semantics.source import UNLABELLED_PALETTE
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import TrackingResult

pytest.importorskip("gtsam")

STRIDE, REVISIT = 3, 20
RATE = 30.0 / STRIDE  # Hz: every STRIDE-th frame of the sequence's 30 Hz camera
BIAS = se3_exp(torch.tensor([0.002, 0.0, 0.0, 0.0, math.radians(0.08), 0.0]))
CONFIG = {"backend": "torch", "device": "cpu", "mapping.every": 2, "mapping.iterations": 5,
          "mapping.init_iterations": 20, "mapping.init_samples_fraction": 0.5, "mapping.optimise_poses": False,
          "submaps.policy": "motion", "submaps.motion_translation": 0.8, "submaps.motion_rotation_deg": 60.0,
          "submaps.boundary_iterations": 5, "loop.keyframe_every": 2, "loop.check_every": 3,
          "loop.odometry_sigma_rotation": 0.01,  # per keyframe: the injected drift is 0.16 degrees (0.003 rad)
          "loop.registration.downsample": 1, "loop.registration.pyramid_levels": 2, "refinement.enabled": False}


def rigid(pose: torch.Tensor) -> torch.Tensor:
    u, _, vt = torch.linalg.svd(pose[:3, :3].double())
    out = pose.clone()
    out[:3, :3] = (u @ vt).to(pose.dtype)
    return out


class DriftingOdometry:
    """The previous estimate composed with the true relative motion and the bias (in the active submap's frame)."""

    def __init__(self, slam: GauSemSLAM, truth: list[torch.Tensor]):
        self.slam, self.truth = slam, truth

    def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None) -> TrackingResult:
        n = len(self.slam.frames)
        world = self.slam.frames[-1].cam_to_world @ invert_pose(self.truth[n - 1]) @ self.truth[n] @ BIAS
        return TrackingResult(rigid(invert_pose(self.slam.active.anchor) @ world), 0.0, 0)


def integrate_odometry(truth: list[torch.Tensor]) -> list[torch.Tensor]:
    poses = [truth[0]]
    for before, after in zip(truth[:-1], truth[1:]):
        poses.append(rigid(poses[-1] @ invert_pose(before) @ after @ BIAS))
    return poses


def timestamps(count: int) -> np.ndarray:
    """The stamps :func:`drifting_run` gives its first ``count`` frames (seconds)."""
    return np.arange(count) / RATE


def ate_rmse(poses, truth) -> float:
    stamps = np.arange(len(truth))
    return absolute_trajectory_error(Trajectory(stamps, np.stack([p.double().numpy() for p in poses])),
                                     Trajectory(stamps, np.stack([p.double().numpy() for p in truth]))).rmse


def panned(frame: Frame, scene, degrees: float) -> Frame:
    """The frame seen from a camera turned ``degrees`` about its vertical axis (re-rendered)."""
    pose = frame.gt_pose @ se3_exp(torch.tensor([0, 0, 0, 0, math.radians(degrees), 0.0])).double().numpy()
    rgb, depth, labels = scene.render(pose, frame.camera)
    return Frame(frame.index, frame.timestamp, rgb, depth, labels, frame.camera, pose)


def revisit_frames(revisit: int = REVISIT, revisit_pan_deg: float = 0.0) -> tuple[SyntheticDataset, list[Frame]]:
    """The loop (every STRIDE-th frame, 80x60) and its first ``revisit`` frames again, turned ``revisit_pan_deg``
    (less overlap with the first visit)."""
    data = SyntheticDataset("loop", resolution=(80, 60), stride=STRIDE)
    frames = [data[i] for i in range(len(data))]
    frames += [panned(data[i], data.scene, revisit_pan_deg) if revisit_pan_deg else data[i] for i in range(revisit)]
    return data, frames


def drifting_run(revisit: int = REVISIT, overrides: dict | None = None, labelled: bool = True,
                 revisit_pan_deg: float = 0.0) -> tuple[GauSemSLAM, list[torch.Tensor]]:
    """SLAM with drifting odometry over :func:`revisit_frames`; returns the finished system and the ground-truth
    poses (first frame = identity). Without ``labelled`` every pixel has one class (as data without labels)."""
    _, frames = revisit_frames(revisit, revisit_pan_deg)
    first = torch.tensor(frames[0].gt_pose)
    truth = [(invert_pose(first) @ torch.tensor(f.gt_pose)).float() for f in frames]
    palette = SYNTHETIC_CLASSES.palette if labelled else UNLABELLED_PALETTE
    slam = GauSemSLAM(from_flat({**CONFIG, **(overrides or {})}), "cpu", len(palette))
    slam.front_end.tracker = DriftingOdometry(slam, truth)
    for n, f in enumerate(frames):
        labels = f.labels if labelled else np.zeros_like(f.labels)
        slam.process(Observation.from_arrays(f.rgb, f.depth, labels, f.camera, palette, n / RATE))
    slam.finish()
    return slam, truth


def true_view_overlap(data: SyntheticDataset, query: int, match: int) -> float:
    """Ground-truth overlap of two processed frames of :func:`drifting_run` (the sequence wraps around)."""
    observe = [Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette)
               for f in (data[match % len(data)], data[query % len(data)])]
    return view_overlap(observe[0], data[match % len(data)].gt_pose, observe[1], data[query % len(data)].gt_pose)


@pytest.mark.slow
@pytest.mark.parametrize("place_recognition, labelled", [("descriptor", True), ("auto", True), ("auto", False)])
def test_loop_closure_lowers_the_ate_of_a_drifting_run(place_recognition, labelled):
    """The paper's descriptor of the semantic image with labels, and (no DINOv2 weights: "auto") the bag of ORB
    words with and without labels. Every closed loop joins two views of one place, by ground-truth view overlap and
    by the paper's protocol, and the revisit is closed."""
    slam, truth = drifting_run(overrides={"loop.place_recognition": place_recognition}, labelled=labelled)
    assert slam.loop_closure.place_recognition == ("fallback" if place_recognition == "descriptor" else "bow")
    estimate = [pose for _, pose in slam.trajectory()]
    closed = slam.loop_closure.loops
    assert closed and all(not r.intra for r in closed)
    drifted = integrate_odometry(truth)
    in_first = [n for n, record in enumerate(slam.frames) if record.submap.submap_id == 0]
    assert len(in_first) > 5  # the first submap holds the world frame: loop closure leaves it where it was
    torch.testing.assert_close(torch.stack([estimate[n] for n in in_first]),
                               torch.stack([drifted[n] for n in in_first]), atol=1e-4, rtol=0)
    ate_without, ate_with = ate_rmse(drifted, truth), ate_rmse(estimate, truth)
    assert ate_with <= 0.5 * ate_without
    data = SyntheticDataset("loop", resolution=(80, 60), stride=STRIDE)
    assert all(true_view_overlap(data, r.query_frame, r.match_frame) >= 0.5 for r in closed)
    positions = np.stack([p[:3, 3].numpy() for p in truth])
    scores = loop_scores([(r.query_frame, r.match_frame) for r in closed], positions,
                         timestamps=timestamps(len(truth)), **DEFAULT_PROTOCOL)
    assert scores.precision == 1.0
    assert any(r.query_frame >= len(data) for r in closed)  # a loop from the revisit (frames len(data) on)


class JumpingOdometry:
    """The drifting odometry between the frames given (``index``: the current one's in the sequence), from the last
    frame recorded; while ``blind``, answers a metre off (the frame is lost and relocalisation fails)."""

    def __init__(self, slam: GauSemSLAM, truth: list[torch.Tensor]):
        self.slam, self.truth, self.backend = slam, truth, "torch"
        self.index, self.recorded, self.blind = 0, [], False  # sequence index of each recorded frame

    def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None) -> TrackingResult:
        last = self.recorded[-1]
        world = self.slam.frames[-1].cam_to_world @ invert_pose(self.truth[last]) @ self.truth[self.index] @ BIAS
        if self.blind:
            world = world @ se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0]))
        return TrackingResult(rigid(invert_pose(self.slam.active.anchor) @ world), 0.0, 0)


@pytest.mark.slow
def test_a_camera_that_jumps_starts_a_segment_that_the_revisit_merges():
    """The drifting run's walk with 15 processed frames (45 camera frames) never seen after frame 40, and the three
    before the gap lost: the tracker gives up, a new tracking segment starts at its last good pose, a sixth of the
    loop behind the camera, and the revisit's loop merges it into the first: one segment at the end, a loop between
    the two, and the ATE of the frames not lost within twice the drifting run's without the jump."""
    _, frames = revisit_frames()
    first = torch.tensor(frames[0].gt_pose)
    truth = [(invert_pose(first) @ torch.tensor(f.gt_pose)).float() for f in frames]
    cfg = from_flat({**CONFIG, "relocalisation.new_segment_after": 3, "tracking.feature_start.mode": "never"})
    slam = GauSemSLAM(cfg, "cpu", len(SYNTHETIC_CLASSES.palette))
    odometry = slam.front_end.tracker = JumpingOdometry(slam, truth)
    for n in [n for n in range(len(frames)) if not 41 <= n <= 55]:
        odometry.index, odometry.blind = n, 38 <= n <= 40
        recorded = len(slam.frames)
        f = frames[n]
        slam.process(Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette, n / RATE))
        odometry.recorded += [n] * (len(slam.frames) - recorded)
    slam.finish()
    starts = [s.submap_id for s in slam.submaps if s.starts_segment]
    assert len(starts) == 1 and slam.segments() == [{s.submap_id for s in slam.submaps}]
    assert any(min(r.query_submap, r.match_submap) < starts[0] <= max(r.query_submap, r.match_submap)
               for r in slam.loop_closure.loops), "no loop joined the segments"
    placed = [(record.cam_to_world, truth[n]) for record, n in zip(slam.frames, odometry.recorded, strict=True)
              if not record.lost]
    drifting, drift_truth = drifting_run()
    unbroken = ate_rmse([pose for _, pose in drifting.trajectory()], drift_truth)
    assert ate_rmse(*zip(*placed)) <= 2 * unbroken
