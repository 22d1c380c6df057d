"""The depth filter before tracking and mapping (slam.depth_filter): less noise, same surfaces, holes kept."""
import pytest
import torch

from gausem_core.config import DepthFilterConfig
from gausem_core.geometry import PinholeCamera
from gausem_core.slam import depth_filter
from gausem_core.slam.depth_filter import bilateral_depth, filter_observation, filters_every_frame
from gausem_core.slam.observation import Observation

CAMERA = PinholeCamera(80.0, 80.0, 40.0, 30.0, 80, 60)


def slanted_wall(noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """(60, 80) depth of a plane from 2 m (left) to 3 m (right), with Gaussian noise growing with range squared."""
    depth = torch.linspace(2.0, 3.0, 80, dtype=torch.float64).expand(60, 80).clone()
    generator = torch.Generator().manual_seed(seed)
    return depth + noise * depth.square() * torch.randn(depth.shape, generator=generator, dtype=torch.float64)


def test_noise_falls_and_the_surface_stays():
    clean, noisy = slanted_wall(), slanted_wall(noise=0.002)
    filtered = bilateral_depth(noisy, 1.6, 0.005)
    inner = (slice(4, -4), slice(4, -4))  # the window (radius 4) lies inside the image
    before = (noisy - clean)[inner]
    after = (filtered - clean)[inner]
    assert after.std() < 0.5 * before.std(), (float(after.std()), float(before.std()))
    assert abs(float(after.mean())) < 5e-4  # no bias: the plane stays where it was
    # a noise-free plane is kept as it is (the weights are symmetric about each pixel on a linear ramp)
    assert torch.allclose(bilateral_depth(clean, 1.6, 0.005)[inner], clean[inner], atol=1e-9)


def test_a_depth_step_is_not_blurred_across_and_holes_stay_holes():
    depth = torch.full((60, 80), 3.0, dtype=torch.float64)
    depth[:, :40] = 1.5  # an object 1.5 m in front of a wall
    depth[20:30, 50:60] = 0.0  # no readings
    filtered = bilateral_depth(depth, 1.6, 0.005)
    assert torch.allclose(filtered[:, :40], depth[:, :40], atol=1e-12)
    assert torch.allclose(filtered[:, 40:], depth[:, 40:], atol=1e-12)
    assert bool((filtered[20:30, 50:60] == 0).all())


def test_the_observation_filter_scales_with_the_image_and_can_be_switched_off():
    depth = slanted_wall(noise=0.002).float()
    obs = Observation(torch.zeros(60, 80, 3), depth, torch.zeros(60, 80, 3), torch.zeros(60, 80, dtype=torch.long),
                      CAMERA)
    assert filter_observation(obs, DepthFilterConfig(enabled=False)) is obs
    filtered = filter_observation(obs, DepthFilterConfig(spatial_sigma=0.02, range_sigma=0.005))
    assert torch.allclose(filtered.depth, bilateral_depth(depth, 1.6, 0.005))
    assert filtered.rgb is obs.rgb and torch.equal(obs.depth, depth)  # the caller's observation is unchanged


def test_bad_sigmas_are_an_error():
    with pytest.raises(ValueError, match="sigmas"):
        bilateral_depth(slanted_wall(), 0.0, 0.005)


def window_reference(depth: torch.Tensor, spatial_sigma: float, range_sigma: float, radius: int) -> torch.Tensor:
    """The bilateral filter as its formula reads, every window at once (one tap per pixel)."""
    size = 2 * radius + 1
    offsets = torch.arange(-radius, radius + 1, dtype=depth.dtype)
    spatial = torch.exp(-(offsets[:, None] ** 2 + offsets[None] ** 2) / (2 * spatial_sigma**2)).reshape(-1, 1, 1)
    padded = torch.nn.functional.pad(depth, (radius,) * 4)
    neighbours = torch.nn.functional.unfold(padded[None, None], size)[0].reshape(size * size, *depth.shape)
    weights = spatial * torch.exp(-0.5 * ((neighbours - depth) / (range_sigma * depth.square())).square())
    weights = weights * (neighbours > 0)
    smoothed = (weights * neighbours).sum(0) / weights.sum(0).clamp_min(1e-12)
    return torch.where(depth > 0, smoothed, torch.zeros_like(depth))


def test_the_filter_is_its_formula_and_wide_windows_still_filter(monkeypatch):
    noisy = slanted_wall(noise=0.002)
    holed = noisy.clone()
    holed[10:14, 20:30] = 0  # holes neither contribute nor get a value
    reference = window_reference(holed, 1.6, 0.005, radius=4)
    assert torch.allclose(bilateral_depth(holed, 1.6, 0.005), reference, rtol=0, atol=1e-9)
    # CUDA's sums (every tap at once, in strips of rows) agree, here on the CPU in strips of 7 rows
    monkeypatch.setattr(depth_filter, "_STRIP_ELEMENTS", 81 * 80 * 7)
    monkeypatch.setattr(depth_filter, "_sums_tap_by_tap", depth_filter._sums_at_once)
    assert torch.allclose(bilateral_depth(holed, 1.6, 0.005), reference, rtol=0, atol=1e-9)
    # a 640-wide image's sigma (6.4 px, radius 13) is sampled with 7x7 taps 4 pixels apart: still less noise, no bias
    wide = torch.nn.functional.interpolate(noisy[None, None], scale_factor=4, mode="nearest")[0, 0]
    clean = torch.nn.functional.interpolate(slanted_wall()[None, None], scale_factor=4, mode="nearest")[0, 0]
    inner = (slice(12, -12), slice(12, -12))
    after, before = (bilateral_depth(wide, 6.4, 0.005) - clean)[inner], (wide - clean)[inner]
    assert after.std() < 0.5 * before.std() and abs(float(after.mean())) < 5e-4


@pytest.mark.parametrize("frames, worker_mode, every", [("all", "async", True), ("keyframes", "sync", False),
                                                        ("async", "async", False), ("async", "sync", True)])
def test_which_frames_are_filtered_before_tracking(frames, worker_mode, every):
    assert filters_every_frame(DepthFilterConfig(frames=frames), worker_mode) is every


def test_an_unknown_frames_mode_is_an_error_naming_the_parameter():
    with pytest.raises(ValueError, match="depth_filter.frames"):
        filters_every_frame(DepthFilterConfig(frames="some"), "sync")
