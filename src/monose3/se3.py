"""Pure, batched rigid-transform helpers on torch tensors (the numpy ones, which need no
torch, are in :mod:`monose3.se3_np`).

Poses are 4x4 homogeneous matrices ``T_a_b`` mapping points in frame b to frame a.
"""

from __future__ import annotations

import torch


def gram_schmidt_6d(r6: torch.Tensor) -> torch.Tensor:
    """6D rotation (two columns, ``[..., 6]`` as r1|r2) to a rotation matrix (Eq. 6).

    u1 = r1/|r1|, u2 = normalise(r2 - (r2.u1) u1), u3 = u1 x u2; the columns are (u1, u2, u3),
    so the result is a proper rotation for any input whose two columns are not parallel.
    """
    r1, r2 = r6[..., :3], r6[..., 3:6]
    u1 = torch.nn.functional.normalize(r1, dim=-1, eps=1e-8)
    u2 = r2 - (r2 * u1).sum(-1, keepdim=True) * u1
    u2 = torch.nn.functional.normalize(u2, dim=-1, eps=1e-8)
    u3 = torch.linalg.cross(u1, u2, dim=-1)
    return torch.stack([u1, u2, u3], dim=-1)


def rotation_to_6d(rot: torch.Tensor) -> torch.Tensor:
    """First two columns of ``rot`` (``[..., 3, 3]``) as ``[..., 6]`` (r1|r2), the Eq. 4 layout."""
    return torch.cat([rot[..., :, 0], rot[..., :, 1]], dim=-1)


def make_pose(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Stack ``[..., 3, 3]`` rotations and ``[..., 3]`` translations into ``[..., 4, 4]`` poses."""
    pose = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    pose[..., :3, :3] = rot
    pose[..., :3, 3] = trans
    pose[..., 3, 3] = 1.0
    return pose


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``[..., 4, 4]`` poses to ``[..., N, 3]`` points."""
    return points @ pose[..., :3, :3].transpose(-1, -2) + pose[..., None, :3, 3]


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """Rotation from extrinsic XYZ Euler angles ``[..., 3]`` (radians): R = Rz @ Ry @ Rx."""
    cx, cy, cz = torch.cos(angles).unbind(-1)
    sx, sy, sz = torch.sin(angles).unbind(-1)
    one, zero = torch.ones_like(cx), torch.zeros_like(cx)
    rx = torch.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1)
    ry = torch.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1)
    rz = torch.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1)
    shape = (*angles.shape[:-1], 3, 3)
    return rz.reshape(shape) @ ry.reshape(shape) @ rx.reshape(shape)


def rotation_angle(rot_a: torch.Tensor, rot_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (radians) between ``[..., 3, 3]`` rotations."""
    rel = rot_a.transpose(-1, -2) @ rot_b
    cos = (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    return torch.arccos(cos.clamp(-1.0, 1.0))
