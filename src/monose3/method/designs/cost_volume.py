"""The designs that compare render and crop through cost volumes: ``cost-volume`` (a regression
head on the comparison) and ``flow-solve`` (the pose solved from a predicted displacement
field), on a ResNet trunk from scratch or on ImageNet-pretrained EfficientNet-Lite0
(``NetworkConfig.backbone = "efficientnet-lite0"``)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from monose3.method.config import BACKBONES, FIELD_STRIDES, NetworkConfig
from monose3.method.denoiser import Denoiser, DenoiserOutput
from monose3.method.designs.blocks import (
    GridHead,
    conv_block,
    coord_channels,
    local_correlation,
    resnet,
    to_net_range,
    upsample,
    zero_head,
)
from monose3.method.flow_pose import Surface, pose_from_field
from monose3.method.update import true_update, update_to_raw

# Radii of the two cost volumes, at strides 8 and 16; 4 and 3 cells reach +-32 and +-48 px of
# a 128x96 crop, the render-crop offsets of t <= ~30.
COST_RADII = (4, 3)
FINEST_RADIUS = 3  # flow-solve at field_stride 4: its stride-4 cost volume reaches +-12 px
# flow-solve's prior on the update at init: ~1 % of what ~300 surface points of a 128x96 crop
# weigh in the solve (rotation per rad^2, translation per (depth unit)^2), so the field decides.
INITIAL_LOG_PRIOR = torch.tensor([7.0, 7.0, 7.5, 11.0, 11.0, 9.0])
PRIOR_GAIN = 10.0  # the prior's log moves 10x faster than its weights, so Adam can move it by ~5 in 2000 steps
INITIAL_FIELD_SCALE = 0.02  # flow-solve: the field's Laplace scale at init (render widths, ~ t 1-10's moves)
PRETRAINED = BACKBONES[2]  # the ImageNet-pretrained trunk (monose3.networks.backbone)


def comparison_trunk(backbone: str, pretrained: bool = True) -> tuple[nn.Sequential, int, nn.Module, Callable]:
    """The shared trunk render and crop both go through: ``fine`` (image to stride 8, whose
    first ``split`` modules reach stride 4), ``coarse`` (stride 8 to 16) and the input scaling.
    A ResNet's layers 1-3 from scratch, or EfficientNet-Lite0's stages 1-5 with their ImageNet
    weights (``pretrained``; off where a checkpoint's weights replace them at once)."""
    if backbone == PRETRAINED:
        from monose3.networks.backbone import EfficientNetLite0, pretrained_lite0

        to_4, to_8, to_16 = (pretrained_lite0() if pretrained else EfficientNetLite0()).pyramid()
        return nn.Sequential(to_4, to_8), 1, to_16, nn.Identity()  # its stem scales the input
    net = resnet(backbone)
    return nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2), 5, net.layer3, to_net_range


