import pytest
import torch

from gausem_core.gaussians import GaussianCloud


def make_cloud(n=10):
    return GaussianCloud.from_points(torch.randn(n, 3), torch.rand(n, 3), torch.rand(n, 3), torch.rand(n) * 0.1 + 0.01, 0.5)


def test_activations():
    c = make_cloud()
    assert torch.allclose(c.opacities, torch.full((10,), 0.5))
    assert len(c) == 10 and (c.radii > 0).all()


def test_shape_validation():
    with pytest.raises(ValueError, match="colors"):
        GaussianCloud(torch.zeros(3, 3), torch.zeros(3), torch.zeros(3), torch.zeros(2, 3), torch.zeros(3, 3))


def test_cat_prune_transform(tmp_path):
    a, b = make_cloud(4), make_cloud(6)
    c = GaussianCloud.cat([a, b])
    assert len(c) == 10 and torch.equal(c.means[4:], b.means)
    keep = torch.zeros(10, dtype=torch.bool)
    keep[[1, 7]] = True
    p = c.prune(keep)
    assert torch.equal(p.colors, c.colors[[1, 7]])
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([1.0, 0, 0])
    assert torch.allclose(c.transformed(pose).means, c.means + torch.tensor([1.0, 0, 0]))


def test_save_load_round_trip(tmp_path):
    c = make_cloud()
    c.save(tmp_path / "c.pt")
    d = GaussianCloud.load(tmp_path / "c.pt")
    for k, v in c.tensors().items():
        assert torch.equal(v, getattr(d, k))
    torch.save({"means": torch.zeros(1, 3)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a GaussianCloud"):
        GaussianCloud.load(tmp_path / "bad.pt")


def test_class_ids_nearest_palette_colour():
    palette = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    c = make_cloud(3)
    c.semantics = torch.tensor([[0.9, 0.1, 0], [0.1, 0.2, 0.8], [0.2, 0.7, 0.1]])
    assert c.class_ids(palette).tolist() == [0, 2, 1]
    assert GaussianCloud.empty().class_ids(palette).numel() == 0
