"""The densification strategy: the map's density follows mapping.density_width, not the image size."""
import dataclasses

import torch

from gausem_core.config import MappingConfig, SlamConfig
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.gaussians import GaussianCloud
from gausem_core.render import render
from gausem_core.slam.densification import DensificationStrategy, blend_weights, fine_residual, pixel_lattice


def first_frame(size):
    dataset = open_dataset("synthetic", size=size, max_frames=1)
    return Pipeline(dataset, SlamConfig(device="cpu"), progress=False).observation(dataset[0])


def test_the_lattice_keeps_one_pixel_per_block():
    lattice = pixel_lattice(6, 8, 2, "cpu")
    assert int(lattice.sum()) == 12 and bool(lattice[1, 1]) and not bool(lattice[0, 0])
    assert bool(pixel_lattice(3, 3, 1, "cpu").all())


def test_spacing_follows_the_image_width():
    strategy = DensificationStrategy(MappingConfig(density_width=80))
    assert strategy.spacing(first_frame((80, 60))) == 1
    assert strategy.spacing(first_frame((160, 120))) == 2
    assert DensificationStrategy(MappingConfig(density_width=0)).spacing(first_frame((160, 120))) == 1


def test_a_wider_image_spawns_as_many_gaussians_each_covering_more_pixels():
    cfg = MappingConfig(density_width=80, init_samples_fraction=0.5)
    small, large = first_frame((80, 60)), first_frame((160, 120))
    small_cloud = DensificationStrategy(cfg, "torch", torch.Generator().manual_seed(0)).initial(small, torch.eye(4))
    large_cloud = DensificationStrategy(cfg, "torch", torch.Generator().manual_seed(0)).initial(large, torch.eye(4))
    dense = DensificationStrategy(dataclasses.replace(cfg, density_width=0), "torch",
                                  torch.Generator().manual_seed(0)).initial(large, torch.eye(4))
    assert abs(len(large_cloud) - len(small_cloud)) < 0.1 * len(small_cloud)
    assert abs(len(dense) - 4 * len(large_cloud)) < 0.1 * len(dense)
    # a footprint of two pixels at the same focal-length ratio: twice the radius of the one-pixel Gaussians
    assert torch.median(large_cloud.radii) > 1.5 * torch.median(dense.radii)


def test_growth_fills_only_what_the_map_lacks_on_the_lattice():
    cfg = MappingConfig(density_width=80)
    obs = first_frame((160, 120))
    strategy = DensificationStrategy(cfg, "torch", torch.Generator().manual_seed(0))
    initial = strategy.initial(obs, torch.eye(4))
    grown = strategy.grow(initial.prune(torch.zeros(len(initial), dtype=torch.bool)), obs, torch.eye(4))
    on_lattice = obs.valid_depth & pixel_lattice(120, 160, 2, obs.depth.device)
    assert len(grown) == int(on_lattice.sum())  # an empty map lacks everything: one Gaussian per lattice pixel
    again = strategy.grow(grown, obs, torch.eye(4))
    assert len(again) - len(grown) < 0.05 * len(grown)  # the map now covers the view


def test_pruning_drops_transparent_and_huge_gaussians():
    cfg = MappingConfig(prune_opacity=0.1, prune_radius=0.5)
    obs = first_frame((80, 60))
    cloud = DensificationStrategy(cfg, "torch", torch.Generator().manual_seed(0)).initial(obs, torch.eye(4))
    with torch.no_grad():
        cloud.opacity_logits[:10] = -10.0
        cloud.log_radii[10:15] = 2.0
    assert len(DensificationStrategy(cfg).prune(cloud)) == len(cloud) - 15


def test_a_lattice_of_non_whole_spacing_keeps_one_pixel_per_block_of_that_size():
    for spacing in (1.25, 2.5, 4.0):
        lattice = pixel_lattice(120, 160, spacing, "cpu")
        assert abs(int(lattice.sum()) - 120 * 160 / spacing ** 2) < 0.1 * 120 * 160 / spacing ** 2
    assert DensificationStrategy(MappingConfig(density_width=64)).spacing(first_frame((160, 120))) == 2.5


