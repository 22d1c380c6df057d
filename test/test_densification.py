"""The densification strategy: the map's density follows mapping.density_width, not the image size."""
import dataclasses

import torch

from gausem_core.config import MappingConfig, SlamConfig
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.slam.densification import DensificationStrategy, pixel_lattice


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
