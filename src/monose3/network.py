"""The render-and-compare pose denoising network (Sec. III-C): inputs, pose update (Eq. 9)
and the disentangled point-matching loss (Eq. 10)."""

from __future__ import annotations

import math

import torch
import torchvision
from torch import nn

from monose3.config import NetworkConfig
from monose3.se3 import gram_schmidt_6d, make_pose, rotation_to_6d, transform_points

NUM_OUTPUTS = 9  # v_xy (2), dR 6D (6), v_z (1)
_IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps ``[B]`` to ``[B, dim]`` (C_emb, Sec. III-C)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


class Denoiser(nn.Module):
    """ResNet (from scratch) over render (3) + crop (3) + timestep embedding (C_emb) channels.

    Outputs raw values; :func:`raw_to_update` turns them into (v_xy, dR, v_z).
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        factory = {"resnet34": torchvision.models.resnet34, "resnet18": torchvision.models.resnet18}
        if config.backbone not in factory:
            raise ValueError(f"unknown backbone {config.backbone!r}")
        net = factory[config.backbone](weights=None)
        net.conv1 = nn.Conv2d(6 + config.time_embedding_dim, 64, kernel_size=7, stride=2, padding=3, bias=False)
        net.fc = nn.Linear(net.fc.in_features, NUM_OUTPUTS)
        # A zero head starts as the identity update, so early training does not fling poses away.
        nn.init.zeros_(net.fc.weight)
        nn.init.zeros_(net.fc.bias)
        self.net = net

    def forward(self, render: torch.Tensor, crop: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``render``, ``crop``: ``[B, 3, h, w]`` in [0, 1]; ``t``: ``[B]`` steps. Returns ``[B, 9]``."""
        b, _, h, w = render.shape
        emb = timestep_embedding(t, self.config.time_embedding_dim).to(render.dtype)
        x = torch.cat([(render - 0.5) * 4.0, (crop - 0.5) * 4.0, emb[:, :, None, None].expand(b, -1, h, w)], dim=1)
        return self.net(x)


def raw_to_update(raw: torch.Tensor, render_width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Network outputs to (v_xy in crop pixels, dR ``[B, 3, 3]``, v_z ratio).

    v_xy is predicted as a fraction of the render width, dR as an offset from the identity
    6D vector and v_z as a log-ratio, so a zero output is the identity update.
    """
    v_xy = raw[:, :2] * render_width
    d_rot = gram_schmidt_6d(raw[:, 2:8] + _IDENTITY_6D.to(raw))
    v_z = torch.exp(raw[:, 8].clamp(-3.0, 3.0))
    return v_xy, d_rot, v_z


def update_to_raw(v_xy: torch.Tensor, d_rot: torch.Tensor, v_z: torch.Tensor, render_width: int) -> torch.Tensor:
    """Inverse of :func:`raw_to_update` (for tests and analysis)."""
    return torch.cat([v_xy / render_width, rotation_to_6d(d_rot) - _IDENTITY_6D.to(v_xy), torch.log(v_z)[:, None]], 1)


def apply_update(
    pose_ref: torch.Tensor, v_xy: torch.Tensor, d_rot: torch.Tensor, v_z: torch.Tensor, K_crop: torch.Tensor
) -> torch.Tensor:
    """Pose update of Eq. 9 about the reference point (camera-from-centroid poses):

    t0_z = v_z t_z;  t0_xy = (v_xy / f + t_xy / t_z) t0_z;  R0 = dR R_t,
    with f the crop intrinsics' focal lengths (v_xy is a displacement in crop pixels).
    """
    t = pose_ref[:, :3, 3]
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=1)
    tz0 = v_z * t[:, 2]
    txy0 = (v_xy / f + t[:, :2] / t[:, 2:3]) * tz0[:, None]
    return make_pose(d_rot @ pose_ref[:, :3, :3], torch.cat([txy0, tz0[:, None]], dim=1))


def true_update(
    pose_ref_t: torch.Tensor, pose_ref_0: torch.Tensor, K_crop: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The (v_xy, dR, v_z) that Eq. 9 needs to map H_t exactly onto H_0."""
    t, t0 = pose_ref_t[:, :3, 3], pose_ref_0[:, :3, 3]
    f = torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], dim=1)
    v_xy = f * (t0[:, :2] / t0[:, 2:3] - t[:, :2] / t[:, 2:3])
    d_rot = pose_ref_0[:, :3, :3] @ pose_ref_t[:, :3, :3].transpose(1, 2)
    return v_xy, d_rot, t0[:, 2] / t[:, 2]


def point_distance(pose_a: torch.Tensor, pose_b: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Dist of Eq. 10: mean over points of the L1 distance between the transformed points, ``[B]``."""
    return (transform_points(pose_a, points) - transform_points(pose_b, points)).abs().sum(-1).mean(-1)


def disentangled_loss(
    raw: torch.Tensor,
    pose_ref_t: torch.Tensor,
    pose_ref_0: torch.Tensor,
    K_crop: torch.Tensor,
    points_ref: torch.Tensor,
    render_width: int,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Disentangled point-matching loss, Eq. 10: each of v_xy, dR, v_z is judged by the pose it
    gives with the other two parts taken from the ground truth.

    ``points_ref``: ``[B, N, 3]`` model points in the centroid frame. Returns the batch mean
    and its three parts.
    """
    v_xy, d_rot, v_z = raw_to_update(raw, render_width)
    g_xy, g_rot, g_z = true_update(pose_ref_t, pose_ref_0, K_crop)
    parts = {
        "xy": point_distance(pose_ref_0, apply_update(pose_ref_t, v_xy, g_rot, g_z, K_crop), points_ref),
        "rot": point_distance(pose_ref_0, apply_update(pose_ref_t, g_xy, d_rot, g_z, K_crop), points_ref),
        "z": point_distance(pose_ref_0, apply_update(pose_ref_t, g_xy, g_rot, v_z, K_crop), points_ref),
    }
    parts = {k: v.mean() for k, v in parts.items()}
    return parts["xy"] + parts["rot"] + parts["z"], parts
