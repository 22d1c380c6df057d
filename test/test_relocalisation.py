"""Relocalisation start poses: the last pose, the ranked keyframes, the active submap's keyframes when few."""
from types import SimpleNamespace

import torch

from gausem_core.slam.relocalisation import relocalisation_starts


def submap(submap_id, frame_ids):
    keyframes = [SimpleNamespace(frame_id=f, cam_to_world=torch.eye(4) * (f + 1)) for f in frame_ids]
    return SimpleNamespace(submap_id=submap_id, keyframes=keyframes)


def test_starts_follow_the_ranking_and_fall_back_to_the_active_submap():
    submaps = [submap(0, [0, 2, 4]), submap(1, [6, 8])]
    last = (submaps[1], torch.eye(4))
    starts = relocalisation_starts(submaps, last, [2, 8, 0], 2)
    assert [s.label for s in starts] == ["last pose", "keyframe 2", "keyframe 8"]
    assert starts[1].submap is submaps[0] and torch.equal(starts[1].cam_to_world, torch.eye(4) * 3)
    few = relocalisation_starts(submaps, last, [4], 3)  # one ranked keyframe: the active submap's join
    assert [s.label for s in few] == ["last pose", "keyframe 4", "keyframe 6", "keyframe 8"]
    assert [s.label for s in relocalisation_starts(submaps, None, [], 2)] == ["keyframe 6", "keyframe 8"]
