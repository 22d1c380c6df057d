"""Cross-view label consistency: carrying labels by depth and pose, checked on views of a known scene."""
import math

import torch

from gausem_core.eval.label_consistency import carried_labels, label_agreement
from gausem_core.geometry import PinholeCamera

CAMERA = PinholeCamera(40.0, 40.0, 16.0, 12.0, 32, 24)


def _wall_view(x: float):
    """A fronto-parallel wall 2 m ahead, labelled 1 left of world x = 0 and 2 right of it, seen from (x, 0, 0)."""
    pose = torch.eye(4, dtype=torch.float64)
    pose[0, 3] = x
    depth = torch.full((CAMERA.height, CAMERA.width), 2.0)
    world_x = CAMERA.backproject(depth.double())[..., 0] + x
    return torch.where(world_x < 0, 1, 2), depth, pose


def test_labels_carried_between_two_views_of_a_wall_agree_where_they_overlap():
    labels_a, depth_a, pose_a = _wall_view(0.0)
    labels_b, depth_b, pose_b = _wall_view(0.4)  # 0.4 m to the right: 8 pixel columns at 2 m
    agree, compared = label_agreement(labels_a, depth_a, pose_a, labels_b, depth_b, pose_b, CAMERA)
    assert compared == CAMERA.height * (CAMERA.width - 8)  # the columns that leave B's view are not compared
    assert agree == compared
    flipped = 3 - labels_b  # B's labels swapped: they disagree everywhere
    assert label_agreement(labels_a, depth_a, pose_a, flipped, depth_b, pose_b, CAMERA)[0] == 0


def test_a_pixel_that_sees_another_surface_is_not_compared():
    labels_a, depth_a, pose_a = _wall_view(0.0)
    labels_b, depth_b, pose_b = _wall_view(0.0)
    depth_b[:, :10] = 1.0  # something stands in front of the wall in B's left columns
    depth_a[0, :] = 0.0  # and A has no depth on its first row
    index, carried = carried_labels(labels_a, depth_a, pose_a, pose_b, depth_b, CAMERA)
    columns, rows = index % CAMERA.width, index // CAMERA.width
    assert bool((columns >= 10).all()) and bool((rows >= 1).all())
    assert index.numel() == (CAMERA.height - 1) * (CAMERA.width - 10)
    assert torch.equal(carried, labels_a.reshape(-1)[index])  # the same pose: each pixel carries its own label


def test_a_rotated_view_lands_where_the_rotation_says():
    labels_a, depth_a, pose_a = _wall_view(0.0)
    pose_b = torch.eye(4, dtype=torch.float64)
    angle = math.atan2(4.0, CAMERA.fx)  # a yaw that shifts the image centre by four pixels
    pose_b[:3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                                   [-math.sin(angle), 0, math.cos(angle)]], dtype=torch.float64)
    centre = (CAMERA.height // 2) * CAMERA.width + CAMERA.width // 2
    only_centre = torch.zeros_like(depth_a).reshape(-1)
    only_centre[centre] = 2.0  # one pixel with depth, straight ahead
    index, _ = carried_labels(labels_a, only_centre.reshape(depth_a.shape), pose_a, pose_b, depth_a, CAMERA)
    assert index.tolist() == [centre - 4]
