"""The disentangled point-matching loss of Eq. 10."""

from __future__ import annotations

import torch

from monose3.geometry.camera import project
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


def flow_targets(
    pose_ref_t: torch.Tensor,
    pose_ref_0: torch.Tensor,
    K_crop: torch.Tensor,
    points_ref: torch.Tensor,
    render_size: tuple[int, int],
    cells: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The auxiliary target of the ``cost-volume`` design (not in the paper): where the robot's
    surface moves in the crop from H_t to H_0, per cell of a ``cells`` = (h, w) grid.

    Each model point is projected under H_t (where the render shows it) and under H_0 (where
    the crop shows it); a cell's target is the mean displacement of the points that H_t puts
    in it, in units of the render width. Returns ``flow [B, 2, h, w]`` and the cells that hold
    any point, ``mask [B, 1, h, w]``. Eq. 10 gives the network 9 numbers to learn from per
    sample; this gives it a displacement field, which a cost volume reads locally."""
    (width, height), (h, w) = render_size, cells
    uv_t = project(transform_points(pose_ref_t, points_ref), K_crop)
    uv_0 = project(transform_points(pose_ref_0, points_ref), K_crop)
    col = (uv_t[..., 0] * w / width).floor().long()
    row = (uv_t[..., 1] * h / height).floor().long()
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    b = len(points_ref)
    index = (torch.arange(b, device=row.device)[:, None] * h + row) * w + col
    index = torch.where(inside, index, b * h * w)  # one spare bin for points outside the crop
    shift = ((uv_0 - uv_t) / width).reshape(-1, 2)
    sums = torch.zeros(b * h * w + 1, 2, dtype=shift.dtype, device=shift.device)
    sums.index_add_(0, index.reshape(-1), shift)
    counts = torch.zeros(b * h * w + 1, dtype=shift.dtype, device=shift.device)
    counts.index_add_(0, index.reshape(-1), torch.ones_like(shift[:, 0]))
    flow = (sums[:-1] / counts[:-1, None].clamp(min=1)).reshape(b, h, w, 2).permute(0, 3, 1, 2)
    return flow, (counts[:-1] > 0).reshape(b, 1, h, w)


def flow_loss(flow: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 error of a predicted displacement field ``[B, 2, h, w]`` over the cells in ``mask``."""
    mask = mask.to(flow.dtype)
    return ((flow - target).abs() * mask).sum() / (2 * mask.sum()).clamp(min=1)


def flow_errors(flow: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """:func:`flow_loss` of each sample alone, ``[B]`` (for judging, not training)."""
    mask = mask.to(flow.dtype)
    return ((flow - target).abs() * mask).sum((1, 2, 3)) / (2 * mask.sum((1, 2, 3))).clamp(min=1)
