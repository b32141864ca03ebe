"""Rotations, one implementation per conversion (roma-style names ``<from>_to_<to>``).

Every function is batched over leading dimensions: rotation matrices are ``[..., 3, 3]``,
6D rotations ``[..., 6]`` (first column | second column, the layout of Eq. 4), Euler angles
and rotation vectors ``[..., 3]`` in radians, quaternions ``[..., 4]`` in (x, y, z, w) order.
The element-wise ones take numpy arrays or torch tensors and return the same kind, so the
robot model and the dataset readers use them without importing torch; the ones built on an
SVD or Shepperd's method are numpy only.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from monose3.geometry.arrays import array_module


def _normalize(v, xp: ModuleType, eps: float = 1e-8):
    norm = xp.linalg.norm(v, axis=-1)[..., None]
    return v / xp.clip(norm, eps, None)


def rotation_6d_to_matrix(r6):
    """6D rotation ``[..., 6]`` (r1 | r2) to a rotation matrix by Gram-Schmidt (Eq. 6).

    u1 = r1/|r1|, u2 = normalise(r2 - (r2.u1) u1), u3 = u1 x u2; the columns are (u1, u2, u3),
    so the result is a proper rotation for any input whose two columns are not parallel.
    """
    xp = array_module(r6)
    r1, r2 = r6[..., :3], r6[..., 3:6]
    u1 = _normalize(r1, xp)
    u2 = _normalize(r2 - (r2 * u1).sum(-1)[..., None] * u1, xp)
    u3 = xp.linalg.cross(u1, u2)
    return xp.stack([u1, u2, u3], -1)


def matrix_to_rotation_6d(rot):
    """First two columns of ``rot`` ``[..., 3, 3]`` as ``[..., 6]`` (r1 | r2), the Eq. 4 layout."""
    xp = array_module(rot)
    return xp.concatenate([rot[..., :, 0], rot[..., :, 1]], -1)


def euler_xyz_to_matrix(angles):
    """Extrinsic XYZ Euler angles ``[..., 3]`` to R = Rz @ Ry @ Rx.

    This is also URDF's roll-pitch-yaw convention (fixed axes X, then Y, then Z).
    """
    xp = array_module(angles)
    if xp is np:
        angles = np.asarray(angles, np.float64)
    c, s = xp.cos(angles), xp.sin(angles)
    cx, cy, cz = c[..., 0], c[..., 1], c[..., 2]
    sx, sy, sz = s[..., 0], s[..., 1], s[..., 2]
    one, zero = xp.ones_like(cx), xp.zeros_like(cx)
    shape = (*angles.shape[:-1], 3, 3)
    rx = xp.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(shape)
    ry = xp.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(shape)
    rz = xp.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(shape)
    return rz @ ry @ rx


def skew(v):
    """Cross-product matrices ``[..., 3, 3]`` of vectors ``[..., 3]``: skew(v) @ u = v x u."""
    xp = array_module(v)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = xp.zeros_like(x)
    return xp.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*v.shape[:-1], 3, 3)


def _rodrigues(k, a, b):
    """R = I + a K + b K^2 (Rodrigues' formula) for cross-product matrices ``k`` ``[..., 3, 3]``."""
    xp = array_module(k)
    eye = xp.eye(3, dtype=k.dtype) if xp is np else xp.eye(3, dtype=k.dtype, device=k.device)
    return eye + a * k + b * (k @ k)


def axis_angle_to_matrix(axis, angle):
    """Unit axes ``[..., 3]`` and angles ``[...]`` (radians) to rotations (Rodrigues, a = sin,
    b = 1 - cos); an axis ``[3]`` with angles ``[B]`` gives ``[B, 3, 3]`` (a URDF joint)."""
    xp = array_module(axis)
    if xp is np:
        axis, angle = np.asarray(axis, np.float64), np.asarray(angle, np.float64)
    s, c = xp.sin(angle)[..., None, None], xp.cos(angle)[..., None, None]
    return _rodrigues(skew(axis), s, 1.0 - c)


def rotvec_to_matrix(rotvec):
    """Rotation vectors ``[..., 3]`` (axis times angle) to matrices (Rodrigues with K = skew(rotvec),
    a = sin(t)/t, b = (1 - cos(t))/t^2), exact and differentiable at and near zero (series below 1e-4 rad)."""
    xp = array_module(rotvec)
    if xp is np:
        rotvec = np.asarray(rotvec, np.float64)
    theta2 = (rotvec * rotvec).sum(-1)[..., None, None]
    theta = xp.sqrt(xp.clip(theta2, 1e-24, None))
    small = theta < 1e-4
    a = xp.where(small, 1.0 - theta2 / 6.0, xp.sin(theta) / theta)
    b = xp.where(small, 0.5 - theta2 / 24.0, (1.0 - xp.cos(theta)) / xp.clip(theta2, 1e-24, None))
    return _rodrigues(skew(rotvec), a, b)


def rotation_angle(rot_a, rot_b):
    """Geodesic angle (radians, in [0, pi]) between rotations, broadcast over leading axes.

    atan2(|vee(R - R^T)|, trace(R) - 1) of R = A^T B (= atan2(2 sin, 2 cos)): accurate near
    0 and near pi, where ``arccos((trace - 1) / 2)`` loses half the digits.
    """
    xp = array_module(rot_a)
    rel = xp.swapaxes(rot_a, -1, -2) @ rot_b
    vee = xp.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1
    )
    trace = rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2]
    return xp.arctan2(xp.linalg.norm(vee, axis=-1), trace - 1.0)


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (x, y, z, w), w >= 0."""
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
    q = cand[np.arange(len(m)), np.argmax(diag, axis=1)]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q.reshape(*shape, 4)


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[..., 4]`` (x, y, z, w; any norm) to rotation matrices ``[..., 3, 3]``."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def matrix_to_rotvec(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to rotation vectors ``[..., 3]`` (angle in [0, pi]),
    through the quaternion, which stays accurate near 0 and near pi."""
    q = matrix_to_quat_xyzw(rot)  # w >= 0
    v, w = q[..., :3], q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    scale = np.where(s < 1e-12, 2.0, angle / np.where(s < 1e-12, 1.0, s))
    return v * scale[..., None]


def procrustes(m: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to each ``[..., 3, 3]`` matrix: U diag(1, 1, det) V^T.

    Applied to a cross-covariance it is the Kabsch fit (:func:`monose3.geometry.poses.rigid_fit`);
    applied to a mean of rotations it is the chordal projection onto SO(3).
    """
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt
