"""The ``evidence`` denoiser: render-and-compare against the robot parser's evidence (not in the
paper; docs/DESIGNS.md, round 6).

Its "crop" is the parser's mask and keypoint maps in the RoboPose crop around H_t and its
"render" the silhouette and projected keypoints at H_t (:mod:`monose3.method.evidence`), so it
compares two maps of the same kind instead of learning to read the robot out of raw pixels: a
far smaller problem, which a plain CNN learns on a CPU. Small crops (64x48) suffice, as the maps
hold no texture. The head sees the flattened last feature map, not a global mean, so where a
feature is (the offset between the two sides) survives to the output.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from monose3.geometry.pose_solve import solve_pose
from monose3.geometry.poses import make_pose
from monose3.method.config import NetworkConfig
from monose3.method.denoiser import NUM_OUTPUTS, Denoiser, DenoiserOutput, timestep_of
from monose3.method.designs.blocks import conv_block, zero_head
from monose3.method.evidence import EVIDENCE_CHANNELS, KEYPOINT_CHANNELS, KEYPOINT_SIGMA
from monose3.method.flow_pose import Surface, sample_field
from monose3.method.pose_space import MIN_DEPTH
from monose3.method.update import true_update, update_to_raw

WIDTHS = (32, 64, 128, 128, 256)  # one 3x3 convolution each; all but the first halve the resolution
GROUPS = 8  # group norm: the batch statistics of a few samples (tracking, chains) would swing a batch norm
# evidence-solve: the solve's prior on the update (log precisions per rotation-vector radian and
# unit of depth) starts negligible beside the keypoints' pull, and moves PRIOR_GAIN times as fast
# as its weights; a keypoint's weight starts at its blob's share (exp(0)) and learns per sample.
INITIAL_LOG_PRIOR = -5.0
PRIOR_GAIN = 10.0
# Its displacement field comes off the trunk's third block (a quarter of the crop's resolution).
# A cell's pull weighs (FIELD_UNIT / scale)^2: about 1 where the network is sure to a pixel of a
# 64-wide crop; at init (scale 0.5 render widths) the few hundred surface points weigh less
# together than one keypoint.
FIELD_BLOCK = 2
FIELD_UNIT = 0.02
INITIAL_FIELD_LOG_SCALE = math.log(0.5)
# The field reaches a few pixels (its receptive field at a quarter of the crop), the moves of
# small t; beyond them its pulls are off however sure it is, so they count by a gate that falls
# from 1 to 0 about t = FIELD_T (its trust learnt per cell at every t spread to the large ones).
FIELD_T, FIELD_T_WIDTH = 12.0, 3.0


class EvidenceNet(Denoiser):
    """A plain CNN over the evidence side, the render side (:data:`EVIDENCE_CHANNELS` each) and
    the timestep embedding, regressing the raw outputs of the update (Eq. 9)."""

    inputs = "parser"
    channels = EVIDENCE_CHANNELS
    outputs = NUM_OUTPUTS  # of its head: Eq. 9's raw outputs

    def __init__(self, config: NetworkConfig, pretrained: bool = True):  # noqa: ARG002 - trained from scratch
        super().__init__(config)
        channels = 2 * EVIDENCE_CHANNELS + config.time_embedding_dim
        layers, cin = [], channels
        for i, cout in enumerate(WIDTHS):
            layers.append(conv_block(cin, cout, 1 if i == 0 else 2, GROUPS))
            cin = cout
        self.trunk = nn.Sequential(*layers)
        w, h = config.render_size
        cells = -(-w // 2 ** (len(WIDTHS) - 1)) * -(-h // 2 ** (len(WIDTHS) - 1))
        self.head = zero_head(WIDTHS[-1] * cells, self.outputs)

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        b, _, h, w = render.shape
        x = torch.cat([crop, render, emb[:, :, None, None].expand(b, -1, h, w)], 1)
        return DenoiserOutput(self.head(self.trunk(x).flatten(1)))


def blob_centres(maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The centre ``[B, C, 2]`` (crop pixels) of each keypoint map ``[B, C, h, w]`` and its mass
    as a share ``[B, C]`` of a whole blob of weight 1: the keypoint's confidence times how much
    of its blob the crop holds (0 where the map is empty)."""
    b, c, h, w = maps.shape
    ys = torch.arange(h, dtype=maps.dtype, device=maps.device)
    xs = torch.arange(w, dtype=maps.dtype, device=maps.device)
    mass = maps.sum((2, 3))
    safe = mass.clamp_min(1e-6)
    centre = torch.stack([(maps.sum(2) * xs).sum(-1) / safe, (maps.sum(3) * ys).sum(-1) / safe], -1)
    return centre, (mass / (2 * torch.pi * KEYPOINT_SIGMA**2)).clamp(0, 1)


