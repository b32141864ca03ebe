"""geometry.rotations, checked against pybullet's rotation conventions and by round trips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from monose3.geometry.poses import make_pose, perturb_poses, rigid_fit, transform_points
from monose3.geometry.rotations import (
    euler_xyz_to_matrix,
    matrix_to_quat_xyzw,
    matrix_to_rotation_6d,
    quat_xyzw_to_matrix,
    rotation_6d_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
)

try:  # pybullet's conventions are the reference where it is installed (its wheels stop at Python 3.11)
    import pybullet as pb
except ImportError:
    pb = None
needs_pybullet = pytest.mark.skipif(pb is None, reason="pybullet is not installed (Python 3.11 only)")


def _pb_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    return np.array(pb.getMatrixFromQuaternion(list(quat_xyzw))).reshape(3, 3)


def _random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _random_rotations(rng: np.random.Generator, n: int) -> torch.Tensor:
    return torch.as_tensor(np.stack([quat_xyzw_to_matrix(q) for q in _random_quats(rng, n)]))


def _assert_proper(rot: torch.Tensor, atol: float = 1e-6) -> None:
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot.transpose(-1, -2) @ rot, eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(rot.shape[:-2], dtype=rot.dtype), atol=atol, rtol=0)


# ---- 6D rotations ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gram_schmidt_6d_gives_proper_rotations(dtype):
    gen = torch.Generator().manual_seed(30)
    r6 = torch.randn(4, 5, 6, generator=gen, dtype=dtype) * torch.rand(4, 5, 1, generator=gen, dtype=dtype) * 10
    rot = rotation_6d_to_matrix(r6)
    assert rot.shape == (4, 5, 3, 3) and rot.dtype == dtype
    _assert_proper(rot, atol=1e-5 if dtype == torch.float32 else 1e-12)
    # first column along r1; second column in the plane of r1, r2 on r2's side
    r1, r2 = r6[..., :3], r6[..., 3:]
    torch.testing.assert_close(rot[..., 0], r1 / r1.norm(dim=-1, keepdim=True))
    assert torch.all((rot[..., 1] * r2).sum(-1) > 0)
    assert (rot[..., 2] * r1).sum(-1).abs().max() < 1e-4
    assert (rot[..., 2] * r2).sum(-1).abs().max() < 1e-4


def test_gram_schmidt_6d_nearly_parallel_columns_still_proper():
    r1 = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    r6 = torch.cat([r1, r1 * 2 + torch.tensor([[1e-4, 0.0, 0.0]], dtype=torch.float64)], -1)
    _assert_proper(rotation_6d_to_matrix(r6), atol=1e-8)


def test_gram_schmidt_6d_has_gradients():
    r6 = torch.randn(3, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotation_6d_to_matrix, (r6,))


def test_rotation_to_6d_round_trip():
    rot = _random_rotations(np.random.default_rng(31), 64)
    r6 = matrix_to_rotation_6d(rot)
    assert r6.shape == (64, 6)
    torch.testing.assert_close(r6[:, :3], rot[:, :, 0])
    torch.testing.assert_close(r6[:, 3:], rot[:, :, 1])
    torch.testing.assert_close(rotation_6d_to_matrix(r6), rot, atol=1e-12, rtol=0)
    # and the other way: the 6D of an orthonormalised input reproduces that rotation
    x = torch.randn(10, 6, dtype=torch.float64)
    torch.testing.assert_close(
        rotation_6d_to_matrix(matrix_to_rotation_6d(rotation_6d_to_matrix(x))), rotation_6d_to_matrix(x)
    )


# ---- Euler, axis-angle, quaternions ---------------------------------------------------------


@needs_pybullet
def test_euler_xyz_matches_pybullet_rpy():
    rng = np.random.default_rng(32)
    angles = rng.uniform(-np.pi, np.pi, (50, 3))
    ours = euler_xyz_to_matrix(torch.as_tensor(angles)).numpy()
    for a, rot in zip(angles, ours, strict=True):
        np.testing.assert_allclose(rot, _pb_matrix(pb.getQuaternionFromEuler(a.tolist())), atol=1e-6)
    np.testing.assert_allclose(euler_xyz_to_matrix(angles), ours, atol=1e-12)
    np.testing.assert_allclose(euler_xyz_to_matrix(angles[0]), ours[0], atol=1e-12)
    # extrinsic XYZ: x first, then y, then z, about the fixed axes
    a = np.array([0.3, -0.7, 1.1])
    ax = [rotvec_to_matrix(e * t) for e, t in zip(np.eye(3), a, strict=True)]
    np.testing.assert_allclose(euler_xyz_to_matrix(a), ax[2] @ ax[1] @ ax[0], atol=1e-12)


def test_euler_batched_shape():
    angles = torch.zeros(2, 7, 3)
    rot = euler_xyz_to_matrix(angles)
    assert rot.shape == (2, 7, 3, 3)
    torch.testing.assert_close(rot, torch.eye(3).expand(2, 7, 3, 3))


@needs_pybullet
def test_axis_angle_matches_pybullet():
    rng = np.random.default_rng(33)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angles = rng.uniform(-4, 4, 3)
        rots = rotvec_to_matrix(axis * angles[:, None])
        for t, rot in zip(angles, rots, strict=True):
            np.testing.assert_allclose(rot, _pb_matrix(pb.getQuaternionFromAxisAngle(axis.tolist(), t)), atol=1e-6)


@needs_pybullet
def test_quaternion_matrix_matches_pybullet_and_round_trips():
    rng = np.random.default_rng(34)
    quats = _random_quats(rng, 200)
    # the branches of Shepperd's method: near-identity and ~180 degrees about each axis
    special = [[0, 0, 0, 1], [1, 0, 0, 1e-3], [0, 1, 0, 1e-3], [0, 0, 1, 1e-3], [1, 1, 0, 0], [0, 1, -1, 0]]
    quats = np.concatenate([quats, np.array(special, float)])
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    for q in quats:
        rot = quat_xyzw_to_matrix(q)
        np.testing.assert_allclose(rot, _pb_matrix(q), atol=1e-6)
        back = matrix_to_quat_xyzw(rot)
        assert back[3] >= 0 and np.linalg.norm(back) == pytest.approx(1.0)
        # q and -q are the same rotation; the canonical one has w >= 0
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9
        np.testing.assert_allclose(quat_xyzw_to_matrix(back), rot, atol=1e-12)


def test_quaternion_is_normalised():
    np.testing.assert_allclose(quat_xyzw_to_matrix(np.array([0, 0, 0, 5.0])), np.eye(3))


def test_rotation_angle():
    rng = np.random.default_rng(35)
    axis = rng.normal(size=(10, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angles = rng.uniform(0, np.pi, 10)
    base = _random_rotations(rng, 10)
    delta = rotvec_to_matrix(axis * angles[:, None])
    got = rotation_angle(base, base @ torch.as_tensor(delta))
    np.testing.assert_allclose(got.numpy(), angles, atol=1e-6)
    # numpy in, numpy out; accurate at 0 and near pi, where arccos(trace) loses digits
    np.testing.assert_allclose(rotation_angle(base.numpy(), base.numpy() @ delta), angles, atol=1e-12)
    near_pi = rotvec_to_matrix(axis * (np.pi - 1e-9))
    np.testing.assert_allclose(rotation_angle(np.eye(3), near_pi), np.pi - 1e-9, atol=1e-12)
    assert rotation_angle(np.eye(3), rotvec_to_matrix(np.array([1e-10, 0, 0]))) == pytest.approx(1e-10, rel=1e-6)


# ---- poses ----------------------------------------------------------------------------------


def test_make_pose_and_transform_points():
    rng = np.random.default_rng(36)
    rot = _random_rotations(rng, 3)
    trans = torch.as_tensor(rng.normal(size=(3, 3)))
    pose = make_pose(rot, trans)
    assert pose.shape == (3, 4, 4)
    torch.testing.assert_close(pose[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=pose.dtype).expand(3, 4))
    pts = torch.as_tensor(rng.normal(size=(3, 20, 3)))
    homog = torch.cat([pts, torch.ones(3, 20, 1, dtype=pts.dtype)], -1)
    expected = (homog @ pose.transpose(-1, -2))[..., :3]
    torch.testing.assert_close(transform_points(pose, pts), expected)
    # composition: applying a then b equals applying b @ a
    pose_b = make_pose(_random_rotations(rng, 3), torch.as_tensor(rng.normal(size=(3, 3))))
    torch.testing.assert_close(
        transform_points(pose_b, transform_points(pose, pts)), transform_points(pose_b @ pose, pts)
    )


def test_rigid_fit_recovers_known_transform():
    rng = np.random.default_rng(37)
    for _ in range(10):
        rot = quat_xyzw_to_matrix(_random_quats(rng, 1)[0])
        t = rng.normal(size=3)
        src = rng.normal(size=(7, 3))
        dst = src @ rot.T + t
        pose, resid = rigid_fit(src, dst)
        np.testing.assert_allclose(pose[:3, :3], rot, atol=1e-9)
        np.testing.assert_allclose(pose[:3, 3], t, atol=1e-9)
        np.testing.assert_allclose(pose[3], [0, 0, 0, 1])
        assert resid < 1e-9


def test_rigid_fit_noise_and_reflection():
    rng = np.random.default_rng(38)
    src = rng.normal(size=(500, 3))
    rot = quat_xyzw_to_matrix(_random_quats(rng, 1)[0])
    noise = rng.normal(scale=0.01, size=src.shape)
    pose, resid = rigid_fit(src, src @ rot.T + noise)
    # RMS residual reports the noise level (3D noise of 0.01 per axis: ~0.017)
    assert resid == pytest.approx(0.01 * np.sqrt(3), rel=0.1)
    np.testing.assert_allclose(pose[:3, :3], rot, atol=5e-3)
    # a mirrored point set must still give a proper rotation, not a reflection
    mirrored = src * np.array([1, 1, -1])
    pose, resid = rigid_fit(src, mirrored)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
    assert resid > 0.1


def test_perturb_poses_keeps_them_rigid_with_the_asked_spread():
    poses = np.repeat(np.eye(4)[None], 4000, 0)
    moved = perturb_poses(poses, np.random.default_rng(0), 0.02, 3.0)
    rot = moved[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9) and np.allclose(moved[:, 3], [0, 0, 0, 1])
    assert np.std(moved[:, :3, 3]) == pytest.approx(0.02, rel=0.05)
    # per-axis angle std of 3 deg: the total angle's RMS is sqrt(3) * 3 deg for small angles
    angles = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.sqrt(np.mean(angles**2)) == pytest.approx(np.sqrt(3) * 3.0, rel=0.05)
