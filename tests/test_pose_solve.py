import torch

from monose3.geometry.camera import project
from monose3.geometry.pose_solve import reprojection_jacobian, solve_pose
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import euler_xyz_to_matrix, rotvec_to_matrix


def _nudged(pose: torch.Tensor, angles=(0.03, -0.04, 0.05), shift=(0.01, -0.02, 0.04)) -> torch.Tensor:
    """``pose`` rotated about its origin and shifted."""
    rot = euler_xyz_to_matrix(torch.tensor([angles], dtype=pose.dtype)) @ pose[:, :3, :3]
    return make_pose(rot, pose[:, :3, 3] + torch.tensor([shift], dtype=pose.dtype))


def test_reprojection_jacobian_matches_finite_differences_of_the_left_update():
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64) * 0.3
    pose = make_pose(euler_xyz_to_matrix(torch.tensor([[0.3, -0.2, 0.5], [1.0, 0.4, -0.3]], dtype=torch.float64)),
                     torch.tensor([[0.1, -0.05, 1.5], [-0.2, 0.1, 1.2]], dtype=torch.float64))  # fmt: skip
    K = torch.tensor([[[300.0, 0, 160], [0, 310, 120], [0, 0, 1]]], dtype=torch.float64).expand(2, 3, 3)
    rotated = points @ pose[:, :3, :3].transpose(1, 2)
    jac = reprojection_jacobian(rotated + pose[:, None, :3, 3], rotated, K)
    assert jac.shape == (2, 5, 2, 6)

    def pixels(update: torch.Tensor) -> torch.Tensor:  # R <- exp(omega) R, t <- t + delta
        rot = rotvec_to_matrix(update[:3].expand(2, 3)) @ pose[:, :3, :3]
        return project(transform_points(make_pose(rot, pose[:, :3, 3] + update[3:]), points), K)

    for axis in range(6):
        step = torch.zeros(6, dtype=torch.float64)
        step[axis] = 1e-6
        numeric = (pixels(step) - pixels(-step)) / 2e-6
        assert torch.allclose(jac[..., axis], numeric, atol=1e-4)


def test_solve_pose_recovers_a_pose_from_exact_pixels_and_stays_put_without_weights():
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(2, 300, 3, generator=gen, dtype=torch.float64) * 0.3
    pose_t = make_pose(
        euler_xyz_to_matrix(torch.randn(2, 3, generator=gen, dtype=torch.float64)),
        torch.tensor([[0.1, -0.05, 1.5], [-0.2, 0.1, 1.2]], dtype=torch.float64),
    )
    pose_0 = _nudged(pose_t)
    K = torch.tensor([[[150.0, 0, 64], [0, 150, 48], [0, 0, 1]]], dtype=torch.float64).expand(2, 3, 3)
    target = project(transform_points(pose_0, points), K)
    solved = solve_pose(pose_t, K, points, target, torch.ones(2, 300, dtype=torch.float64), iterations=8)
    assert torch.allclose(solved, pose_0, atol=1e-6)
    still = solve_pose(pose_t, K, points, target, torch.zeros(2, 300, dtype=torch.float64))
    assert torch.allclose(still, pose_t)
    ones = torch.ones(2, 300, dtype=torch.float64)
    free = solve_pose(pose_t, K, points, target, ones, torch.zeros(2, 6, dtype=torch.float64), iterations=8)
    assert torch.allclose(free, pose_0, atol=1e-6)  # a zero-precision prior changes nothing
    held = solve_pose(pose_t, K, points, target, ones, torch.full((2, 6), 1e12, dtype=torch.float64))
    assert torch.allclose(held, pose_t, atol=1e-5)  # an overwhelming prior keeps H_t
    halfway = solve_pose(pose_t, K, points, target, ones, torch.full((2, 6), 1e7, dtype=torch.float64), iterations=8)
    moved = lambda p: (p[:, :3, 3] - pose_t[:, :3, 3]).norm(dim=1)  # noqa: E731
    assert ((moved(halfway) > 0.05 * moved(pose_0)) & (moved(halfway) < 0.95 * moved(pose_0))).all()
