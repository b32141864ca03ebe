"""The paper's denoiser (``concat``) and its grid-headed variant (``concat-grid``)."""

from __future__ import annotations

import torch
from torch import nn

from monose3.method.config import NetworkConfig
from monose3.method.denoiser import NUM_OUTPUTS, Denoiser, DenoiserOutput
from monose3.method.designs.blocks import GridHead, coord_channels, resnet, to_net_range
from monose3.method.flow_pose import Surface


class Concat(Denoiser):
    """The paper's (Sec. III-C): a ResNet (from scratch) over render (3) + crop (3) + timestep
    embedding (C_emb) channels, regressing the raw outputs."""

    coordinates = False  # whether CoordConv channels join the input

    def __init__(self, config: NetworkConfig, pretrained: bool = True):  # noqa: ARG002 - a ResNet from scratch
        super().__init__(config)
        net = resnet(config.backbone)
        channels = 6 + 2 * self.coordinates + config.time_embedding_dim
        net.conv1 = nn.Conv2d(channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.net = self.with_head(net)

    def with_head(self, net: nn.Module) -> nn.Module:
        """The trunk with its regression head: a zero one, which starts as the identity update,
        so early training does not fling poses away."""
        net.fc = nn.Linear(net.fc.in_features, NUM_OUTPUTS)
        nn.init.zeros_(net.fc.weight)
        nn.init.zeros_(net.fc.bias)
        return net

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        b, _, h, w = render.shape
        x = [to_net_range(render), to_net_range(crop), emb[:, :, None, None].expand(b, -1, h, w)]
        if self.coordinates:
            x.append(coord_channels(b, h, w, render))
        return DenoiserOutput(self.net(torch.cat(x, dim=1)))


class ConcatGrid(Concat):
    """``concat`` with CoordConv channels and a :class:`~monose3.method.designs.blocks.GridHead`
    instead of the global pool (docs/DESIGNS.md)."""

    coordinates = True

    def with_head(self, net: nn.Module) -> nn.Module:
        return nn.Sequential(
            net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2, net.layer3, net.layer4,
            GridHead(net.fc.in_features),
        )  # fmt: skip
