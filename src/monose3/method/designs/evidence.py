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

import torch
from torch import nn

from monose3.method.config import NetworkConfig
from monose3.method.denoiser import Denoiser, DenoiserOutput
from monose3.method.designs.blocks import zero_head
from monose3.method.evidence import EVIDENCE_CHANNELS
from monose3.method.flow_pose import Surface

WIDTHS = (32, 64, 128, 128, 256)  # one 3x3 convolution each; all but the first halve the resolution


def conv_block(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.GroupNorm(8, cout), nn.ReLU(inplace=True))


class EvidenceNet(Denoiser):
    """A plain CNN over the evidence side, the render side (:data:`EVIDENCE_CHANNELS` each) and
    the timestep embedding, regressing the raw outputs of the update (Eq. 9)."""

    inputs = "parser"
    channels = EVIDENCE_CHANNELS

    def __init__(self, config: NetworkConfig, pretrained: bool = True):  # noqa: ARG002 - trained from scratch
        super().__init__(config)
        channels = 2 * EVIDENCE_CHANNELS + config.time_embedding_dim
        layers, cin = [], channels
        for i, cout in enumerate(WIDTHS):
            layers.append(conv_block(cin, cout, 1 if i == 0 else 2))
            cin = cout
        self.trunk = nn.Sequential(*layers)
        w, h = config.render_size
        cells = -(-w // 2 ** (len(WIDTHS) - 1)) * -(-h // 2 ** (len(WIDTHS) - 1))
        self.head = zero_head(WIDTHS[-1] * cells)

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        b, _, h, w = render.shape
        x = torch.cat([crop, render, emb[:, :, None, None].expand(b, -1, h, w)], 1)
        return DenoiserOutput(self.head(self.trunk(x).flatten(1)))
