"""Semantic front end: DINOv2 loading (offline, real ViT-S/14 architecture with random weights), segmenters, head
training, global descriptors and dense features."""
import argparse
import socket

import numpy as np
import pytest
import torch
from transformers import Dinov2Config, Dinov2Model

from gausem_core.semantics import (ColourLayoutDescriptor, Dinov2Descriptor, HeadInfo, LabelsSegmenter, load_dinov2,
                                   load_head, make_descriptor, make_segmenter, save_head, train_linear_head)
from gausem_core.semantics import backbone as backbone_module
from gausem_core.semantics.backbone import IMAGENET_MEAN, IMAGENET_STD, model_input_size
from gausem_core.semantics.head import patch_majority_labels
from gausem_core.tools import train_head

VITS14 = dict(hidden_size=384, num_hidden_layers=12, num_attention_heads=6, patch_size=14, image_size=518,
              layerscale_value=1.0, mlp_ratio=4)
TINY = dict(hidden_size=384, num_hidden_layers=1, num_attention_heads=6, patch_size=14, image_size=56,
            layerscale_value=1.0, mlp_ratio=1)
COLOURS = np.array([[230, 30, 30], [30, 200, 40], [40, 60, 220]], np.uint8)


def save_model(directory, config):
    torch.manual_seed(1)
    model = Dinov2Model(Dinov2Config(**config)).eval()
    model.save_pretrained(directory)
    return model


@pytest.fixture(scope="module")
def vits14(tmp_path_factory):
    directory = tmp_path_factory.mktemp("dinov2_vits14")
    return directory, save_model(directory, VITS14)


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    directory = tmp_path_factory.mktemp("dinov2_tiny")
    save_model(directory, TINY)
    return directory


def random_head_file(path, num_classes, feature_dim=384, short_side=56, weight_scale=1.0, bias=None):
    head = torch.nn.Linear(feature_dim, num_classes)
    with torch.no_grad():
        head.weight.mul_(weight_scale)
        if bias is not None:
            head.bias.copy_(torch.as_tensor(bias))
    save_head(path, head, HeadInfo(num_classes, feature_dim, 14, short_side))
    return path


def patch_mosaic(classes: np.ndarray, rng, noise=10) -> tuple[np.ndarray, np.ndarray]:
    """An image of 14x14 patches coloured by class (plus noise) and its label map."""
    labels = np.kron(classes, np.ones((14, 14), np.int64))
    rgb = COLOURS[labels].astype(np.int64) + rng.integers(-noise, noise + 1, labels.shape + (3,))
    return np.clip(rgb, 0, 255).astype(np.uint8), labels


def layout_image(split_col: int, left: int, right: int, box_at: int) -> np.ndarray:
    """120x160 semantic image: two classes split at a column, a third-class box at a column offset."""
    labels = np.where(np.arange(160)[None, :] < split_col, left, right).repeat(120, 0)
    labels[30:70, box_at:box_at + 40] = 2
    return COLOURS[labels]


# --- backbone -------------------------------------------------------------------------------------------------------

def test_real_vits14_loads_offline_and_matches_the_saved_model(vits14, monkeypatch):
    directory, model = vits14

    def refuse(*args, **kwargs):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    backbone_module._load_cached.cache_clear()
    backbone = load_dinov2(directory)
    assert (backbone.hidden_size, backbone.patch_size) == (384, 14)
    assert sum(p.numel() for p in backbone.model.parameters()) == sum(p.numel() for p in model.parameters())
    assert 21e6 < sum(p.numel() for p in model.parameters()) < 23e6  # ViT-S/14: 22.1 M
    image = torch.rand(1, 56, 84, 3)
    cls, patches = backbone.tokens(image, short_side=56)
    assert cls.shape == (1, 384) and patches.shape == (1, 4, 6, 384)
    pixels = (image.permute(0, 3, 1, 2) - torch.tensor(IMAGENET_MEAN)[:, None, None]) / torch.tensor(
        IMAGENET_STD)[:, None, None]
    with torch.no_grad():
        expected = model(pixel_values=pixels).last_hidden_state
    torch.testing.assert_close(cls, expected[:, 0])
    torch.testing.assert_close(patches, expected[:, 1:].reshape(1, 4, 6, 384))
    assert load_dinov2(directory) is backbone  # cached


