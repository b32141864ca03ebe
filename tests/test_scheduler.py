import math
from dataclasses import replace

import pytest
import torch

from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix, rotation_angle
from monose3.method.config import DiffusionConfig
from monose3.method.pose_space import MIN_DEPTH, base_frame, centroid_frame, denormalize_pose, normalize_pose
from monose3.method.scheduler import DDIMScheduler, FixPer, make_noiser


def random_poses(n: int, gen: torch.Generator) -> torch.Tensor:
    rot = euler_xyz_to_matrix((torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 2 * math.pi)
    trans = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.4
    trans[:, 2] = 0.5 + 3 * torch.rand(n, generator=gen, dtype=torch.float64)
    return make_pose(rot, trans)


def random_intrinsics(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    size = torch.stack([400 + 600 * torch.rand(n, generator=gen), 300 + 400 * torch.rand(n, generator=gen)], 1)
    K = torch.zeros(n, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = 300 + 700 * torch.rand(n, generator=gen)
    K[:, 1, 1] = K[:, 0, 0] * (1 + 0.05 * torch.randn(n, generator=gen))
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = size[:, 0] / 2, size[:, 1] / 2, 1
    return K, size.double()


def test_normalize_then_denormalize_is_identity():
    gen = torch.Generator().manual_seed(0)
    pose = random_poses(500, gen)
    K, size = random_intrinsics(500, gen)
    back = denormalize_pose(normalize_pose(pose, K, size, 1.5), K, size, 1.5)
    assert torch.allclose(back, pose, atol=1e-5)


def test_normalized_translation_is_the_image_position():
    # Eq. 4: f tx / (w tz) is the offset from the principal point as a fraction of the width.
    K = torch.tensor([[[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]], dtype=torch.float64)
    size = torch.tensor([[640.0, 480.0]], dtype=torch.float64)
    pose = make_pose(torch.eye(3, dtype=torch.float64)[None], torch.tensor([[0.64, -0.24, 2.0]], dtype=torch.float64))
    x = normalize_pose(pose, K, size, 1.5)
    assert x[0, 6:].tolist() == pytest.approx([0.25, -0.125, 0.5])


def test_centroid_frame_round_trip_keeps_rotation_and_moves_origin():
    gen = torch.Generator().manual_seed(1)
    pose = random_poses(10, gen)
    c = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    ref = centroid_frame(pose, c)
    assert torch.allclose(ref[:, :3, :3], pose[:, :3, :3])
    expected = (pose[:, :3, :3] @ c[..., None])[..., 0] + pose[:, :3, 3]
    assert torch.allclose(ref[:, :3, 3], expected)
    assert torch.allclose(base_frame(ref, c), pose)


def test_ddim_step_with_true_x0_and_noise_lands_on_posterior_mean():
    schedule = DDIMScheduler(DiffusionConfig())
    gen = torch.Generator().manual_seed(2)
    x0 = torch.randn(64, 9, generator=gen, dtype=torch.float64)
    eps = torch.randn(64, 9, generator=gen, dtype=torch.float64)
    for t_val in (2, 10, 50, 100):
        t = torch.full((64,), t_val)
        x_t = schedule.add_noise_normalized(x0, t, eps)
        # eta = 1 gives DDPM's posterior mean of q(x_{t-1} | x_t, x0) (DDIM, Sec. 4.1).
        out = schedule.step_normalized(x0, t, t - 1, x_t, eta=1.0)
        a_t, a_prev = schedule.alpha_bar[t_val], schedule.alpha_bar[t_val - 1]
        beta = schedule.betas[t_val]
        scale = torch.tensor([1.0] * 6 + [DiffusionConfig().gamma] * 3, dtype=torch.float64)
        mean = (a_prev.sqrt() * beta / (1 - a_t)) * x0 * scale + ((1 - beta).sqrt() * (1 - a_prev) / (1 - a_t)) * (
            x_t * scale
        )
        assert torch.allclose(out, mean / scale, atol=1e-6)
        # eta = 0 is deterministic DDIM: the forward sample at t-1 with the same noise.
        det = schedule.step_normalized(x0, t, t - 1, x_t, eta=0.0)
        assert torch.allclose(det, schedule.add_noise_normalized(x0, t - 1, eps), atol=1e-6)


def test_ddim_to_step_zero_returns_x0():
    schedule = DDIMScheduler(DiffusionConfig())
    x0, x_t = torch.randn(4, 9), torch.randn(4, 9)
    out = schedule.step_normalized(x0, torch.full((4,), 20), torch.zeros(4, dtype=torch.long), x_t)
    assert torch.allclose(out, x0, atol=1e-5)


def test_schedule_is_linear_with_T_steps():
    schedule = DDIMScheduler(DiffusionConfig())
    assert len(schedule.betas) == 101 and schedule.alpha_bar[0] == 1
    assert torch.allclose(schedule.betas[1:].diff(), schedule.betas[2:3] - schedule.betas[1:2])
    assert schedule.timesteps(5) == [100, 80, 60, 40, 20]
    assert schedule.timesteps(1, 10) == [10] and schedule.timesteps(3, 30) == [30, 20, 10]


def test_visdiff_noise_grows_with_t_and_keeps_rotation_about_centroid():
    gen = torch.Generator().manual_seed(3)
    cfg = DiffusionConfig()
    noiser = DDIMScheduler(cfg)
    pose = random_poses(1, gen).repeat(400, 1, 1)
    K, size = random_intrinsics(1, gen)
    K, size = K.repeat(400, 1, 1), size.repeat(400, 1)
    spreads = []
    for t_val in (5, 50, 100):
        noisy = noiser.add_noise(pose, torch.full((400,), t_val), K, size, gen)
        spreads.append(rotation_angle(noisy[:, :3, :3], pose[:, :3, :3]).mean().item())
        assert torch.allclose(torch.det(noisy[:, :3, :3]), torch.ones(400, dtype=torch.float64), atol=1e-6)
    assert spreads[0] < spreads[1] < spreads[2]


def test_fixper_matches_robopose_statistics():
    gen = torch.Generator().manual_seed(4)
    noiser = FixPer(DiffusionConfig())
    pose = random_poses(1, gen).repeat(4000, 1, 1)
    noisy = noiser.add_noise(pose, torch.ones(4000, dtype=torch.long), None, None, gen)
    dt = noisy[:, :3, 3] - pose[:, :3, 3]
    assert dt.std(0).tolist() == pytest.approx([0.1, 0.1, 0.1], rel=0.08)


def test_step_on_poses_is_normalise_ddim_denormalise():
    """The scheduler's pose-space step (Eq. 8) equals the normalised step between Eq. 4 and Eq. 6-7,
    noise drawn from the generator included; t_prev = 0 returns the predicted H_0."""
    gen = torch.Generator().manual_seed(5)
    cfg = DiffusionConfig()
    scheduler = DDIMScheduler(cfg)
    pose_t, pose_0 = random_poses(16, gen), random_poses(16, gen)
    K, size = random_intrinsics(16, gen)
    out = scheduler.step(pose_0, 40, 20, pose_t, K, size, eta=1.0, generator=torch.Generator().manual_seed(9))
    x_t, x_0 = normalize_pose(pose_t, K, size, cfg.c_z), normalize_pose(pose_0, K, size, cfg.c_z)
    noise = torch.randn(x_t.shape, generator=torch.Generator().manual_seed(9), dtype=x_t.dtype)
    x_prev = scheduler.step_normalized(x_0, torch.full((16,), 40), torch.full((16,), 20), x_t, 1.0, noise)
    assert torch.allclose(out, denormalize_pose(x_prev, K, size, cfg.c_z), atol=1e-9)
    assert torch.allclose(scheduler.step(pose_0, 40, 0, pose_t, K, size), pose_0, atol=1e-5)


def test_one_depth_floor_for_forward_process_and_reverse_step():
    """A pose pushed behind the camera comes out at MIN_DEPTH from add_noise, FixPer and step alike."""
    gen = torch.Generator().manual_seed(6)
    cfg = DiffusionConfig()
    scheduler = DDIMScheduler(cfg)
    K, size = random_intrinsics(8, gen)
    behind = random_poses(8, gen)
    behind[:, 2, 3] = -1.0
    near = random_poses(8, gen)
    near[:, 2, 3] = 0.3
    # Stepping to t_prev = 0 returns the prediction, so a prediction behind the camera is floored.
    floor = torch.full((8,), MIN_DEPTH, dtype=torch.float64)
    assert torch.allclose(scheduler.step(behind, 30, 0, near, K, size)[:, 2, 3], floor, atol=1e-6)
    fixper = FixPer(replace(cfg, fixper_trans_std=0.0))
    assert torch.allclose(fixper.add_noise(behind, None, K, size, gen)[:, 2, 3], floor)
    at_floor = near.repeat(50, 1, 1)
    at_floor[:, 2, 3] = MIN_DEPTH  # a small t keeps samples near H_0: about half fall below the floor
    noisy = scheduler.add_noise(at_floor, torch.full((400,), 5), K.repeat(50, 1, 1), size.repeat(50, 1), gen)
    assert noisy[:, 2, 3].min() >= MIN_DEPTH - 1e-12 and (noisy[:, 2, 3] < MIN_DEPTH + 1e-9).sum() > 100
    assert isinstance(make_noiser(cfg), DDIMScheduler) and isinstance(make_noiser(replace(cfg, noise="fixper")), FixPer)