class CostVolumeNet(nn.Module):
    """Render and crop through one shared trunk; the rest of the network sees **only their
    comparison**: FlowNet-C cost volumes (:func:`local_correlation`) at strides 8 and 16
    (radii :data:`COST_RADII`), with CoordConv channels and C_emb, and a :class:`GridHead`.

    No path carries the crop's (or the render's) own features past the correlation, so the
    crop-alone shortcut the concat designs take for xy (docs/DESIGNS.md) does not exist: a
    shift, a rotation and a scale change of the robot between render and crop are all read
    as the displacement field that the cost volume encodes, where each cell is (the grid)."""

    def __init__(self, config: NetworkConfig, width: int = 128, pretrained: bool = True):
        super().__init__()
        self.fine, self.split, self.coarse, self.scale_input = comparison_trunk(config.backbone, pretrained)
        r_fine, r_coarse = COST_RADII
        self.fine_cost = conv_block((2 * r_fine + 1) ** 2 + 2 + config.time_embedding_dim, width)
        self.down = conv_block(width, width, stride=2)
        self.coarse_cost = nn.Sequential(
            conv_block(width + (2 * r_coarse + 1) ** 2 + 2, 2 * width),
            conv_block(2 * width, 2 * width),
            conv_block(2 * width, 2 * width),
        )
        self.head = GridHead(2 * width)
        self.flow = nn.Conv2d(2 * width, 2, 1)  # the auxiliary displacement field (flow_pose.field_targets)

    def trunk(self, render: torch.Tensor, crop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Render's and crop's trunk features (render's first) at strides 4 and 8."""
        stride4 = self.fine[: self.split](self.scale_input(torch.cat([render, crop], dim=0)))
        return stride4, self.fine[self.split :](stride4)

    def compare_features(self, fine: torch.Tensor, b: int, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The comparison of the trunk's stride-8 features ``fine`` (render's first ``b``, then the
        crop's): features at stride 8 ``[B, width, h/8, w/8]`` and 16 ``[B, 2 width, h/16, w/16]``."""
        r_fine, r_coarse = COST_RADII
        coarse = self.coarse(fine)
        h, w = fine.shape[-2:]
        x = [local_correlation(fine[:b], fine[b:], r_fine), coord_channels(b, h, w, fine)]
        x_fine = self.fine_cost(torch.cat([*x, emb[:, :, None, None].expand(b, -1, h, w)], dim=1))
        h, w = coarse.shape[-2:]
        cost = local_correlation(coarse[:b], coarse[b:], r_coarse)
        x = torch.cat([self.down(x_fine), cost, coord_channels(b, h, w, coarse)], dim=1)
        return x_fine, self.coarse_cost(x)

    def forward(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The raw outputs ``[B, 9]`` and the predicted displacement field ``[B, 2, h/16, w/16]``."""
        _, fine = self.trunk(render, crop)
        _, x = self.compare_features(fine, render.shape[0], emb)
        return self.head(x), self.flow(x)


class FlowSolveNet(CostVolumeNet):
    """:class:`CostVolumeNet`'s comparison, decoded (the coarse features upsampled beside the
    fine ones) to a displacement field and its uncertainty at ``config.field_stride``: 8, or 4
    with a third cost volume on the trunk's stride-4 features for finer moves. No regression
    head: the pose comes from the field (:func:`monose3.method.flow_pose.pose_from_field`),
    so the network can only move the pose by saying where the render's parts are in the crop."""

    def __init__(self, config: NetworkConfig, width: int = 128, pretrained: bool = True):
        super().__init__(config, width, pretrained)
        del self.head, self.flow
        if config.field_stride not in FIELD_STRIDES:
            raise ValueError(f"field_stride must be one of {FIELD_STRIDES}, got {config.field_stride}")
        self.decode = conv_block(3 * width, width)
        self.finest: nn.Module | None = None
        out = width
        if config.field_stride == 4:
            self.finest = conv_block(width + (2 * FINEST_RADIUS + 1) ** 2 + 2, width // 2)
            out = width // 2
        self.field = nn.Conv2d(out, 3, 1)  # (dx, dy) in render widths, log of the Laplace scale
        nn.init.zeros_(self.field.weight)  # zero field, uniform scale: the identity update at init
        nn.init.zeros_(self.field.bias)
        nn.init.constant_(self.field.bias[2:], math.log(INITIAL_FIELD_SCALE))
        emb = config.time_embedding_dim
        self.prior = zero_head(emb, 6, hidden=32)

    def prior_precision(self, emb: torch.Tensor) -> torch.Tensor:
        """Precisions ``[B, 6]`` of the solve's prior on the update at each sample's t (learned:
        how far the poses of step t lie from H_0, against how far the field can be trusted)."""
        return torch.exp(INITIAL_LOG_PRIOR.to(emb) + PRIOR_GAIN * self.prior(emb))

    def forward(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """The displacement field and the log of its Laplace scale per cell, ``[B, 3, h/s, w/s]``."""
        b = render.shape[0]
        stride4, fine = self.trunk(render, crop)
        x_fine, x = self.compare_features(fine, b, emb)
        x = self.decode(torch.cat([x_fine, upsample(x, x_fine)], dim=1))
        if self.finest is not None:
            h, w = stride4.shape[-2:]
            cost = local_correlation(stride4[:b], stride4[b:], FINEST_RADIUS)
            x = self.finest(torch.cat([upsample(x, stride4), cost, coord_channels(b, h, w, stride4)], dim=1))
        return self.field(x)


class CostVolume(Denoiser):
    """:class:`CostVolumeNet`: raw outputs regressed from the comparison alone, and an
    auxiliary displacement field (``TrainConfig.flow_weight`` trains it)."""

    predicts_field = True

    def __init__(self, config: NetworkConfig, pretrained: bool = True):
        super().__init__(config)
        self.net = CostVolumeNet(config, pretrained=pretrained)

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        return DenoiserOutput(*self.net(render, crop, emb))


class FlowSolve(Denoiser):
    """:class:`FlowSolveNet`: the update is that to the pose its field implies (docs/DESIGNS.md)."""

    predicts_field = True
    rotation_outputs = ("6d",)  # the raw outputs are those of a solved pose, never regressed

    def __init__(self, config: NetworkConfig, pretrained: bool = True):
        super().__init__(config)
        self.net = FlowSolveNet(config, pretrained=pretrained)

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        """The raw outputs of the update to the pose the field implies, and the field with its
        log-scale ``[B, 3, h/s, w/s]``. Each cell counts in the solve by its precision
        (1 / scale^2), against a prior on the update learned per t
        (:meth:`FlowSolveNet.prior_precision`): a field the network is unsure of moves the pose little."""
        field = self.net(render, crop, emb)
        precision = torch.exp(-2.0 * (field[:, 2:].float() - math.log(INITIAL_FIELD_SCALE)))
        size = self.config.render_size
        prior = self.net.prior_precision(emb.float())
        pose_0 = pose_from_field(field[:, :2].float(), precision, surface, size, prior)
        raw = update_to_raw(*true_update(surface.pose_ref_t, pose_0, surface.K_crop), size[0])
        return DenoiserOutput(raw.to(field.dtype), field)
