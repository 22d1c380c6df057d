"""Two-stage global refinement: per-submap L_refine optimisation, then alignment of submaps to the global map."""
import pytest
import torch

from gausem_core.config import MappingConfig, RefinementConfig, RegistrationConfig
from gausem_core.semantics.descriptors import make_descriptor
from gausem_core.slam.mapper import Mapper
from gausem_core.slam.refinement import align_to_global, global_refinement, refine_submap
from loop_scene import frame, make_submap, perturbation, pose_error


def test_stage_one_lowers_the_refinement_loss_and_keeps_the_fixed_keyframe():
    submap = make_submap(0, [0, 4, 8], size=(80, 60))
    truth = [kf.cam_to_world.clone() for kf in submap.keyframes]
    observations = [kf.obs for kf in submap.keyframes]
    cloud, losses = refine_submap(submap.cloud, submap.keyframes, observations, Mapper(MappingConfig()), 6,
                                  make_descriptor("fallback"), 0.5, backend="torch")
    assert len(losses) == 6 and losses[-1] < 0.8 * losses[0]
    assert 0 < len(cloud) <= len(submap.cloud)
    assert torch.equal(submap.keyframes[0].cam_to_world, truth[0])
    for kf, pose in zip(submap.keyframes[1:], truth[1:]):
        translation, rotation = pose_error(kf.cam_to_world, pose)
        assert translation < 0.01 and rotation < 0.5  # the poses were right: the refinement keeps them


def test_stage_two_aligns_a_misplaced_submap_to_the_others():
    reference = make_submap(0, [0, 6, 12, 18])
    misplaced = make_submap(1, [9, 15, 21, 27])
    truth = misplaced.anchor.clone()
    misplaced.anchor = perturbation(0.05, 2.5, 7).float() @ truth
    before = pose_error(misplaced.anchor, truth)
    assert align_to_global(misplaced, [reference], RegistrationConfig(), make_descriptor("fallback"), "torch")
    after = pose_error(misplaced.anchor, truth)
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]
    assert not align_to_global(misplaced, [], RegistrationConfig(), None, "torch")  # nothing to align to


def test_global_refinement_runs_both_stages_and_holds_the_first_submap():
    first = make_submap(0, [0, 6, 12], size=(80, 60))
    second = make_submap(1, [9, 15, 21], size=(80, 60))
    second.anchor = perturbation(0.04, 2.0, 8).float() @ frame(9, 80, 60)[1]
    anchor = first.anchor.clone()
    before = pose_error(second.anchor, frame(9, 80, 60)[1])
    report = global_refinement([first, second], Mapper(MappingConfig()), RefinementConfig(iterations_per_keyframe=2),
                               RegistrationConfig(downsample=1), make_descriptor("fallback"), "torch")
    assert set(report.first_pass_loss) == set(report.last_pass_loss) == {0, 1}
    assert report.aligned == {1: True}
    assert torch.equal(first.anchor, anchor)
    after = pose_error(second.anchor, frame(9, 80, 60)[1])
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]


def test_the_system_refines_after_the_last_frame_with_or_without_loop_closure():
    """``loop.enabled`` and ``refinement.enabled`` are separate ablations (paper Tab. VIII)."""
    from gausem_core.config import load_config
    from gausem_core.data import open_dataset
    from gausem_core.pipeline import Pipeline
    from gausem_core.slam.system import GauSemSLAM

    means = {}
    for refine in (True, False):
        cfg = load_config(None, {"loop.enabled": False, "refinement.enabled": refine, "device": "cpu",
                                 "backend": "torch", "mapping.every": 2, "mapping.init_iterations": 5,
                                 "mapping.iterations": 3, "refinement.iterations_per_keyframe": 2})
        dataset = open_dataset("synthetic", size=(40, 30), max_frames=3)
        pipeline = Pipeline(dataset, cfg, progress=False)
        with GauSemSLAM(cfg, "cpu") as slam:
            for i in range(len(dataset)):
                slam.process(pipeline.observation(dataset[i]))
            before = slam.global_cloud().means.clone()
            slam.finish()
            means[refine] = (before, slam.global_cloud().means)
    before, after = means[True]
    assert slam.loop_closure is None
    assert before.shape != after.shape or not torch.equal(before, after)  # refined
    assert torch.equal(*means[False])  # ablation "w/o global refinement": untouched


@pytest.mark.slow
def test_stage_one_decays_the_centres_learning_rate_and_uses_its_own_depth_weight():
    def refine(**options):
        submap = make_submap(0, [0, 4, 8], size=(80, 60))
        noise = torch.randn(submap.cloud.means.shape, generator=torch.Generator().manual_seed(1))
        submap.cloud.means.add_(0.01 * noise)
        refined, losses = refine_submap(submap.cloud.clone(), submap.keyframes, [kf.obs for kf in submap.keyframes],
                                        Mapper(MappingConfig()), 4, None, 0.0, "torch", **options)
        return (refined.means - submap.cloud.means).norm(dim=1).mean(), losses  # no pruning on this scene

    moved_constant, losses_constant = refine(final_lr_means_fraction=1.0)
    moved_decayed, losses_decayed = refine(final_lr_means_fraction=1e-4)
    assert moved_decayed < 0.6 * moved_constant
    assert losses_decayed[-1] < losses_decayed[0]
    _, losses_without_depth = refine(final_lr_means_fraction=1.0, w_depth=0.0)
    assert losses_without_depth[0] < losses_constant[0]  # the depth term is gone from L_refine


