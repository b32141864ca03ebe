"""Layers the denoiser designs share: trunks, heads, cost volumes, coordinate channels."""

from __future__ import annotations

import torch
import torchvision
from torch import nn

from monose3.method.denoiser import NUM_OUTPUTS

GRID = (3, 4)  # (h, w) cells a GridHead pools the last feature map to (not one global mean)
RESNETS = {"resnet34": torchvision.models.resnet34, "resnet18": torchvision.models.resnet18}


def resnet(backbone: str) -> torchvision.models.ResNet:
    """A ResNet from scratch (the paper's denoiser trains its own)."""
    if backbone not in RESNETS:
        raise ValueError(f"unknown backbone {backbone!r}; this design takes one of {tuple(RESNETS)}")
    return RESNETS[backbone](weights=None)


def to_net_range(image: torch.Tensor) -> torch.Tensor:
    """[0, 1] images to roughly zero-mean, unit-scale network input (the from-scratch trunks)."""
    return (image - 0.5) * 4.0


def coord_channels(b: int, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """CoordConv channels ``[b, 2, h, w]``: x and y of each cell in [-1, 1] (where a feature is)."""
    ys = torch.linspace(-1.0, 1.0, h, dtype=like.dtype, device=like.device)
    xs = torch.linspace(-1.0, 1.0, w, dtype=like.dtype, device=like.device)
    grid = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1])
    return grid[None].expand(b, 2, h, w)


def zero_head(in_features: int, outputs: int = NUM_OUTPUTS, hidden: int = 256) -> nn.Sequential:
    """MLP (one hidden layer) whose last layer is zero: to the 9 raw outputs, the identity update
    at init; to other outputs (a solve's weights, a prior), their value at zero."""
    head = nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, outputs))
    nn.init.zeros_(head[2].weight)
    nn.init.zeros_(head[2].bias)
    return head


class GridHead(nn.Module):
    """Pools a feature map to a coarse :data:`GRID` of cells (not one global mean), squeezes
    the channels and flattens, so the head knows *where* each feature is. A rotation about
    the robot moves image content in opposite directions on either side of it; a global
    average pools that displacement field to ~0, a grid keeps it."""

    def __init__(self, channels: int, squeeze: int = 64):
        super().__init__()
        self.pool = nn.Sequential(
            nn.AdaptiveAvgPool2d(GRID), nn.Conv2d(channels, squeeze, 1), nn.ReLU(inplace=True), nn.Flatten()
        )
        self.head = zero_head(squeeze * GRID[0] * GRID[1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.pool(x))


def local_correlation(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """FlowNet-C style cost volume: for each displacement d in [-r, r]^2 the mean over channels
    of a(x) * b(x + d) (features L2-normalised per cell), ``[B, (2r+1)^2, h, w]``."""
    a = nn.functional.normalize(a, dim=1)
    b = nn.functional.pad(nn.functional.normalize(b, dim=1), [radius] * 4)
    h, w = a.shape[-2:]
    span = range(2 * radius + 1)
    return torch.stack([(a * b[:, :, i : i + h, j : j + w]).sum(1) for i in span for j in span], dim=1)


def conv_block(c_in: int, c_out: int, stride: int = 1, groups: int | None = None) -> nn.Sequential:
    """3x3 convolution, batch norm (or group norm over ``groups`` groups: small batches) and ReLU."""
    norm = nn.BatchNorm2d(c_out) if groups is None else nn.GroupNorm(groups, c_out)
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False), norm, nn.ReLU(inplace=True))


def upsample(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return nn.functional.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)
