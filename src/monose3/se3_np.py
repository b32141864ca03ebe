"""Pure, batched rigid-transform helpers in numpy: URDF rotations, quaternions, rigid fits.

Kept apart from :mod:`monose3.se3` so that what imports only these (the robot model, and
with it every render worker process; the dataset readers) does not load torch.
"""

from __future__ import annotations

import numpy as np


def euler_xyz_to_matrix_np(angles: np.ndarray) -> np.ndarray:
    """Rotations from extrinsic XYZ Euler angles ``[..., 3]`` (radians): R = Rz @ Ry @ Rx
    (as :func:`monose3.se3.euler_xyz_to_matrix`)."""
    angles = np.asarray(angles, np.float64)
    cx, cy, cz = np.moveaxis(np.cos(angles), -1, 0)
    sx, sy, sz = np.moveaxis(np.sin(angles), -1, 0)
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    shape = (*angles.shape[:-1], 3, 3)
    rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(shape)
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(shape)
    rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(shape)
    return rz @ ry @ rx


def rpy_to_matrix_np(rpy: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed XYZ axes) to a 3x3 rotation: R = Rz(y) Ry(p) Rx(r)."""
    return euler_xyz_to_matrix_np(rpy)


def axis_angle_to_matrix_np(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: unit ``axis`` (3,) and angles ``[B]`` to rotations ``[B, 3, 3]``."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=np.float64)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def matrix_to_quat_xyzw_np(rot: np.ndarray) -> np.ndarray:
    """Batched rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (x, y, z, w), w >= 0."""
    m = np.asarray(rot, np.float64)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    # Shepperd: build all four candidates and take the best-conditioned one per matrix.
    tr = np.trace(m, axis1=1, axis2=2)
    a = lambda i, j: m[:, i, j]  # noqa: E731
    cand = np.stack(
        [
            np.stack([1 + 2 * a(0, 0) - tr, a(0, 1) + a(1, 0), a(0, 2) + a(2, 0), a(2, 1) - a(1, 2)], -1),
            np.stack([a(0, 1) + a(1, 0), 1 + 2 * a(1, 1) - tr, a(1, 2) + a(2, 1), a(0, 2) - a(2, 0)], -1),
            np.stack([a(0, 2) + a(2, 0), a(1, 2) + a(2, 1), 1 + 2 * a(2, 2) - tr, a(1, 0) - a(0, 1)], -1),
            np.stack([a(2, 1) - a(1, 2), a(0, 2) - a(2, 0), a(1, 0) - a(0, 1), 1 + tr], -1),
        ],
        1,
    )  # [N, 4 candidates, 4]
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], -1)
    best = np.argmax(diag, axis=1)
    q = cand[np.arange(len(m)), best]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q.reshape(*shape, 4)


def quat_xyzw_to_matrix_np(q: np.ndarray) -> np.ndarray:
    """Batched quaternions ``[..., 4]`` (x, y, z, w; any norm) to rotation matrices ``[..., 3, 3]``."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def rigid_fit_np(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares rigid transform T with dst ~ T src (Kabsch/Umeyama, no scale).

    Returns the 4x4 transform and the RMS residual in the points' unit.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s)
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = mu_d - rot @ mu_s
    resid = dst - (src @ rot.T + pose[:3, 3])
    return pose, float(np.sqrt((resid**2).sum(1).mean()))


def perturb_poses_np(poses: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float) -> np.ndarray:
    """Poses ``[N, 4, 4]`` moved by Gaussian noise: the rotation turned by XYZ Euler angles of
    std ``rot_deg`` per axis (in the camera frame, about the base origin), the translation
    shifted by std ``trans_m`` per axis. Stands in for a rough prior or an inter-frame motion."""
    out = np.array(poses, np.float64)
    angles = rng.normal(0, np.radians(rot_deg), (len(out), 3))
    out[:, :3, :3] = euler_xyz_to_matrix_np(angles) @ out[:, :3, :3]
    out[:, :3, 3] += rng.normal(0, trans_m, (len(out), 3))
    return out
