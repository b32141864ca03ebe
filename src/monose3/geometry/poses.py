"""Rigid poses as ``[..., 4, 4]`` homogeneous matrices, numpy or torch alike.

Naming, stated once: ``a_from_b`` (written ``T_a_b`` in formulas) maps points in frame b to
frame a. The estimate monose3 returns is ``camera_from_base``: the robot base's pose in the
camera frame (OpenCV camera axes: x right, y down, z forward), in metres.
"""

from __future__ import annotations

import numpy as np

from monose3.geometry.arrays import array_module
from monose3.geometry.rotations import euler_xyz_to_matrix, procrustes


def make_pose(rot, trans):
    """Stack ``[..., 3, 3]`` rotations and ``[..., 3]`` translations into ``[..., 4, 4]`` poses."""
    xp = array_module(rot)
    if xp is np:
        rot, trans = np.asarray(rot, np.float64), np.asarray(trans, np.float64)
        pose = np.zeros((*rot.shape[:-2], 4, 4))
    else:
        pose = xp.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    pose[..., :3, :3] = rot
    pose[..., :3, 3] = trans
    pose[..., 3, 3] = 1.0
    return pose


def invert_pose(pose):
    """``b_from_a`` from ``a_from_b`` ``[..., 4, 4]``: (R, t) -> (R^T, -R^T t)."""
    xp = array_module(pose)
    rot_t = xp.swapaxes(pose[..., :3, :3], -1, -2)
    return make_pose(rot_t, -(rot_t @ pose[..., :3, 3:4])[..., 0])


def transform_points(pose, points):
    """Apply ``[..., 4, 4]`` poses to ``[..., N, 3]`` points."""
    xp = array_module(pose)
    return points @ xp.swapaxes(pose[..., :3, :3], -1, -2) + pose[..., None, :3, 3]


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares rigid transform T with dst ~ T src for ``[N, 3]`` point sets (Kabsch, no scale).

    Returns the 4x4 transform and the RMS residual in the points' unit.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    rot = procrustes((dst - mu_d).T @ (src - mu_s))
    pose = make_pose(rot, mu_d - rot @ mu_s)
    resid = dst - transform_points(pose, src)
    return pose, float(np.sqrt((resid**2).sum(1).mean()))


def perturb_poses(poses: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float,
                  pivot: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Poses ``[N, 4, 4]`` moved by Gaussian noise: the rotation turned by XYZ Euler angles of
    std ``rot_deg`` per axis (in the camera frame, about the base origin, or about ``pivot``, a
    point ``[3]`` in the base frame), the translation shifted by std ``trans_m`` per axis. Stands
    in for a rough prior or an inter-frame motion, and draws the local search's trial poses."""
    out = np.array(poses, np.float64)
    turn = euler_xyz_to_matrix(rng.normal(0, np.radians(rot_deg), (len(out), 3)))
    centre = out[:, :3, 3] if pivot is None else transform_points(out, np.asarray(pivot, np.float64)[None])[:, 0]
    out[:, :3, :3] = turn @ out[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", turn, out[:, :3, 3] - centre) + centre
    out[:, :3, 3] += rng.normal(0, trans_m, (len(out), 3))
    return out