def test_detail_goes_only_where_the_view_holds_colour_finer_than_the_lattice():
    obs = first_frame((160, 120))
    cfg = MappingConfig(density_width=80, densify_color_error=0.05)
    strategy = DensificationStrategy(cfg, "torch", torch.Generator().manual_seed(0))
    covering = strategy.grow(GaussianCloud.empty(), obs, torch.eye(4))
    for _ in range(2):  # the lattice's Gaussians cover the view
        covering = strategy.grow(covering, obs, torch.eye(4))
    shifted, striped = obs.rgb.clone(), obs.rgb.clone()
    shifted[:60] = (shifted[:60] + 0.2).clamp(0, 1)  # the upper half all brighter: a region off, nothing finer
    striped[:60, ::2] = 1 - striped[:60, ::2]  # the upper half in one-pixel stripes the lattice cannot hold
    upper_pixels = int(obs.valid_depth[:60].sum())
    edges = len(strategy.add_detail(covering, obs, torch.eye(4))) - len(covering)  # the view itself: edges only
    assert edges < 0.05 * obs.valid_depth.sum()
    brighter = strategy.add_detail(covering, dataclasses.replace(obs, rgb=shifted), torch.eye(4))
    assert len(brighter) - len(covering) < edges + 0.1 * upper_pixels
    grown = strategy.add_detail(covering, dataclasses.replace(obs, rgb=striped), torch.eye(4))
    new = grown.means[len(covering):]
    assert len(new) > 0.5 * upper_pixels  # one-pixel detail where the view is finer than the lattice ...
    rows = obs.camera.fy * new[:, 1] / new[:, 2] + obs.camera.cy
    assert int((rows >= 64).sum()) <= edges  # ... and only there (blending blurs the boundary by a few pixels)
    assert torch.median(grown.radii[len(covering):]) < 0.75 * torch.median(covering.radii)
    for off in (dataclasses.replace(cfg, densify_color_error=0.0), dataclasses.replace(cfg, density_width=0)):
        unchanged = DensificationStrategy(off, "torch").add_detail(covering, dataclasses.replace(obs, rgb=striped),
                                                                   torch.eye(4))
        assert len(unchanged) == len(covering)
    assert len(strategy.grow(covering, dataclasses.replace(obs, rgb=striped), torch.eye(4))) - len(covering) \
        < 0.05 * len(new)  # growth is for coverage only


def test_the_fine_residual_keeps_what_varies_within_the_lattice_spacing():
    smooth = torch.linspace(0, 1, 40)[None, :, None].expand(30, 40, 3)  # a ramp: locally linear, nothing finer
    stripes = (torch.arange(40) % 2).to(torch.float32)[None, :, None].expand(30, 40, 3)
    assert fine_residual(smooth, 2.5)[:, 3:-3].abs().max() < 1e-5
    assert fine_residual(stripes, 2.5).abs().mean() > 0.4


def test_blend_weights_add_up_to_the_rendered_silhouette():
    obs = first_frame((80, 60))
    cloud = DensificationStrategy(MappingConfig(), "torch", torch.Generator().manual_seed(0)).initial(obs, torch.eye(4))
    view = (torch.eye(4), obs.camera)
    weights = blend_weights(cloud, [view], "torch")
    silhouette = render(cloud, *view, backend="torch").alpha.sum()
    assert torch.isclose(weights.sum(), silhouette, rtol=1e-4)
    assert torch.allclose(blend_weights(cloud, [view, view], "torch"), 2 * weights)


def test_a_closed_submap_drops_the_gaussians_hidden_behind_an_opaque_surface_and_keeps_its_image():
    obs = first_frame((80, 60))
    strategy = DensificationStrategy(MappingConfig(prune_weight=0.05), "torch", torch.Generator().manual_seed(0))
    front = strategy.initial(obs, torch.eye(4), opacity=0.999)
    with torch.no_grad():
        front.log_radii += 1.0  # wide enough that the surface has no gaps between its Gaussians
    behind = front.clone()
    behind.means[:] *= 1.5  # the same rays, half as far again behind the surface
    behind.semantics[:] = 0.123  # a mark to find them by
    both, view = GaussianCloud.cat([front, behind]), (torch.eye(4), obs.camera)
    kept = strategy.prune_hidden(both, [view])
    assert int((kept.semantics[:, 0] == 0.123).sum()) < 0.02 * len(behind)
    assert len(kept) < 0.9 * len(front)  # (wide and opaque, the surface's own Gaussians hide each other too)
    before, after = render(both, *view, backend="torch"), render(kept, *view, backend="torch")
    assert (before.color - after.color).abs().mean() < 0.002 and (before.alpha - after.alpha).abs().mean() < 0.002
    off = DensificationStrategy(MappingConfig(prune_weight=0.0), "torch")
    assert len(off.prune_hidden(both, [view])) == len(both)
