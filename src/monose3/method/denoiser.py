"""The render-and-compare pose denoising network (Sec. III-C): inputs, pose update (Eq. 9)
and the disentangled point-matching loss (Eq. 10)."""

from __future__ import annotations

import math

import torch
import torchvision
from torch import nn

from monose3.geometry.rotations import matrix_to_rotation_6d, rotvec_to_matrix
from monose3.method.config import DESIGNS, FIELD_DESIGNS, FIELD_STRIDES, ROTATION_OUTPUTS, NetworkConfig
from monose3.method.flow_pose import Surface, pose_from_field
from monose3.method.update import IDENTITY_6D, true_update, update_to_raw

NUM_OUTPUTS = 9  # v_xy (2), dR 6D (6), v_z (1)


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps ``[B]`` to ``[B, dim]`` (C_emb, Sec. III-C)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


_GRID = (3, 4)  # (h, w) cells the "-grid" designs pool the last feature map to (not one global mean)
# "cost-volume": radii of its two cost volumes, at strides 8 and 16; 4 and 3 cells reach +-32
# and +-48 px of a 128x96 crop, the render-crop offsets of t <= ~30.
_COST_RADII = (4, 3)
_FINEST_RADIUS = 3  # flow-solve at field_stride 4: its stride-4 cost volume reaches +-12 px
# flow-solve's prior on the update at init: ~1 % of what ~300 surface points of a 128x96 crop
# weigh in the solve (rotation per rad^2, translation per (depth unit)^2), so the field decides.
INITIAL_LOG_PRIOR = torch.tensor([7.0, 7.0, 7.5, 11.0, 11.0, 9.0])
_PRIOR_GAIN = 10.0  # the prior's log moves 10x faster than its weights, so Adam can move it by ~5 in 2000 steps
INITIAL_FIELD_SCALE = 0.02  # flow-solve: the field's Laplace scale at init (render widths, ~ t 1-10's moves)


def _resnet(backbone: str) -> torchvision.models.ResNet:
    factory = {"resnet34": torchvision.models.resnet34, "resnet18": torchvision.models.resnet18}
    if backbone not in factory:
        raise ValueError(f"unknown backbone {backbone!r}")
    return factory[backbone](weights=None)


def _to_net_range(image: torch.Tensor) -> torch.Tensor:
    """[0, 1] images to roughly zero-mean, unit-scale network input."""
    return (image - 0.5) * 4.0


def so3_raw(raw: torch.Tensor) -> torch.Tensor:
    """Raw outputs whose rotation part is read as a rotation vector (``raw[:, 2:5]``, radians)
    instead of a 6D offset, returned in the 6D layout :func:`raw_to_update` reads (exact: the
    6D of a rotation matrix is orthonormal already). Unlike the 6D offset, the rotation vector
    has no directions that leave dR unchanged: in those (the 6D columns' lengths and their
    mutual angle) the loss has zero gradient, and Adam turns the float noise there into
    full-size steps (measured: raw std ~0.3 on the two 6D diagonal entries after 1000 steps)."""
    rot = matrix_to_rotation_6d(rotvec_to_matrix(raw[:, 2:5])) - IDENTITY_6D.to(raw)
    return torch.cat([raw[:, :2], rot, raw[:, 8:]], dim=1)


def coord_channels(b: int, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """CoordConv channels ``[b, 2, h, w]``: x and y of each cell in [-1, 1] (where a feature is)."""
    ys = torch.linspace(-1.0, 1.0, h, dtype=like.dtype, device=like.device)
    xs = torch.linspace(-1.0, 1.0, w, dtype=like.dtype, device=like.device)
    grid = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1])
    return grid[None].expand(b, 2, h, w)


class GridHead(nn.Module):
    """Pools a feature map to a coarse :data:`_GRID` of cells (not one global mean), squeezes
    the channels and flattens, so the head knows *where* each feature is. A rotation about
    the robot moves image content in opposite directions on either side of it; a global
    average pools that displacement field to ~0, a grid keeps it."""

    def __init__(self, channels: int, squeeze: int = 64):
        super().__init__()
        self.pool = nn.Sequential(
            nn.AdaptiveAvgPool2d(_GRID), nn.Conv2d(channels, squeeze, 1), nn.ReLU(inplace=True), nn.Flatten()
        )
        self.head = _zero_head(squeeze * _GRID[0] * _GRID[1])

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


def _zero_head(in_features: int) -> nn.Sequential:
    """MLP to the 9 raw outputs whose last layer is zero: the identity update at init."""
    head = nn.Sequential(nn.Linear(in_features, 256), nn.ReLU(inplace=True), nn.Linear(256, NUM_OUTPUTS))
    nn.init.zeros_(head[2].weight)
    nn.init.zeros_(head[2].bias)
    return head


def _conv_block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)
    )