def test_model_input_size_rounds_to_patch_multiples():
    assert model_input_size(480, 640, 224, 14) == (224, 294)  # 640 * 224 / 480 = 298.7 -> 21 patches
    assert model_input_size(640, 480, 224, 14) == (294, 224)
    assert model_input_size(56, 56, 230, 14) == (224, 224)  # 230 / 14 = 16.4 -> 16 patches
    assert model_input_size(10, 1000, 14, 14) == (14, 1400)
    with pytest.raises(ValueError, match="short_side"):
        model_input_size(56, 56, 10, 14)


@pytest.mark.parametrize("make_path, message", [
    (lambda tmp: None, "dinov2_weights is not set"),
    (lambda tmp: tmp / "absent", "does not exist"),
    (lambda tmp: tmp, "lacks config.json"),
])
def test_missing_dinov2_weights_name_the_parameter(tmp_path, make_path, message):
    with pytest.raises(FileNotFoundError, match=message) as info:
        load_dinov2(make_path(tmp_path))
    assert "dinov2_weights" in str(info.value) and "no download is attempted" in str(info.value)


def test_incomplete_checkpoint_is_rejected(tmp_path):
    Dinov2Model(Dinov2Config(**TINY)).save_pretrained(tmp_path)
    config = (tmp_path / "config.json").read_text().replace('"num_hidden_layers": 1', '"num_hidden_layers": 2')
    (tmp_path / "config.json").write_text(config)
    with pytest.raises(ValueError, match="not a complete Dinov2Model checkpoint"):
        load_dinov2(tmp_path)


# --- head -----------------------------------------------------------------------------------------------------------

