"""The visibility-constrained SE(3) diffusion process (Sec. III-B) and its DDIM reverse
step (Sec. III-C), separate from the network, as diffusers separates schedulers from models.

All functions are batched over the leading dimension and work on the pose of the robot's
*centroid frame* (origin at the centre of the posed robot's bounding box, base-frame
orientation), so rotating a pose does not move the robot in the image (Sec. III-B).
"""

from __future__ import annotations

import math
from typing import Protocol

import torch

from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix
from monose3.method.config import DiffusionConfig
from monose3.method.pose_space import denormalize_pose, normalize_pose


class NoiseSchedule:
    """The linear beta schedule of Sec. IV-A, indexed t = 0..T with alpha_bar[0] = 1."""

    def __init__(self, config: DiffusionConfig):
        self.config = config
        self.num_steps = config.num_steps
        betas = torch.linspace(config.beta_start, config.beta_end, config.num_steps, dtype=torch.float64)
        self.betas = torch.cat([torch.zeros(1, dtype=torch.float64), betas])
        self.alpha_bar = torch.cumprod(1.0 - self.betas, dim=0)

    def alpha_bar_at(self, t: torch.Tensor) -> torch.Tensor:
        return self.alpha_bar.to(t.device)[t.long()].float()

    def ddim_timesteps(self, num: int, start: int | None = None) -> list[int]:
        """``num`` evenly spaced timesteps from ``start`` (default T) down to > 0."""
        start = self.num_steps if start is None else start
        return [max(1, round(start * (num - i) / num)) for i in range(num)]

    def sigma(self, t: torch.Tensor, t_prev: torch.Tensor, eta: float) -> torch.Tensor:
        """DDIM's sigma_t (Eq. 3): eta * sqrt((1 - a_prev)/(1 - a_t) * (1 - a_t/a_prev)).

        The paper prints the factor as (1 - a_prev/a_t), negative for any t; we use the
        DDIM paper's form, which is what the equation is meant to be.
        """
        a_t, a_prev = self.alpha_bar_at(t), self.alpha_bar_at(t_prev)
        var = (1 - a_prev) / (1 - a_t).clamp_min(1e-12) * (1 - a_t / a_prev)
        return eta * var.clamp_min(0).sqrt()


def _diffusion_scale(config: DiffusionConfig, like: torch.Tensor) -> torch.Tensor:
    """Per-coordinate scale into the diffusion space: 1 for the 6D rotation, gamma for translation."""
    scale = torch.ones(9, dtype=like.dtype, device=like.device)
    scale[6:] = config.gamma
    return scale


def diffuse_normalized(x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor, schedule: NoiseSchedule) -> torch.Tensor:
    """Forward process in the normalised space, Eq. 5: x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps.

    ``x0`` and the result are normalised poses (Eq. 4); the diffusion itself runs on
    x0 * scale (see ``DiffusionConfig.gamma``) and is mapped back.
    """
    scale = _diffusion_scale(schedule.config, x0)
    a = schedule.alpha_bar_at(t).to(x0.dtype)[:, None]
    return (a.sqrt() * x0 * scale + (1 - a).sqrt() * noise) / scale


def ddim_step(
    x_t: torch.Tensor,
    x0_pred: torch.Tensor,
    t: torch.Tensor,
    t_prev: torch.Tensor,
    schedule: NoiseSchedule,
    eta: float = 1.0,
    noise: torch.Tensor | None = None,
) -> torch.Tensor:
    """One DDIM reverse step in the normalised space, Eq. 8 (Eq. 3 with eps from x0).

    eps = (x_t - sqrt(a_t) x0) / sqrt(1 - a_t); x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev - s^2) eps
    (+ s z when ``noise`` z is given; the paper omits it). t_prev = 0 returns x0.
    """
    scale = _diffusion_scale(schedule.config, x_t)
    xt_s, x0_s = x_t * scale, x0_pred * scale
    a_t = schedule.alpha_bar_at(t).to(x_t.dtype)[:, None]
    a_prev = schedule.alpha_bar_at(t_prev).to(x_t.dtype)[:, None]
    sigma = schedule.sigma(t, t_prev, eta).to(x_t.dtype)[:, None]
    eps = (xt_s - a_t.sqrt() * x0_s) / (1 - a_t).clamp_min(1e-12).sqrt()
    x_prev = a_prev.sqrt() * x0_s + (1 - a_prev - sigma**2).clamp_min(0).sqrt() * eps
    if noise is not None:
        x_prev = x_prev + sigma * noise
    return x_prev / scale


class PoseNoiser(Protocol):
    """Makes the noisy training pose H_t from H_0; VisDiff and FixPer share this interface."""

    def __call__(
        self,
        pose_ref: torch.Tensor,
        t: torch.Tensor,
        K: torch.Tensor,
        image_size: torch.Tensor,
        generator: torch.Generator,
    ) -> torch.Tensor: ...


class VisDiffNoiser:
    """q(H_t | H_0) of Sec. III-B: normalise (Eq. 4), diffuse (Eq. 5), denormalise (Eq. 6-7)."""

    def __init__(self, config: DiffusionConfig):
        self.schedule = NoiseSchedule(config)
        self.c_z = config.c_z

    def __call__(self, pose_ref, t, K, image_size, generator):
        x0 = normalize_pose(pose_ref, K, image_size, self.c_z)
        eps = torch.randn(x0.shape, generator=generator, dtype=x0.dtype)
        x_t = diffuse_normalized(x0, t, eps, self.schedule)
        # A sample behind the camera cannot be rendered; keep depth positive (rare at gamma=3).
        x_t[:, 8] = x_t[:, 8].clamp_min(0.1 - self.c_z)
        return denormalize_pose(x_t, K, image_size, self.c_z)


class FixPerNoiser:
    """RoboPose's fixed-scale perturbation (the paper's FixPer baseline), independent of t:
    Euler XYZ angles ~ N(0, 60 deg) each and translation ~ N(0, 0.1 m) per axis, applied
    about the reference point."""

    def __init__(self, config: DiffusionConfig):
        self.rot_std = math.radians(config.fixper_rot_std_deg)
        self.trans_std = config.fixper_trans_std

    def __call__(self, pose_ref, t, K, image_size, generator):
        n = pose_ref.shape[0]
        angles = torch.randn((n, 3), generator=generator, dtype=pose_ref.dtype) * self.rot_std
        dt = torch.randn((n, 3), generator=generator, dtype=pose_ref.dtype) * self.trans_std
        rot = euler_xyz_to_matrix(angles) @ pose_ref[:, :3, :3]
        trans = pose_ref[:, :3, 3] + dt
        trans[:, 2] = trans[:, 2].clamp_min(0.1)
        return make_pose(rot, trans)


def make_noiser(config: DiffusionConfig) -> PoseNoiser:
    if config.noise == "visdiff":
        return VisDiffNoiser(config)
    if config.noise == "fixper":
        return FixPerNoiser(config)
    raise ValueError(f"unknown noise process {config.noise!r} (visdiff or fixper)")
