"""Device-to-host reads of the tracking and mapping loops (issue 47), counted by :class:`sync_counter.HostReads`."""
import pytest
import torch
from sync_counter import HostReads
from test_device_alignment import views  # noqa: F401 (a fixture)
from test_direct_alignment import WEIGHTS

from gausem_core.config import SlamConfig
from gausem_core.data import open_dataset
from gausem_core.pipeline import Pipeline
from gausem_core.slam.device_alignment import align_level_on_device
from gausem_core.slam.mapper import Keyframe, Mapper


def test_the_counter_sees_gausem_core_alone_and_puts_the_tensor_methods_back():
    methods = dict(vars(torch.Tensor))
    with HostReads() as reads:
        float(torch.ones(()))
        Mapper(SlamConfig().mapping)._keyframe_index(3)
    assert reads.sites == {"gausem_core/slam/mapper.py:Mapper._keyframe_index": 1}
    assert vars(torch.Tensor) == methods


@pytest.mark.parametrize("damping, expected", [(2.0, 4), (1e-4, 2)])
def test_an_alignment_level_reads_its_convergence_every_few_steps_and_its_cost_once(views, damping,  # noqa: F811
                                                                                     expected):
    """16 iterations checked every 4: damped so much that they do not converge, reads after steps 4, 8 and 12 and
    the cost's; converged in 4 steps, the read after step 4 and the cost's."""
    with HostReads() as reads:
        align_level_on_device(*views, torch.eye(4), WEIGHTS, 16, damping=damping, check_every=4)
    assert reads.sites == {"gausem_core/slam/device_alignment.py:align_level_on_device": expected}


@pytest.fixture(scope="module")
def observation():
    cfg = SlamConfig(device="cpu")
    dataset = open_dataset("synthetic", size=(32, 24), max_frames=1)
    return cfg, Pipeline(dataset, cfg, progress=False).observation(dataset[0])


def test_a_mapping_optimisation_reads_as_often_whatever_its_iterations(observation):
    """Counted: every read from gausem_core but two kinds, which come once per iteration. The keyframe draw
    (``Mapper._keyframe_index``) reads the mapper's generator, a CPU one on every device, so it is no device read;
    the torch rasteriser splits the image into bands of data-dependent sizes (``render/pairs.py``), two reads per
    render (the GPU's rasteriser is gsplat's)."""
    cfg, obs = observation
    counts = []
    for iterations in (3, 6):
        mapper = Mapper(cfg.mapping, "torch", seed=0)
        cloud = mapper.strategy.initial(obs, torch.eye(4))
        with HostReads() as reads:
            _, losses = mapper.optimise(cloud, [Keyframe(0, obs, torch.eye(4))], iterations)
        assert len(losses) == iterations
        counts.append(reads.count("gausem_core/slam/mapper.py:Mapper._keyframe_index", "gausem_core/render/pairs.py"))
    assert counts[0] == counts[1] == 2  # the losses and the pruning, once each