def test_stage_one_leaves_the_optimised_colours_unclamped():
    submap = make_submap(0, [0, 4], size=(80, 60))
    submap.cloud.colors[:10] = 1.25  # what the optimiser may settle on where Gaussians overlap with partial opacity
    submap.cloud.colors[10:20] = -0.25
    refined, _ = refine_submap(submap.cloud.clone(), submap.keyframes, [kf.obs for kf in submap.keyframes],
                               Mapper(MappingConfig()), 0, None, 0.0, "torch")
    assert torch.equal(refined.colors[:20], submap.cloud.colors[:20])


def test_stage_one_decays_the_poses_learning_rate():
    def moved(fraction: float) -> float:
        submap = make_submap(0, [0, 4, 8], size=(80, 60))
        for n, kf in enumerate(submap.keyframes[1:], start=1):
            kf.cam_to_world = perturbation(0.01, 0.5, n).float() @ kf.cam_to_world
        before = [kf.cam_to_world.clone() for kf in submap.keyframes]
        refine_submap(submap.cloud, submap.keyframes, [kf.obs for kf in submap.keyframes], Mapper(MappingConfig()),
                      4, None, 0.0, "torch", final_lr_pose_fraction=fraction)
        return sum(pose_error(kf.cam_to_world, pose)[0] for kf, pose in zip(submap.keyframes, before))

    constant, decayed = moved(1.0), moved(1e-4)
    assert constant > 1e-3  # the poses move at the mapper's rate ...
    assert decayed < 0.6 * constant  # ... and settle sooner when the rate decays


def test_a_run_keeps_the_poses_as_tracked_apart_from_the_refined_ones():
    """``RunResult.tracked_poses`` are the poses as each frame was tracked (what its health judged); the global
    refinement moves the keyframes afterwards, so the final poses differ where they are keyframes."""
    import numpy as np

    from gausem_core.config import load_config
    from gausem_core.data import open_dataset
    from gausem_core.pipeline import Pipeline

    cfg = load_config(None, {"loop.enabled": False, "device": "cpu", "backend": "torch", "mapping.every": 2,
                             "mapping.init_iterations": 5, "mapping.iterations": 3,
                             "refinement.iterations_per_keyframe": 2,
                             "health.lost_coverage": 0.0})  # this thin map renders no silhouette pixel
    result = Pipeline(open_dataset("synthetic", size=(40, 30), max_frames=3), cfg, progress=False).run()
    assert result.tracked_poses.shape == result.poses.shape == (3, 4, 4)
    np.testing.assert_allclose(result.tracked_poses[0], result.poses[0])  # the fixed first keyframe
    np.testing.assert_allclose(result.tracked_poses[1], result.poses[1])  # tracked from it, not moved
    assert not np.allclose(result.tracked_poses[2], result.poses[2])  # a keyframe moved by the refinement


def test_a_run_names_the_frames_whose_loop_correction_moved_the_map():
    """``RunResult.corrected_frames``: a frame whose loop closure corrected the map is recorded at the corrected pose,
    so its step from the frame before is no tracking error (benchmarks/health.py leaves it out); a correction that
    moved nothing does not count."""
    import dataclasses

    from gausem_core.config import load_config
    from gausem_core.data import open_dataset
    from gausem_core.pipeline import Pipeline
    from gausem_core.slam.events import Correction
    from gausem_core.slam.loop_closure import LoopOutcome, LoopRecord
    from gausem_core.slam.system import GauSemSLAM

    cfg = load_config(None, {"loop.enabled": False, "refinement.enabled": False, "device": "cpu", "backend": "torch",
                             "mapping.init_iterations": 5, "mapping.iterations": 3,
                             "health.lost_coverage": 0.0})  # this thin map renders no silhouette pixel
    pipeline = Pipeline(open_dataset("synthetic", size=(40, 30), max_frames=4), cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", num_classes=len(pipeline.palette))
    process, corrections = slam.process, {2: Correction(1, 3), 3: Correction(0, 0)}

    def reporting(obs, skipped=0):
        result = process(obs, skipped)
        if result.frame_id in corrections:
            record = LoopRecord(result.frame_id, 0, 1, 0, False, True, 0.9, 0.1)
            loop = LoopOutcome(record, correction=corrections[result.frame_id])
            result = dataclasses.replace(result, events=dataclasses.replace(result.events, loop=loop))
        return result
    slam.process = reporting
    assert pipeline.run(slam=slam).corrected_frames == [2]
