"""GauSemSLAM with submaps: allocation at keyframes, anchor chaining, offload/reload, trajectory and map coverage.

Tracking is replaced by an oracle that returns the ground-truth pose (in the active submap's frame), so these tests
exercise the submap machinery and do not depend on tracker accuracy; mapping runs for real, with tiny iteration counts.
"""
import threading
import time

import numpy as np
import pytest
import torch

from gausem_core.config import from_flat
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.geometry import invert_pose, rigid_product, se3_exp
from gausem_core.maps.occupancy import build_grid
from gausem_core.maps.slam_grid import KeyframeRays, floor_class_id, slam_grid
from gausem_core.slam.allocation import make_allocation, partition_keyframes
from gausem_core.slam.depth_filter import filter_observation
from gausem_core.slam.loop_graphs import PoseGraphUpdate
from gausem_core.slam.observation import Observation
from gausem_core.slam.submap import StoredObservation
from gausem_core.slam.system import GauSemSLAM
from gausem_core.slam.tracker import TrackingResult
from scripted_policy import script_submaps

CHEAP = {"backend": "torch", "loop.enabled": False, "mapping.iterations": 2, "mapping.init_iterations": 5,
         "mapping.init_samples_fraction": 0.25, "submaps.boundary_iterations": 2,
         # the oracle's poses are right; the thin maps of these settings would be judged lost
         "health.lost_inlier_fraction": 0.0, "health.lost_jump": 1e9, "health.lost_valid_depth": 0.0,
         "health.lost_coverage": 0.0}
SEQUENCE_STRIDE = 5  # the conftest's `sequence`: every 5th frame
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(),
                                                                                     reason="needs CUDA")])]


class OracleTracker:
    """Returns the ground-truth pose of the next frame in the active submap's frame."""

    def __init__(self, slam: GauSemSLAM, world_poses: list[torch.Tensor]):
        self.slam, self.world_poses = slam, world_poses

    def track(self, cloud, obs, init_cam_to_world, alternatives=(), search=False, keyframe=None) -> TrackingResult:
        world = self.world_poses[len(self.slam.frames)].to(self.slam.device)
        return TrackingResult(invert_pose(self.slam.active.anchor) @ world, 0.0, 0)


def run(sequence, count, overrides=None, switch_at=None, device="cpu", stored=None):
    """SLAM over the first ``count`` frames with oracle tracking (and a scripted policy switching at ``switch_at``);
    copies of what goes to the submap store are kept in ``stored`` when given."""
    observations, poses = sequence
    slam = GauSemSLAM(from_flat({**CHEAP, **(overrides or {})}), device, len(SYNTHETIC_CLASSES))
    slam.front_end.tracker = OracleTracker(slam, poses)
    if switch_at is not None:
        script_submaps(slam, (observations[i].timestamp for i in switch_at))
    if stored is not None:
        keep = slam.back_end.store.store

        def recording_store(key, tensors):
            stored[key] = {name: t.clone() for name, t in tensors.items()}
            keep(key, tensors)
        slam.back_end.store.store = recording_store
    inputs = [Observation(*(getattr(o, n).to(device) for n in ("rgb", "depth", "semantic", "labels")), o.camera,
                          o.timestamp) for o in observations[:count]]
    return slam, [slam.process(obs) for obs in inputs], inputs


def boundaries(submap_ids):
    return [k for k in range(1, len(submap_ids)) if submap_ids[k] != submap_ids[k - 1]]


def test_new_submaps_start_exactly_at_the_policy_decisions(sequence):
    slam, results, _ = run(sequence, 10, {"mapping.every": 2}, switch_at=[4, 8])
    assert [r.submap_id for r in results] == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2]
    assert [r.is_keyframe for r in results] == [i % 2 == 0 for i in range(10)]
    assert [r.allocation is not None and r.allocation.new for r in results] == [i in (4, 8) for i in range(10)]
    assert [[kf.frame_id for kf in s.keyframes] for s in slam.submaps] == [[0, 2], [4, 6], [8]]
    for submap in slam.submaps:  # the first keyframe anchors the submap: fixed at the identity
        assert submap.keyframes[0].fixed and torch.equal(submap.keyframes[0].cam_to_world, torch.eye(4))
        assert submap.num_gaussians == len(submap.cloud) > 0
    assert [s.is_active for s in slam.submaps] == [False, False, True]
    assert [f.submap.submap_id for f in slam.frames] == [r.submap_id for r in results]


