"""The robot parser: from the whole image, the robot's mask and its keypoints' heatmaps.

Not in the paper. Dense 2D evidence is what the best known-joint systems fit the pose to
(DREAM's keypoints + PnP, CtRNet's mask + keypoints, EasyHeC's mask); a dense prediction on an
ImageNet-pretrained trunk learns from far fewer samples than a pose regressor. The network is
EfficientNet-Lite0 with a small U-Net decoder to stride 2: one mask logit per cell and, per
keypoint, logits of a spatial softmax (where the keypoint is).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from monose3.networks.backbone import FEATURE_CHANNELS, EfficientNetLite0, pretrained_lite0
from monose3.perception.config import ParserConfig

OUTPUT_STRIDE = 2
PEAK_RADIUS = 2  # cells around a heatmap's peak that its sub-cell position is averaged over


def _conv(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class RobotParser(nn.Module):
    """``forward(image [B, 3, H, W] in [0, 1]) -> (mask logits [B, 1, H/2, W/2],
    keypoint logits [B, K, H/2, W/2])``."""

    def __init__(self, config: ParserConfig, pretrained: bool = True):
        super().__init__()
        self.config = config
        self.trunk = pretrained_lite0() if pretrained else EfficientNetLite0()
        self.trunk.drop_classifier()
        width = config.decoder_width
        deep = FEATURE_CHANNELS[::-1]  # 320 (s32), 112, 40, 24, 16 (s2)
        self.top = _conv(deep[0], width)
        self.merge = nn.ModuleList(_conv(width + c, width) for c in deep[1:])
        self.head = nn.Conv2d(width, 1 + config.num_keypoints, 1)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.trunk.features(image)[::-1]
        x = self.top(feats[0])
        for skip, merge in zip(feats[1:], self.merge, strict=True):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = merge(torch.cat([x, skip], 1))
        out = self.head(x)
        return out[:, :1], out[:, 1:]


def cell_to_pixel(uv: torch.Tensor) -> torch.Tensor:
    """Output-cell coordinates to input pixels (pixel centres at integers, as OpenCV)."""
    return (uv + 0.5) * OUTPUT_STRIDE - 0.5


def pixel_to_cell(uv: torch.Tensor) -> torch.Tensor:
    return (uv + 0.5) / OUTPUT_STRIDE - 0.5


def decode_keypoints(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Keypoints ``[B, K, 2]`` (input pixels) and their confidence ``[B, K]`` (the probability
    mass near the peak) from heatmap logits ``[B, K, h, w]``: the peak cell, refined to sub-cell
    precision by the probability-weighted mean of the cells within :data:`PEAK_RADIUS`."""
    b, k, h, w = logits.shape
    prob = logits.flatten(2).softmax(-1).view(b, k, h, w)
    peak = prob.flatten(2).argmax(-1)
    py, px = peak // w, peak % w
    offsets = torch.arange(-PEAK_RADIUS, PEAK_RADIUS + 1, device=logits.device)
    ys = (py[..., None] + offsets).clamp(0, h - 1)  # [B, K, R]
    xs = (px[..., None] + offsets).clamp(0, w - 1)
    window = prob.gather(2, ys[..., None].expand(b, k, len(offsets), w))  # rows [B, K, R, w]
    window = window.gather(3, xs[:, :, None, :].expand(b, k, len(offsets), len(offsets)))  # [B, K, R, R]
    mass = window.sum((-1, -2)).clamp_min(1e-12)
    u = (window.sum(-2) * xs.float()).sum(-1) / mass
    v = (window.sum(-1) * ys.float()).sum(-1) / mass
    return cell_to_pixel(torch.stack([u, v], -1)), mass


def mask_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy plus a soft Dice term per image (so small robots weigh as much as big ones)."""
    bce = F.binary_cross_entropy_with_logits(logits, target)
    prob = logits.sigmoid()
    inter = (prob * target).sum((1, 2, 3))
    dice = 1 - (2 * inter + 1) / (prob.sum((1, 2, 3)) + target.sum((1, 2, 3)) + 1)
    return bce + dice.mean()


def keypoint_loss(logits: torch.Tensor, uv: torch.Tensor, sigma: float) -> torch.Tensor:
    """Cross-entropy of each heatmap's spatial softmax against a Gaussian of ``sigma`` cells
    around the keypoint ``uv`` ``[B, K, 2]`` (input pixels); keypoints outside the image are skipped."""
    b, k, h, w = logits.shape
    cell = pixel_to_cell(uv)
    inside = (cell[..., 0] > -0.5) & (cell[..., 0] < w - 0.5) & (cell[..., 1] > -0.5) & (cell[..., 1] < h - 0.5)
    xs = torch.arange(w, device=logits.device, dtype=logits.dtype)
    ys = torch.arange(h, device=logits.device, dtype=logits.dtype)
    gx = torch.exp(-((xs - cell[..., 0:1]) ** 2) / (2 * sigma**2))  # [B, K, w]
    gy = torch.exp(-((ys - cell[..., 1:2]) ** 2) / (2 * sigma**2))  # [B, K, h]
    target = gy[..., :, None] * gx[..., None, :]
    target = target / target.sum((-1, -2), keepdim=True).clamp_min(1e-12)
    ce = -(target * logits.flatten(2).log_softmax(-1).view(b, k, h, w)).sum((-1, -2))
    return (ce * inside).sum() / inside.sum().clamp_min(1)
