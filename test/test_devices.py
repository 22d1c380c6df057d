"""Functions that once mixed devices (issue 22) keep their work and results on their inputs' device and agree with the
CPU. Each test runs on the CPU (a reference for the logic) and on CUDA (cuda-marked, skipped without a GPU): torch on
the CPU alone cannot see a mix."""
import math

import pytest
import torch

from gausem_core.data import SYNTHETIC_CLASSES
from gausem_core.eval.fragmentation import allocation_cohesion
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, make_pose, se3_exp, so3_exp
from gausem_core.slam.allocation import SubmapExtent
from gausem_core.slam.loop_closure import SemanticPalette
from gausem_core.slam.observation import Observation
from gausem_core.slam.registration import coarse_registration, fine_views

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(),
                                                                                     reason="needs a CUDA device")])]
PALETTE = SYNTHETIC_CLASSES.palette.float()
CAMERA = PinholeCamera(40.0, 40.0, 16.0, 12.0, 32, 24)


def labelled(labels: torch.Tensor) -> Observation:
    h, w = labels.shape
    return Observation(torch.zeros(h, w, 3), torch.full((h, w), 2.0), PALETTE[labels], labels, CAMERA)


def to(obs: Observation, device: str) -> Observation:
    return Observation(obs.rgb.to(device), obs.depth.to(device), obs.semantic.to(device), obs.labels.to(device),
                       obs.camera)


@pytest.mark.parametrize("device", DEVICES)
def test_class_kl_to_the_anchor_on_the_labels_device(device):
    anchor, current = torch.zeros(24, 32, dtype=torch.long), torch.full((24, 32), 3)
    anchor[:, 16:], current[:12] = 2, 7  # the current keyframe shows a class the anchor lacks: histograms grow
    extent = SubmapExtent.start(to(labelled(anchor), device), torch.eye(4, device=device), 1)
    expected = SubmapExtent.start(labelled(anchor), torch.eye(4), 1).kl_to_anchor(current)
    assert extent.kl_to_anchor(current.to(device)) == pytest.approx(expected, rel=1e-12) and expected > 1


@pytest.mark.parametrize("device", DEVICES)
def test_coarse_registration_and_fine_views_on_the_poses_device(device):
    g = torch.Generator().manual_seed(2)
    transform = make_pose(so3_exp(torch.tensor([0.2, -0.3, 0.4], dtype=torch.float64)),
                          torch.tensor([0.5, -0.2, 0.1], dtype=torch.float64))
    source = se3_exp(torch.randn(8, 6, generator=g, dtype=torch.float64))
    descriptors = torch.randn(8, 16, generator=g, dtype=torch.float64)
    args = (descriptors, source, descriptors, transform @ source)
    result = coarse_registration(*(a.to(device) for a in args), k=5, seed=(1, 1),
                                 consensus=(0.1, math.radians(5)))
    expected = coarse_registration(*args, k=5, seed=(1, 1), consensus=(0.1, math.radians(5)))
    assert result.transform.device.type == result.pairs.device.type == device
    torch.testing.assert_close(result.transform.cpu(), expected.transform, atol=1e-9, rtol=0)
    assert torch.equal(result.pairs.cpu(), expected.pairs) and result.pairs[0].tolist() == [1, 1]
    views = fine_views(result.pairs, source.to(device), 4)
    assert views.device.type == device and torch.equal(views.cpu(), fine_views(expected.pairs, source, 4))


@pytest.mark.parametrize("device", DEVICES)
def test_rigid_moves_follow_the_moved_tensors(device):
    correction = se3_exp(torch.tensor([0.1, 0.2, -0.3, 0.05, 0.0, 0.1], dtype=torch.float64))
    cloud = GaussianCloud.from_points(torch.rand(5, 3), torch.rand(5, 3), torch.rand(5, 3), torch.ones(5))
    shifted = cloud.to(device).transformed(correction)  # a CPU float64 transform for a cloud on ``device``
    assert shifted.device.type == device
    torch.testing.assert_close(shifted.means.cpu(), cloud.transformed(correction).means)


@pytest.mark.parametrize("device", DEVICES)
def test_the_semantic_palette_learns_the_same_colours_on_any_device(device):
    images = [PALETTE[torch.tensor([[5, 2], [2, 9]])], PALETTE[torch.tensor([[9, 4], [1, 5]])]]
    palette, expected = SemanticPalette(), SemanticPalette()
    for image in images:
        palette.update(image.to(device))
        expected.update(image)
    assert torch.equal(palette.colors, expected.colors) and len(palette) == 5


@pytest.mark.parametrize("device", DEVICES)
def test_allocation_cohesion_on_the_keyframes_device(device):
    labels = torch.zeros(24, 32, dtype=torch.long)
    labels[:, 16:] = 3
    depth = torch.full((24, 32), 2.0)
    poses = [torch.eye(4, dtype=torch.float64), se3_exp(torch.tensor([0.3, 0, 0, 0, 0.1, 0], dtype=torch.float64))]
    keyframes = [(depth, labels, CAMERA, pose) for pose in poses]
    moved = [(d.to(device), lab.to(device), camera, pose) for d, lab, camera, pose in keyframes]  # CPU poses
    expected = allocation_cohesion(keyframes, [0, 1], (), min_points=10, revisit_gap=1)
    assert allocation_cohesion(moved, [0, 1], (), min_points=10, revisit_gap=1).objects == expected.objects
