"""The disentangled point-matching loss of Eq. 10."""

from __future__ import annotations

import torch

from monose3.geometry.poses import transform_points
from monose3.method.update import apply_update, raw_to_update, true_update


def point_distance(pose_a: torch.Tensor, pose_b: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Dist of Eq. 10: mean over points of the L1 distance between the transformed points, ``[B]``."""
    return (transform_points(pose_a, points) - transform_points(pose_b, points)).abs().sum(-1).mean(-1)


def disentangled_parts(
    raw: torch.Tensor,
    pose_ref_t: torch.Tensor,
    pose_ref_0: torch.Tensor,
    K_crop: torch.Tensor,
    points_ref: torch.Tensor,
    render_width: int,
) -> dict[str, torch.Tensor]:
    """Per-sample parts of Eq. 10, ``{"xy", "rot", "z"}`` each ``[B]``: each of v_xy, dR, v_z
    judged by the pose it gives with the other two parts taken from the ground truth."""
    v_xy, d_rot, v_z = raw_to_update(raw, render_width)
    g_xy, g_rot, g_z = true_update(pose_ref_t, pose_ref_0, K_crop)
    return {
        "xy": point_distance(pose_ref_0, apply_update(pose_ref_t, v_xy, g_rot, g_z, K_crop), points_ref),
        "rot": point_distance(pose_ref_0, apply_update(pose_ref_t, g_xy, d_rot, g_z, K_crop), points_ref),
        "z": point_distance(pose_ref_0, apply_update(pose_ref_t, g_xy, g_rot, v_z, K_crop), points_ref),
    }


def disentangled_loss(
    raw: torch.Tensor,
    pose_ref_t: torch.Tensor,
    pose_ref_0: torch.Tensor,
    K_crop: torch.Tensor,
    points_ref: torch.Tensor,
    render_width: int,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Disentangled point-matching loss, Eq. 10 (batch means of :func:`disentangled_parts`).

    ``points_ref``: ``[B, N, 3]`` model points in the centroid frame. Returns the batch mean
    and its three parts.
    """
    per_sample = disentangled_parts(raw, pose_ref_t, pose_ref_0, K_crop, points_ref, render_width)
    parts = {k: v.mean() for k, v in per_sample.items()}
    return parts["xy"] + parts["rot"] + parts["z"], parts


def flow_loss(flow: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean error of a predicted displacement field ``[B, 2, h, w]`` over the cells in ``mask``
    ``[B, 1, h, w]``: L1, or, when ``flow`` has a third channel (log of a Laplace scale b per
    cell, ``flow-solve``), the Laplace negative log-likelihood |f - f*| / b + log b, which
    teaches the network how far each cell of its field can be trusted."""
    mask = mask.to(flow.dtype)
    error = (flow[:, :2] - target).abs()
    if flow.shape[1] == 3:
        log_scale = flow[:, 2:]
        error = error * torch.exp(-log_scale) + log_scale
    return (error * mask).sum() / (2 * mask.sum()).clamp(min=1)


def flow_errors(flow: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 error of each sample's displacement field (its first two channels), ``[B]`` (for judging)."""
    mask = mask.to(flow.dtype)
    return ((flow[:, :2] - target).abs() * mask).sum((1, 2, 3)) / (2 * mask.sum((1, 2, 3))).clamp(min=1)
