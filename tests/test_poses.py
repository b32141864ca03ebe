"""geometry.poses: assembly, inversion, point transforms and the rigid fit, numpy and torch alike."""

import numpy as np
import pytest
import torch

from monose3.geometry.poses import invert_pose, make_pose, perturb_poses, rigid_fit, transform_points
from monose3.geometry.rotations import rotation_angle, rotvec_to_matrix


def random_poses(rng, n):
    return make_pose(rotvec_to_matrix(rng.normal(size=(n, 3))), rng.normal(size=(n, 3)))


def test_make_pose_numpy_and_torch_agree():
    rng = np.random.default_rng(0)
    rot, trans = rotvec_to_matrix(rng.normal(size=(5, 3))), rng.normal(size=(5, 3))
    pose = make_pose(rot, trans)
    assert pose.shape == (5, 4, 4) and np.array_equal(pose[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)))
    as_torch = make_pose(torch.as_tensor(rot), torch.as_tensor(trans))
    assert isinstance(as_torch, torch.Tensor) and torch.equal(as_torch, torch.as_tensor(pose))


def test_invert_and_transform_round_trip():
    rng = np.random.default_rng(1)
    poses, points = random_poses(rng, 4), rng.normal(size=(4, 10, 3))
    np.testing.assert_allclose(invert_pose(poses) @ poses, np.broadcast_to(np.eye(4), (4, 4, 4)), atol=1e-12)
    back = transform_points(invert_pose(poses), transform_points(poses, points))
    np.testing.assert_allclose(back, points, atol=1e-12)
    # the same on torch tensors
    torch.testing.assert_close(invert_pose(torch.as_tensor(poses)), torch.as_tensor(invert_pose(poses)))


def test_rigid_fit_recovers_the_transform_and_reports_the_residual():
    rng = np.random.default_rng(2)
    true = random_poses(rng, 1)[0]
    src = rng.normal(size=(20, 3))
    fit, rms = rigid_fit(src, transform_points(true, src))
    np.testing.assert_allclose(fit, true, atol=1e-10)
    assert rms < 1e-10
    noisy = transform_points(true, src) + rng.normal(0, 0.01, (20, 3))
    _, rms = rigid_fit(src, noisy)
    assert 0.005 < rms < 0.02


def test_rigid_fit_returns_a_rotation_for_mirrored_points():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(10, 3))
    fit, _ = rigid_fit(src, src * [1, 1, -1])  # a reflection has no rigid fit; the best rotation still is one
    assert np.linalg.det(fit[:3, :3]) == pytest.approx(1.0)


def test_perturb_poses_moves_by_the_asked_amounts():
    rng = np.random.default_rng(4)
    poses = np.repeat(np.eye(4)[None], 2000, 0)
    moved = perturb_poses(poses, rng, trans_m=0.02, rot_deg=3.0)
    assert np.std(moved[:, :3, 3]) == pytest.approx(0.02, rel=0.05)
    # three independent 3 deg axes: a mean angle of about sqrt(8 / pi) * 3 deg
    mean_deg = np.degrees(rotation_angle(np.eye(3), moved[:, :3, :3])).mean()
    assert mean_deg == pytest.approx(np.sqrt(8 / np.pi) * 3.0, rel=0.05)


def test_perturb_poses_turns_about_the_pivot():
    poses = np.repeat(make_pose(np.eye(3), np.array([0.1, -0.2, 1.5]))[None], 50, 0)
    pivot = np.array([0.0, 0.0, 0.4])
    moved = perturb_poses(poses, np.random.default_rng(0), trans_m=0.0, rot_deg=10.0, pivot=pivot)
    np.testing.assert_allclose(transform_points(moved, pivot[None]), transform_points(poses, pivot[None]), atol=1e-12)
    assert np.abs(moved[:, :3, 3] - poses[:, :3, 3]).max() > 0.02  # the base origin swings round it
