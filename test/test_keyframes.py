"""Keyframes by need (``mapping.keyframes: motion``) beside every d_map-th frame, and a resumed session's last
keyframe."""
import dataclasses
import math

import pytest
import torch

from gausem_core.config import MappingConfig, from_flat
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.pipeline import Pipeline
from gausem_core.slam.health import TrackingHealth
from gausem_core.slam.keyframes import KeyframePolicy, view_motion
from gausem_core.slam.observation import Observation
from gausem_core.slam.system import GauSemSLAM

CAMERA = PinholeCamera(50.0, 50.0, 20.0, 15.0, 40, 30)
COVERED = TrackingHealth("ok", coverage=1.0)


def pose(x=0.0, yaw_deg=0.0) -> torch.Tensor:
    return se3_exp(torch.tensor([x, 0.0, 0.0, 0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64)).float()


def observation(depth: float = 2.0) -> Observation:
    h, w = CAMERA.height, CAMERA.width
    return Observation(torch.zeros(h, w, 3), torch.full((h, w), depth), torch.zeros(h, w, 3),
                       torch.zeros(h, w, dtype=torch.long), CAMERA)


def test_view_motion_is_translation_over_depth_plus_rotation():
    assert view_motion(pose(), pose(x=0.1), 2.0) == pytest.approx(0.05, rel=1e-5)
    assert view_motion(pose(), pose(yaw_deg=10.0), 2.0) == pytest.approx(math.radians(10.0), rel=1e-4)
    assert view_motion(pose(x=0.3), pose(x=0.3), 0.5) == 0.0


def test_motion_keyframes_come_with_motion_low_coverage_or_the_interval():
    cfg = MappingConfig(keyframes="motion", keyframe_motion=0.1, max_keyframe_interval=6, every=2)
    policy = KeyframePolicy(cfg)
    policy.remember(0, pose())
    still = [policy.is_keyframe(i, pose(), observation(), COVERED, gap=False) for i in range(1, 8)]
    assert still == [False] * 5 + [True, False]  # a still camera: only the interval (frame 6), not every 2nd frame
    # 0.1 m per frame at 2 m depth (0.05 a frame): frame 8 is 0.1 from keyframe 6, frame 9 only 0.05 from 8 ...
    moving = [policy.is_keyframe(i, pose(x=0.1 * (i - 6)), observation(), COVERED, gap=False) for i in (7, 8, 9, 10)]
    assert moving == [False, True, False, True] and policy.last[0] == 10
    # ... but at 0.5 m depth every such step is a keyframe: the view moves four times as much
    assert policy.is_keyframe(11, pose(x=0.5), observation(0.5), COVERED, gap=False)
    sparse = TrackingHealth("ok", coverage=0.3)  # the coverage rule (after gaps, by default) still applies
    assert not policy.is_keyframe(12, pose(x=0.5), observation(), sparse, gap=False)
    assert policy.is_keyframe(13, pose(x=0.5), observation(), sparse, gap=True)


def test_every_keeps_the_d_map_rule_and_the_coverage_rule_after_gaps():
    policy = KeyframePolicy(MappingConfig(every=3, coverage_keyframes="gaps", min_coverage=0.6))
    sparse = TrackingHealth("ok", coverage=0.3)
    assert [policy.is_keyframe(i, pose(x=i), observation(), COVERED, gap=False) for i in range(1, 7)] == \
        [False, False, True, False, False, True]
    assert not policy.is_keyframe(7, pose(), observation(), sparse, gap=False)
    assert policy.is_keyframe(7, pose(), observation(), sparse, gap=True)


def test_unknown_policies_and_intervals_are_named():
    with pytest.raises(ValueError, match="mapping.keyframes must be one of"):
        KeyframePolicy(MappingConfig(keyframes="often"))
    with pytest.raises(ValueError, match="mapping.max_keyframe_interval"):
        KeyframePolicy(dataclasses.replace(MappingConfig(), max_keyframe_interval=0))


def test_a_system_with_motion_keyframes_maps_where_the_view_moved_and_resumes_from_its_last_keyframe(tmp_path):
    """Keyframes of the synthetic walk at 40x30 (its view moves about 0.06 a frame): each one the interval's or one
    whose view moved at least keyframe_motion from the previous keyframe's (its pose as tracked); a loaded session
    goes on from the saved map's newest keyframe."""
    cfg = from_flat({"device": "cpu", "mapping.keyframes": "motion", "mapping.keyframe_motion": 0.2,
                     "mapping.max_keyframe_interval": 8, "mapping.iterations": 5, "mapping.init_iterations": 30,
                     "loop.enabled": False, "refinement.enabled": False})
    dataset = SyntheticDataset("default", resolution=(40, 30), max_frames=24)
    pipeline = Pipeline(dataset, cfg, progress=False)
    slam = GauSemSLAM(cfg, "cpu", len(SYNTHETIC_CLASSES))
    results = [slam.process(pipeline.observation(dataset[i])) for i in range(len(dataset))]
    keyframes = [r for r in results if r.is_keyframe]
    assert 2 < len(keyframes) < len(results) // 2
    for previous, current in zip(keyframes, keyframes[1:]):
        obs = pipeline.observation(dataset[current.frame_id])
        moved = view_motion(previous.cam_to_world, current.cam_to_world, float(obs.depth[obs.valid_depth].median()))
        assert current.frame_id - previous.frame_id == 8 or moved >= 0.2 - 1e-3  # (poses as reported then)
    slam.save(tmp_path)
    loaded = GauSemSLAM.load(tmp_path)
    newest = max((kf.frame_id, submap.submap_id) for submap in loaded.submaps for kf in submap.keyframes)
    assert loaded.front_end.keyframes.last[0] == newest[0] == keyframes[-1].frame_id