def test_head_file_round_trip_and_errors(tmp_path):
    head = torch.nn.Linear(384, 5)
    info = HeadInfo(5, 384, 14, 224, ("a", "b", "c", "d", "e"))
    save_head(tmp_path / "head.pt", head, info)
    loaded, loaded_info = load_head(tmp_path / "head.pt")
    assert loaded_info == info
    torch.testing.assert_close(loaded.weight, head.weight)
    torch.testing.assert_close(loaded.bias, head.bias)
    with pytest.raises(FileNotFoundError, match="head_weights.*no download is attempted"):
        load_head(tmp_path / "absent.pt")
    with pytest.raises(FileNotFoundError, match="head_weights is not set"):
        load_head("")
    torch.save({"weight": head.weight}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a GauSem linear-head file"):
        load_head(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="info says"):
        save_head(tmp_path / "bad.pt", head, HeadInfo(4, 384, 14, 224))


def test_patch_majority_labels_by_hand():
    labels = np.array([[0, 0, 1, 1, 2, 2],
                       [0, 1, 1, 1, 2, 0],
                       [2, 2, 0, 1, 1, 1],
                       [2, 0, 0, 0, 1, 2]])
    expected = [[0, 1, 2], [2, 0, 1]]
    assert patch_majority_labels(labels, (2, 3), 3).tolist() == expected
    with pytest.raises(ValueError, match="outside 0..2"):
        patch_majority_labels(labels + 1, (2, 3), 3)


def test_head_training_learns_a_synthetic_segmentation(tiny_dir, tmp_path):
    rng = np.random.default_rng(0)
    samples = [patch_mosaic(rng.integers(0, 3, (4, 4)), rng) for _ in range(12)]
    backbone = load_dinov2(tiny_dir)

    def encode(rgb):
        return backbone.tokens(torch.from_numpy(rgb)[None].float() / 255, 56)[1][0]

    head, losses = train_linear_head(encode, [s[0] for s in samples], [s[1] for s in samples], 3, epochs=40, lr=1e-2)
    assert len(losses) == 40 and losses[-1] < 0.3 * losses[0]
    save_head(tmp_path / "head.pt", head, HeadInfo(3, 384, 14, 56))
    segmenter = make_segmenter("dinov2", dinov2_weights=str(tiny_dir), head_weights=str(tmp_path / "head.pt"))
    rgb, labels = patch_mosaic(rng.integers(0, 3, (4, 4)), rng)
    assert (segmenter.segment(rgb) == labels).mean() > 0.8


def test_train_head_cli_writes_a_loadable_head(tiny_dir, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    train_head.add_arguments(parser)
    args = parser.parse_args(["--dataset", "synthetic", "--frames", "2", "--dinov2-weights", str(tiny_dir),
                              "--output", str(tmp_path / "head.pt"), "--short-side", "56", "--epochs", "3"])
    assert train_head.main(args) == 0
    _, info = load_head(tmp_path / "head.pt")
    assert (info.feature_dim, info.patch_size, info.input_short_side) == (384, 14, 56)
    assert info.class_names is not None and len(info.class_names) == info.num_classes
    assert "epoch   3" in capsys.readouterr().out


# --- segmenters -----------------------------------------------------------------------------------------------------

def test_dinov2_segmenter_on_the_real_architecture(vits14, tmp_path):
    directory, _ = vits14
    head = random_head_file(tmp_path / "head.pt", 5)
    segmenter = make_segmenter("dinov2", dinov2_weights=str(directory), head_weights=str(head))
    rgb = np.random.default_rng(0).integers(0, 256, (70, 98, 3), dtype=np.uint8)
    labels = segmenter.segment(rgb)
    assert segmenter.num_classes == 5 and segmenter.short_side == 56
    assert labels.shape == (70, 98) and labels.dtype == np.int64
    assert labels.min() >= 0 and labels.max() < 5
    assert segmenter.logits(rgb).shape == (5, 70, 98)
    constant = random_head_file(tmp_path / "constant.pt", 4, weight_scale=0.0, bias=[0.0, 0.0, 1.0, 0.0])
    assert (make_segmenter("dinov2", dinov2_weights=str(directory), head_weights=str(constant)).segment(rgb) == 2).all()


def test_dinov2_segmenter_errors_name_the_parameters(vits14, tmp_path):
    directory, _ = vits14
    head = random_head_file(tmp_path / "head.pt", 3)
    with pytest.raises(FileNotFoundError, match="dinov2_weights"):
        make_segmenter("dinov2", dinov2_weights=str(tmp_path / "absent"), head_weights=str(head))
    with pytest.raises(FileNotFoundError, match="head_weights"):
        make_segmenter("dinov2", dinov2_weights=str(directory), head_weights=str(tmp_path / "absent.pt"))
    narrow = random_head_file(tmp_path / "narrow.pt", 3, feature_dim=192)
    with pytest.raises(ValueError, match="192-d tokens"):
        make_segmenter("dinov2", dinov2_weights=str(directory), head_weights=str(narrow))
    segmenter = make_segmenter("dinov2", dinov2_weights=str(directory), head_weights=str(head))
    with pytest.raises(ValueError, match="uint8"):
        segmenter.segment(np.zeros((28, 28, 3), np.float32))


def test_labels_segmenter_passes_through_and_remaps():
    rgb = np.zeros((2, 3, 3), np.uint8)
    labels = np.array([[0, 1, 2], [2, 1, 0]], np.uint16)
    out = make_segmenter("labels", num_classes=3).segment(rgb, labels)
    assert out.dtype == np.int64 and out.tolist() == labels.tolist()
    remapped = make_segmenter("labels", num_classes=2, remap=[1, 0, 0]).segment(rgb, labels)
    assert remapped.tolist() == [[1, 0, 0], [0, 0, 1]]


@pytest.mark.parametrize("labels, message", [
    (None, "needs the class ids"),
    (np.zeros((3, 2), np.int64), "differs from the image size"),
    (np.zeros((2, 3), np.float32), "integer class ids"),
    (np.array([[0, 1, 3], [0, 0, 0]]), r"outside the class range 0..2"),
    (np.array([[0, -1, 0], [0, 0, 0]]), r"outside the class range"),
])
def test_labels_segmenter_rejects_bad_labels(labels, message):
    with pytest.raises(ValueError, match=message):
        LabelsSegmenter(3).segment(np.zeros((2, 3, 3), np.uint8), labels)


def test_labels_segmenter_rejects_bad_remaps_and_kinds():
    with pytest.raises(ValueError, match="remap maps to ids"):
        LabelsSegmenter(2, remap=[0, 2])
    with pytest.raises(ValueError, match="remap table's range 0..1"):
        LabelsSegmenter(3, remap=[0, 1]).segment(np.zeros((1, 1, 3), np.uint8), np.array([[2]]))
    with pytest.raises(ValueError, match="unknown segmenter kind"):
        make_segmenter("segformer")


# --- descriptors ----------------------------------------------------------------------------------------------------

def test_fallback_descriptor_by_hand():
    red = np.zeros((12, 18, 3), np.uint8)
    red[..., 0] = 255  # quantised levels (3, 0, 0) -> colour bin 48 in each of the 6 cells
    expected = np.zeros(384, np.float32)
    expected[np.arange(6) * 64 + 48] = 1 / np.sqrt(6)
    np.testing.assert_allclose(ColourLayoutDescriptor().describe(red), expected, atol=1e-7)


def test_fallback_descriptor_separates_layouts_more_than_shifts():
    descriptor = make_descriptor()
    assert isinstance(descriptor, ColourLayoutDescriptor)
    original = descriptor.describe(layout_image(80, 0, 1, 50))
    shifted = descriptor.describe(layout_image(84, 0, 1, 54))
    swapped = descriptor.describe(layout_image(80, 1, 0, 50))
    moved_box = descriptor.describe(layout_image(80, 0, 1, 110))
    assert original.shape == (384,) and original.dtype == np.float32
    assert np.linalg.norm(original) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_array_equal(original, make_descriptor("fallback").describe(layout_image(80, 0, 1, 50)))
    near = np.linalg.norm(original - shifted)
    assert near < np.linalg.norm(original - swapped) and near < np.linalg.norm(original - moved_box)
    float_image = torch.from_numpy(layout_image(80, 0, 1, 50)).float() / 255
    np.testing.assert_allclose(descriptor.describe(float_image), original, atol=1e-6)


def test_dinov2_descriptor_on_the_real_architecture(vits14):
    directory, _ = vits14
    descriptor = make_descriptor("auto", dinov2_weights=str(directory), short_side=56)
    assert isinstance(descriptor, Dinov2Descriptor)
    image = layout_image(80, 0, 1, 50)
    a, b = descriptor.describe(image), descriptor.describe(image.copy())
    assert a.shape == (384,) and a.dtype == np.float32
    assert np.linalg.norm(a) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_array_equal(a, b)
    assert np.linalg.norm(a - descriptor.describe(layout_image(80, 1, 0, 50))) > 0
    with pytest.raises(ValueError, match="one image"):
        descriptor.describe(np.zeros((2, 28, 28, 3), np.uint8))


def test_make_descriptor_never_ignores_a_given_path(tmp_path):
    assert isinstance(make_descriptor("auto", dinov2_weights=""), ColourLayoutDescriptor)
    with pytest.raises(FileNotFoundError, match="dinov2_weights"):
        make_descriptor("auto", dinov2_weights=str(tmp_path / "absent"))
    with pytest.raises(FileNotFoundError, match="dinov2_weights is not set"):
        make_descriptor("dinov2")
    with pytest.raises(ValueError, match="unknown descriptor kind"):
        make_descriptor("netvlad")


@pytest.mark.parametrize("kind", ["fallback", "dinov2"])
def test_dense_features_are_differentiable(kind, vits14):
    directory, _ = vits14
    descriptor = make_descriptor(kind, dinov2_weights=str(directory) if kind == "dinov2" else None, short_side=56)
    image = torch.rand(56, 70, 3, requires_grad=True)
    features = descriptor.dense_features(image)
    assert features.shape == (4, 5, 384)
    target = descriptor.dense_features(torch.rand(56, 70, 3)).detach()
    ((features - target) ** 2).sum().backward()
    assert image.grad is not None and torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0
    assert descriptor.dense_features(torch.rand(2, 56, 70, 3)).shape == (2, 4, 5, 384)


def test_fallback_dense_features_gradcheck_and_patch_locality():
    descriptor = ColourLayoutDescriptor(short_side=14)
    image = torch.rand(14, 14, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(descriptor.dense_features, (image,), fast_mode=True)
    two_patches = torch.rand(14, 28, 3)
    changed = two_patches.clone()
    changed[:, 14:] = torch.rand(14, 14, 3)
    a, b = descriptor.dense_features(two_patches), descriptor.dense_features(changed)
    torch.testing.assert_close(a[:, 0], b[:, 0])
    assert (a[:, 1] - b[:, 1]).abs().max() > 1e-3