def test_process_reports_keyframes_and_submaps_as_events(sequence):
    slam, results, inputs = run(sequence, 10, {"mapping.every": 2}, switch_at=[4, 8])
    keyframes = [r.events.keyframe for r in results]
    assert [k is not None for k in keyframes] == [r.is_keyframe for r in results]
    assert [(k.frame_id, k.submap_id, k.timestamp) for k in keyframes if k] == [
        (i, i // 4, inputs[i].timestamp) for i in (0, 2, 4, 6, 8)]
    changes = [(i, c.submap_id, c.first_keyframe, c.opened) for i, r in enumerate(results) for c in r.events.submaps]
    assert changes == [(0, 0, 0, True), (4, 0, 0, False), (4, 1, 4, True), (8, 1, 4, False), (8, 2, 8, True)]
    for result in results:
        for change in result.events.submaps:  # anchors as the system holds them, in float64
            anchor = slam.submaps[change.submap_id].anchor
            assert change.anchor.dtype == torch.float64 and torch.equal(change.anchor, anchor.double())
    kf = keyframes[6]  # its pose when it was made (bundle adjustment refines it later)
    assert torch.allclose(kf.anchor @ kf.pose, results[6].cam_to_world.double(), atol=1e-5)
    assert [(k.frame_id, k.submap_id) for k in slam.keyframe_states()] == [(0, 0), (2, 0), (4, 1), (6, 1), (8, 2)]
    assert all(r.events.loop is None for r in results)  # loop closure off


def test_apply_pose_graph_moves_anchors_and_keyframes_and_frames_follow(sequence):
    slam, _, _ = run(sequence, 10, {"mapping.every": 2, "loop.enabled": True, "loop.keyframe_every": 1000,
                                    "loop.remap_iterations_per_keyframe": 1}, switch_at=[6])
    before = [p.clone() for _, p in slam.trajectory()]
    shift = se3_exp(torch.tensor([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    moved_kf = slam.submaps[0].keyframes[1].cam_to_world.double() @ shift
    update = PoseGraphUpdate(keyframes={2: moved_kf.numpy(), 99: moved_kf.numpy()},
                             anchors={1: (shift @ slam.submaps[1].anchor.double()).numpy(), 7: shift.numpy()})
    correction = slam.apply_pose_graph(update)
    after = [p for _, p in slam.trajectory()]
    assert (correction.anchors, correction.keyframes, correction.submaps) == (1, 1, (0,))  # unknown ids ignored
    assert torch.allclose(slam.submaps[0].keyframes[1].cam_to_world.double(), moved_kf, atol=1e-6)
    for i in range(6, 10):  # frames of submap 1 follow its anchor
        assert torch.allclose(after[i].double(), shift @ before[i].double(), atol=1e-5)
    assert torch.allclose(after[0], before[0]) and torch.allclose(after[4], before[4])  # keyframe 0's frames stay
    assert torch.allclose(after[2].double(), before[2].double() @ shift, atol=1e-5)


def test_semantic_policy_in_the_loop_decides_as_on_its_own(sequence):
    """The system's boundaries are those of the allocation run alone on the same keyframes and poses."""
    observations, poses = sequence
    slam, results, _ = run(sequence, len(observations), {"mapping.every": 1})
    expected, _ = partition_keyframes(make_allocation(slam.cfg.submaps), list(zip(observations, poses)),
                                      len(SYNTHETIC_CLASSES))
    assert [r.submap_id for r in results] == expected
    assert len(boundaries(expected)) >= 2
    for k in boundaries(expected):
        assert results[k].allocation.new and "overlap" in results[k].allocation.reason


def test_anchors_chain_and_frames_follow_corrections(sequence):
    observations, poses = sequence
    slam, results, _ = run(sequence, 12, {"mapping.every": 2, "mapping.optimise_poses": False}, switch_at=[6])
    old, new = slam.submaps
    # the switch keyframe: tracked in the old submap, then the new submap's identity-fixed anchor keyframe
    assert torch.allclose(new.anchor, old.anchor @ (invert_pose(old.anchor) @ poses[6]), atol=1e-6)
    assert torch.allclose(results[6].cam_to_world, poses[6], atol=1e-5)
    for result, pose in zip(results, poses):  # every frame's world pose survives the switch
        assert torch.allclose(result.cam_to_world, pose, atol=1e-5)
    assert all(torch.allclose(p, q, atol=1e-5) for (_, p), q in zip(slam.trajectory(), poses))
    # later corrections move the frames that reference the corrected anchor / keyframe, and only those
    before = [p for _, p in slam.trajectory()]
    correction = se3_exp(torch.tensor([0.1, -0.2, 0.05, 0.02, 0.0, -0.03]))
    old.anchor = correction @ old.anchor
    old.keyframes[1].cam_to_world = old.keyframes[1].cam_to_world @ se3_exp(torch.tensor([0.0, 0.0, 0.1, 0, 0, 0]))
    after = [p for _, p in slam.trajectory()]
    for i in range(12):
        if i in (2, 3):  # referenced keyframe 2
            assert not torch.allclose(after[i], correction @ before[i], atol=1e-3)
        elif i < 6:
            assert torch.allclose(after[i], correction @ before[i], atol=1e-5)
        else:
            assert torch.equal(after[i], before[i])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("budget_mb, spilled", [(0.0, True), (64.0, False)])
def test_inactive_submaps_leave_the_device_and_come_back_bit_identical(sequence, device, budget_mb, spilled):
    stored = {}
    slam, _, inputs = run(sequence, 8, {"mapping.every": 2, "submaps.memory_budget_mb": budget_mb,
                                        "vignetting.calibrate": False},  # keyframes keep the frames' colour
                          switch_at=[4], device=device, stored=stored)
    closed, active = slam.submaps
    assert not closed.is_active and active.is_active and ("cloud", 0) in stored and ("cloud", 1) not in stored
    assert slam.back_end.store.on_disk(("cloud", 0)) is spilled
    for name, tensor in closed.load_cloud(device).tensors().items():
        assert tensor.device.type == device and torch.equal(tensor, stored[("cloud", 0)][name])
    assert all(t.device.type == "cpu" for t in closed.load_cloud().tensors().values())
    for kf in closed.keyframes:
        assert isinstance(kf.obs, StoredObservation) and kf.obs.timestamp == inputs[kf.frame_id].timestamp
        back = closed.observation(kf, device)
        kept = filter_observation(inputs[kf.frame_id], slam.cfg.depth_filter)  # what the system maps with
        for name in ("rgb", "depth", "semantic", "labels"):
            original = getattr(kept, name)
            assert getattr(back, name).dtype == original.dtype and torch.equal(getattr(back, name), original)
    assert all(t.device.type == device for t in active.cloud.tensors().values())
    # writing an inactive submap's Gaussians goes to the store
    moved = closed.load_cloud(device)
    moved.means += 1.0
    closed.cloud = moved
    assert torch.equal(closed.load_cloud().means, moved.means.cpu()) and not closed.is_active


def test_trajectory_and_global_cloud_cover_all_frames(sequence):
    observations, _ = sequence
    slam, results, _ = run(sequence, 9, {"mapping.every": 2, "submaps.memory_budget_mb": 0.0}, switch_at=[4, 6])
    assert [t for t, _ in slam.trajectory()] == [o.timestamp for o in observations[:9]]
    # keyframe BA (and the boundary BA at each switch) may since have refined the poses a little
    assert all(torch.allclose(p, r.cam_to_world, atol=0.05) for (_, p), r in zip(slam.trajectory(), results))
    store = slam.back_end.store
    spilled = [key for key in store.keys() if store.on_disk(key)]
    cloud = slam.global_cloud()
    sizes = [s.num_gaussians for s in slam.submaps]
    assert len(slam.submaps) == 3 and len(cloud) == sum(sizes)
    parts = torch.split(cloud.means, sizes)
    for submap, part in zip(slam.submaps, parts):
        assert torch.allclose(part, submap.load_cloud().transformed(submap.anchor).means)
    assert spilled and [key for key in store.keys() if store.on_disk(key)] == spilled  # read where they lie
    floor = floor_class_id(SYNTHETIC_CLASSES.names, "floor")  # the grid, read a submap at a time: the whole map's
    whole = build_grid(cloud, KeyframeRays(slam.cfg.grid.pixel_stride).views(slam), slam.cfg.grid,
                       cloud.class_ids(SYNTHETIC_CLASSES.palette) == floor)
    grid = slam_grid(slam, slam.cfg.grid, SYNTHETIC_CLASSES.palette, floor)
    assert np.array_equal(grid.cells, whole.cells) and np.array_equal(grid.floor.pose, whole.floor.pose)
    directory = slam.back_end.store.directory
    assert directory.is_dir()
    slam.close()
    assert not directory.exists()


def test_anchor_chains_stay_rigid():
    step = se3_exp(torch.tensor([0.31, -0.12, 0.05, 0.4, -0.7, 0.25]))
    naive = anchor = torch.eye(4)
    for _ in range(200):
        naive, anchor = naive @ step, rigid_product(anchor, step)

    def orthogonality(pose):
        return float((pose[:3, :3] @ pose[:3, :3].T - torch.eye(3)).abs().max())
    assert orthogonality(anchor) < 1e-6 < orthogonality(naive)
    assert anchor.dtype == torch.float32 and torch.allclose(anchor, naive, atol=1e-3)
    assert torch.equal(anchor[3], torch.tensor([0.0, 0, 0, 1]))


def test_boundary_settings_are_checked():
    with pytest.raises(ValueError, match="boundary_window"):
        GauSemSLAM(from_flat({"submaps.boundary_window": 0}))



def test_interrupt_cuts_the_frame_in_progress_short_and_leaves_a_consistent_map():
    """Ctrl-C in a live node: another thread interrupts a long optimisation, which stops at its next iteration; the
    frame is recorded and the next frame runs unhurried."""
    cfg = from_flat({**CHEAP, "device": "cpu", "mapping.init_iterations": 100000, "refinement.enabled": False})
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(SYNTHETIC_CLASSES))
    data = SyntheticDataset("default", resolution=(40, 30))
    obs = [Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette, f.timestamp)
           for f in (data[0], data[1])]
    threading.Timer(0.5, slam.interrupt).start()
    start = time.monotonic()
    slam.process(obs[0])  # 100000 initial iterations: many minutes, unless cut short
    assert time.monotonic() - start < 5.0
    assert len(slam.frames) == 1 and len(slam.active.cloud) > 0
    slam.process(obs[1])
    assert len(slam.frames) == 2 and not slam.back_end.mapper.hurry.is_set()