class CostVolumeNet(nn.Module):
    """Render and crop through one shared trunk; the rest of the network sees **only their
    comparison**: FlowNet-C cost volumes (:func:`local_correlation`) at strides 8 and 16
    (radii :data:`_COST_RADII`), with CoordConv channels and C_emb, and a :class:`GridHead`.

    No path carries the crop's (or the render's) own features past the correlation, so the
    crop-alone shortcut the other designs take for xy (docs/DESIGNS.md) does not exist: a
    shift, a rotation and a scale change of the robot between render and crop are all read
    as the displacement field that the cost volume encodes, where each cell is (the grid)."""

    def __init__(self, config: NetworkConfig, width: int = 128):
        super().__init__()
        net = _resnet(config.backbone)
        self.fine = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2)
        self.coarse = net.layer3
        r_fine, r_coarse = _COST_RADII
        self.fine_cost = _conv_block((2 * r_fine + 1) ** 2 + 2 + config.time_embedding_dim, width)
        self.down = _conv_block(width, width, stride=2)
        self.coarse_cost = nn.Sequential(
            _conv_block(width + (2 * r_coarse + 1) ** 2 + 2, 2 * width),
            _conv_block(2 * width, 2 * width),
            _conv_block(2 * width, 2 * width),
        )
        self.head = GridHead(2 * width)
        self.flow = nn.Conv2d(2 * width, 2, 1)  # the auxiliary displacement field (flow_pose.field_targets)

    def compare_features(self, fine: torch.Tensor, b: int, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The comparison of the trunk's stride-8 features ``fine`` (render's first ``b``, then the
        crop's): features at stride 8 ``[B, width, h/8, w/8]`` and 16 ``[B, 2 width, h/16, w/16]``."""
        r_fine, r_coarse = _COST_RADII
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
        fine = self.fine(torch.cat([_to_net_range(render), _to_net_range(crop)], dim=0))
        _, x = self.compare_features(fine, render.shape[0], emb)
        return self.head(x), self.flow(x)


class FlowSolveNet(CostVolumeNet):
    """:class:`CostVolumeNet`'s comparison, decoded (the coarse features upsampled beside the
    fine ones) to a displacement field and its uncertainty at ``config.field_stride``: 8, or 4
    with a third cost volume on the trunk's stride-4 features (layer1) for finer moves. No
    regression head: the pose comes from the field (:func:`monose3.method.flow_pose.pose_from_field`),
    so the network can only move the pose by saying where the render's parts are in the crop."""

    def __init__(self, config: NetworkConfig, width: int = 128):
        super().__init__(config, width)
        del self.head, self.flow
        if config.field_stride not in FIELD_STRIDES:
            raise ValueError(f"field_stride must be one of {FIELD_STRIDES}, got {config.field_stride}")
        self.decode = _conv_block(3 * width, width)
        self.finest: nn.Module | None = None
        out = width
        if config.field_stride == 4:
            self.finest = _conv_block(width + (2 * _FINEST_RADIUS + 1) ** 2 + 2, width // 2)
            out = width // 2
        self.field = nn.Conv2d(out, 3, 1)  # (dx, dy) in render widths, log of the Laplace scale
        nn.init.zeros_(self.field.weight)  # zero field, uniform scale: the identity update at init
        nn.init.zeros_(self.field.bias)
        nn.init.constant_(self.field.bias[2:], math.log(INITIAL_FIELD_SCALE))
        emb = config.time_embedding_dim
        self.prior = nn.Sequential(nn.Linear(emb, 32), nn.ReLU(inplace=True), nn.Linear(32, 6))
        nn.init.zeros_(self.prior[2].weight)
        nn.init.zeros_(self.prior[2].bias)

    def prior_precision(self, emb: torch.Tensor) -> torch.Tensor:
        """Precisions ``[B, 6]`` of the solve's prior on the update at each sample's t (learned:
        how far the poses of step t lie from H_0, against how far the field can be trusted)."""
        return torch.exp(INITIAL_LOG_PRIOR.to(emb) + _PRIOR_GAIN * self.prior(emb))

    def forward(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """The displacement field and the log of its Laplace scale per cell, ``[B, 3, h/s, w/s]``."""
        b = render.shape[0]
        stride4 = self.fine[:5](torch.cat([_to_net_range(render), _to_net_range(crop)], dim=0))
        x_fine, x = self.compare_features(self.fine[5:](stride4), b, emb)
        x = self.decode(torch.cat([x_fine, _upsample(x, x_fine)], dim=1))
        if self.finest is not None:
            h, w = stride4.shape[-2:]
            cost = local_correlation(stride4[:b], stride4[b:], _FINEST_RADIUS)
            x = self.finest(torch.cat([_upsample(x, stride4), cost, coord_channels(b, h, w, stride4)], dim=1))
        return self.field(x)


def _upsample(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return nn.functional.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


class Denoiser(nn.Module):
    """The pose denoiser of Sec. III-C; ``config.design`` picks the architecture (:data:`DESIGNS`).

    ``concat`` (the paper's): a ResNet (from scratch) over render (3) + crop (3) + timestep
    embedding (C_emb) channels; ``concat-grid``: the same with coordinate channels and a
    :class:`GridHead`. ``cost-volume``: :class:`CostVolumeNet`, whose head sees only the
    comparison. ``flow-solve``: :class:`FlowSolveNet`, the pose solved from its displacement
    field (docs/DESIGNS.md). Outputs raw values; :func:`raw_to_update` turns them into (v_xy, dR, v_z).
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        if config.design not in DESIGNS:
            raise ValueError(f"unknown denoiser design {config.design!r}; choose one of {DESIGNS}")
        if config.rotation_output not in ROTATION_OUTPUTS:
            raise ValueError(f"unknown rotation output {config.rotation_output!r}; choose one of {ROTATION_OUTPUTS}")
        if config.design == "concat-grid":
            net = _resnet(config.backbone)
            net.conv1 = nn.Conv2d(8 + config.time_embedding_dim, 64, kernel_size=7, stride=2, padding=3, bias=False)
            self.net = nn.Sequential(
                net.conv1,
                net.bn1,
                net.relu,
                net.maxpool,
                net.layer1,
                net.layer2,
                net.layer3,
                net.layer4,
                GridHead(net.fc.in_features),
            )
        elif config.design == "concat":
            net = _resnet(config.backbone)
            net.conv1 = nn.Conv2d(6 + config.time_embedding_dim, 64, kernel_size=7, stride=2, padding=3, bias=False)
            net.fc = nn.Linear(net.fc.in_features, NUM_OUTPUTS)
            # A zero head starts as the identity update, so early training does not fling poses away.
            nn.init.zeros_(net.fc.weight)
            nn.init.zeros_(net.fc.bias)
            self.net: nn.Module = net
        elif config.design == "cost-volume":
            self.net = CostVolumeNet(config)
        else:
            if config.rotation_output != "6d":
                raise ValueError("the flow-solve design solves its rotation from the field; use rotation_output='6d'")
            self.net = FlowSolveNet(config)

    @property
    def predicts_flow(self) -> bool:
        """Whether :meth:`forward` can also return a displacement field (``cost-volume``, ``flow-solve``)."""
        return self.config.design in FIELD_DESIGNS

    @property
    def needs_surface(self) -> bool:
        """Whether :meth:`forward` needs ``surface`` (the render's visible surface, flow_pose.render_surface)."""
        return self.config.design == "flow-solve"

    def forward(
        self,
        render: torch.Tensor,
        crop: torch.Tensor,
        t: torch.Tensor,
        surface: Surface | None = None,
        with_flow: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """``render``, ``crop``: ``[B, 3, h, w]`` in [0, 1]; ``t``: ``[B]`` steps; ``surface``: the
        render's visible surface (:func:`~monose3.method.flow_pose.render_surface`, needed by
        ``flow-solve``). Returns ``[B, 9]``, and with ``with_flow`` (:data:`FIELD_DESIGNS`) also
        the predicted displacement field ``[B, 2, h', w']`` (``flow-solve``: ``[B, 3, h', w']``,
        with the log of its Laplace scale) for :func:`monose3.method.loss.flow_loss`."""
        if with_flow and not self.predicts_flow:
            raise ValueError(f"the {self.config.design!r} denoiser predicts no flow; {FIELD_DESIGNS} do")
        emb = timestep_embedding(t, self.config.time_embedding_dim).to(render.dtype)
        flow = None
        if self.config.design == "flow-solve":
            raw, flow = self.solve(render, crop, emb, surface)
        elif self.config.design == "cost-volume":
            raw, flow = self.net(render, crop, emb)
        else:
            b, _, h, w = render.shape
            x = [_to_net_range(render), _to_net_range(crop), emb[:, :, None, None].expand(b, -1, h, w)]
            if self.config.design == "concat-grid":
                x.append(coord_channels(b, h, w, render))
            raw = self.net(torch.cat(x, dim=1))
        if self.config.rotation_output == "so3":
            raw = so3_raw(raw)
        return (raw, flow) if with_flow else raw

    def solve(
        self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``flow-solve``: the raw outputs of the update to the pose its field implies, and the
        field with its log-scale ``[B, 3, h/s, w/s]``. Each cell counts in the solve by its
        precision (1 / scale^2), against a prior on the update learned per t
        (:meth:`FlowSolveNet.prior_precision`): a field the network is unsure of moves the pose little."""
        if surface is None:
            raise ValueError("the flow-solve denoiser needs the render's surface (method.flow_pose.render_surface)")
        field = self.net(render, crop, emb)
        precision = torch.exp(-2.0 * (field[:, 2:].float() - math.log(INITIAL_FIELD_SCALE)))
        size = self.config.render_size
        prior = self.net.prior_precision(emb.float())
        pose_0 = pose_from_field(field[:, :2].float(), precision, surface, size, prior)
        return update_to_raw(*true_update(surface.pose_ref_t, pose_0, surface.K_crop), size[0]).to(field.dtype), field