class EvidenceSolve(EvidenceNet):
    """The evidence denoiser whose pose is solved, not regressed (as ``flow-solve`` solves it from
    a displacement field). Two kinds of pulls on the render at H_t, each weighted by how far the
    network trusts it, fitted at once (damped Gauss-Newton from H_t against a prior on the update
    learned per t: :func:`~monose3.geometry.pose_solve.solve_pose`):

    * each keypoint to where the parser's blob of it lies in the crop (its centre), moved by a
      learned residual and weighted by a learned confidence times the blob's share in the crop:
      they carry large moves, as the blobs say which keypoint is which;
    * each point of the render's visible surface by a displacement field the network predicts
      from the two sides at a quarter of the crop's resolution, with a Laplace scale per cell
      (``flow_weight`` trains it on the true field): the silhouettes' fine alignment. It starts
      trusted little (:data:`INITIAL_FIELD_LOG_SCALE`), so the keypoints lead until it learns,
      and acts at small t only (:data:`FIELD_T`), where its moves are within its reach.

    Untrained, it is a PnP step toward the parser's keypoints."""

    rotation_outputs = ("6d",)  # the raw outputs are those of a solved pose, never regressed
    predicts_field = True
    outputs = 3 * KEYPOINT_CHANNELS  # of its head: per keypoint a residual (x, y) in render widths and a log-weight

    def __init__(self, config: NetworkConfig, pretrained: bool = True):
        super().__init__(config, pretrained)
        self.field = nn.Sequential(conv_block(WIDTHS[FIELD_BLOCK], 64, 1, GROUPS), nn.Conv2d(64, 3, 1))
        nn.init.zeros_(self.field[1].weight)
        nn.init.zeros_(self.field[1].bias)
        nn.init.constant_(self.field[1].bias[2:], INITIAL_FIELD_LOG_SCALE)
        emb = config.time_embedding_dim
        self.prior = zero_head(emb, 6, hidden=32)

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        if surface.keypoints_ref is None:
            raise ValueError("evidence-solve needs the robot's keypoints with the surface (Surface.keypoints_ref)")
        b, _, h, w = render.shape
        x = torch.cat([crop, render, emb[:, :, None, None].expand(b, -1, h, w)], 1)
        for i, block in enumerate(self.trunk):
            x = block(x)
            if i == FIELD_BLOCK:
                field = self.field(x).float()
        out = self.head(x.flatten(1)).float().reshape(b, KEYPOINT_CHANNELS, 3)
        k = surface.keypoints_ref.shape[1]
        centres, share = blob_centres(crop[:, 1 : 1 + k].float())
        kp_target, kp_weights = centres + out[:, :k, :2] * w, share * torch.exp(out[:, :k, 2])
        # The field's pulls, by normalised convolution as flow_pose.pose_from_field takes them.
        precision = torch.exp(-2.0 * (field[:, 2:] - math.log(FIELD_UNIT)))
        sampled = sample_field(torch.cat([field[:, :2] * precision, precision], 1), surface.uv, (w, h))
        uv_target = surface.uv + sampled[..., :2] / sampled[..., 2:].clamp_min(1e-6) * w
        gate = torch.sigmoid((FIELD_T - timestep_of(emb.float())) / FIELD_T_WIDTH)
        uv_weights = sampled[..., 2] * surface.valid.float() * gate[:, None]
        points = torch.cat([surface.keypoints_ref.float(), surface.points_ref.float()], 1)
        prior = torch.exp(INITIAL_LOG_PRIOR + PRIOR_GAIN * self.prior(emb.float()))
        pose = solve_pose(surface.pose_ref_t.float(), surface.K_crop.float(), points,
                          torch.cat([kp_target, uv_target.float()], 1), torch.cat([kp_weights, uv_weights], 1),
                          prior)  # fmt: skip
        pose = make_pose(pose[:, :3, :3], torch.cat([pose[:, :2, 3], pose[:, 2:3, 3].clamp_min(MIN_DEPTH)], 1))
        raw = update_to_raw(*true_update(surface.pose_ref_t.float(), pose, surface.K_crop.float()), w)
        return DenoiserOutput(raw.to(render.dtype), field.to(render.dtype))
