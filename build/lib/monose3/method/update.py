"""The pose update of Eq. 9: the network's raw outputs as (v_xy, dR, v_z), applied about the
reference point, and the exact update that maps H_t onto H_0 (the training target)."""

from __future__ import annotations

import torch

from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import matrix_to_rotation_6d, rotation_6d_to_matrix

IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


def raw_to_update(raw: torch.Tensor, render_width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Network outputs to (v_xy in crop pixels, dR ``[B, 3, 3]``, v_z ratio).

    v_xy is predicted as a fraction of the render width, dR as an offset from the identity
    6D vector and v_z as a log-ratio, so a zero output is the identity update.
    """
    v_xy = raw[:, :2] * render_width
    d_rot = rotation_6d_to_matrix(raw[:, 2:8] + IDENTITY_6D.to(raw))
    v_z = torch.exp(raw[:, 8].clamp(-3.0, 3.0))
    return v_xy, d_rot, v_z


def update_to_raw(v_xy: torch.Tensor, d_rot: torch.Tensor, v_z: torch.Tensor, render_width: int) -> torch.Tensor:
    """Inverse of :func:`raw_to_update` (for tests and analysis)."""
    return torch.cat(
        [v_xy / render_width, matrix_to_rotation_6d(d_rot) - IDENTITY_6D.to(v_xy), torch.log(v_z)[:, None]], 1
    )


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
