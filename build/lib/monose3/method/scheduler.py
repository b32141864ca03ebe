"""The visibility-constrained SE(3) diffusion process (Sec. III-B) and its DDIM reverse step
(Sec. III-C) as one scheduler object, separate from the network, as diffusers separates its
``DDIMScheduler`` from the model. The sampling loop is (Alg. 2)::

    steps = scheduler.timesteps(K, start)
    for t, t_prev in zip(steps, [*steps[1:], 0]):
        pose = scheduler.step(model(pose, t), t, t_prev, pose, K, size)

All methods are batched over the leading dimension and work on the pose of the robot's
*centroid frame* (origin at the centre of the posed robot's bounding box, base-frame
orientation), so rotating a pose does not move the robot in the image (Sec. III-B). The
scheduler's configuration is :class:`DiffusionConfig`, saved with every model.
"""

from __future__ import annotations

import math
from typing import Protocol

import torch

from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix
from monose3.method.config import DiffusionConfig
from monose3.method.pose_space import MIN_DEPTH, denormalize_pose, floor_depth, normalize_pose


class DDIMScheduler:
    """The linear beta schedule of Sec. IV-A (t = 0..T, alpha_bar[0] = 1), VisDiff's forward
    process (Eq. 4-7) and the DDIM reverse step (Eq. 8), with one depth floor (MIN_DEPTH)."""

    def __init__(self, config: DiffusionConfig):
        self.config = config
        self.num_steps = config.num_steps
        self.c_z = config.c_z
        betas = torch.linspace(config.beta_start, config.beta_end, config.num_steps, dtype=torch.float64)
        self.betas = torch.cat([torch.zeros(1, dtype=torch.float64), betas])
        self.alpha_bar = torch.cumprod(1.0 - self.betas, dim=0)

    # ---- the schedule -----------------------------------------------------------------------

    def alpha_bar_at(self, t: torch.Tensor) -> torch.Tensor:
        """alpha_bar_t of Eq. 5 for integer timesteps ``t`` ``[B]``, float32 on ``t``'s device."""
        return self.alpha_bar.to(t.device)[t.long()].float()

    def timesteps(self, num: int, start: int | None = None) -> list[int]:
        """The reverse process's ``num`` evenly spaced timesteps from ``start`` (default T) down to > 0 (Alg. 2)."""
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

    def diffusion_scale(self, like: torch.Tensor) -> torch.Tensor:
        """Per-coordinate scale into the diffusion space ``[9]``: 1 for the 6D rotation, gamma for translation."""
        scale = torch.ones(9, dtype=like.dtype, device=like.device)
        scale[6:] = self.config.gamma
        return scale

    # ---- in the normalised space (Eq. 4) ----------------------------------------------------

    def add_noise_normalized(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Forward process in the normalised space, Eq. 5: x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps.

        ``x0`` ``[B, 9]`` and the result are normalised poses (Eq. 4); the diffusion itself runs
        on x0 * scale (see ``DiffusionConfig.gamma``) and is mapped back. No depth floor.
        """
        scale = self.diffusion_scale(x0)
        a = self.alpha_bar_at(t).to(x0.dtype)[:, None]
        return (a.sqrt() * x0 * scale + (1 - a).sqrt() * noise) / scale

    def step_normalized(
        self,
        x0_pred: torch.Tensor,
        t: torch.Tensor,
        t_prev: torch.Tensor,
        x_t: torch.Tensor,
        eta: float = 1.0,
        noise: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One DDIM reverse step in the normalised space, Eq. 8 (Eq. 3 with eps from x0), no depth floor.

        eps = (x_t - sqrt(a_t) x0) / sqrt(1 - a_t); x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev - s^2) eps
        (+ s z when ``noise`` z is given; the paper omits it). t_prev = 0 returns x0.
        """
        scale = self.diffusion_scale(x_t)
        xt_s, x0_s = x_t * scale, x0_pred * scale
        a_t = self.alpha_bar_at(t).to(x_t.dtype)[:, None]
        a_prev = self.alpha_bar_at(t_prev).to(x_t.dtype)[:, None]
        sigma = self.sigma(t, t_prev, eta).to(x_t.dtype)[:, None]
        eps = (xt_s - a_t.sqrt() * x0_s) / (1 - a_t).clamp_min(1e-12).sqrt()
        x_prev = a_prev.sqrt() * x0_s + (1 - a_prev - sigma**2).clamp_min(0).sqrt() * eps
        if noise is not None:
            x_prev = x_prev + sigma * noise
        return x_prev / scale

    # ---- on poses ---------------------------------------------------------------------------

    def add_noise(
        self,
        pose_ref: torch.Tensor,
        t: torch.Tensor,
        K: torch.Tensor,
        image_size: torch.Tensor,
        generator: torch.Generator,
    ) -> torch.Tensor:
        """VisDiff's q(H_t | H_0) (Sec. III-B) on camera-from-centroid poses ``[B, 4, 4]``: normalise
        (Eq. 4), diffuse (Eq. 5), floor the depth at MIN_DEPTH, denormalise (Eq. 6-7)."""
        x0 = normalize_pose(pose_ref, K, image_size, self.c_z)
        eps = torch.randn(x0.shape, generator=generator, dtype=x0.dtype)
        x_t = floor_depth(self.add_noise_normalized(x0, t, eps), self.c_z)  # rare at gamma = 3
        return denormalize_pose(x_t, K, image_size, self.c_z)

    def step(
        self,
        pose_0: torch.Tensor,
        t: int,
        t_prev: int,
        pose_t: torch.Tensor,
        K: torch.Tensor,
        image_size: torch.Tensor,
        eta: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """One reverse step on poses, Eq. 8: the network's H_0 ``pose_0`` and the current H_t
        ``pose_t`` (camera-from-centroid ``[B, 4, 4]``) are normalised (Eq. 4), stepped from t to
        t_prev by DDIM, floored at MIN_DEPTH and denormalised (Eq. 6-7) into H_{t_prev}.

        With a ``generator`` DDIM's noise term sigma z is added (one draw of ``[B, 9]``).
        """
        x_t = normalize_pose(pose_t, K, image_size, self.c_z)
        x_0 = normalize_pose(pose_0, K, image_size, self.c_z)
        n = len(pose_t)
        noise = torch.randn(x_t.shape, generator=generator, dtype=x_t.dtype) if generator is not None else None
        x_prev = self.step_normalized(x_0, torch.full((n,), t), torch.full((n,), t_prev), x_t, eta, noise)
        return denormalize_pose(floor_depth(x_prev, self.c_z), K, image_size, self.c_z)


class PoseNoiser(Protocol):
    """Makes the noisy training pose H_t from H_0; DDIMScheduler (VisDiff) and FixPer share it."""

    def add_noise(
        self,
        pose_ref: torch.Tensor,
        t: torch.Tensor,
        K: torch.Tensor,
        image_size: torch.Tensor,
        generator: torch.Generator,
    ) -> torch.Tensor: ...


class FixPer:
    """RoboPose's fixed-scale perturbation (the paper's FixPer baseline, Sec. IV), independent of
    t: Euler XYZ angles ~ N(0, 60 deg) each and translation ~ N(0, 0.1 m) per axis, applied about
    the reference point; depth floored at MIN_DEPTH like the diffusion."""

    def __init__(self, config: DiffusionConfig):
        self.rot_std = math.radians(config.fixper_rot_std_deg)
        self.trans_std = config.fixper_trans_std

    def add_noise(self, pose_ref, t, K, image_size, generator):
        """The perturbed camera-from-centroid poses ``[B, 4, 4]`` (``t``, ``K``, ``image_size`` unused)."""
        n = pose_ref.shape[0]
        angles = torch.randn((n, 3), generator=generator, dtype=pose_ref.dtype) * self.rot_std
        dt = torch.randn((n, 3), generator=generator, dtype=pose_ref.dtype) * self.trans_std
        rot = euler_xyz_to_matrix(angles) @ pose_ref[:, :3, :3]
        trans = pose_ref[:, :3, 3] + dt
        trans[:, 2] = trans[:, 2].clamp_min(MIN_DEPTH)
        return make_pose(rot, trans)


def make_noiser(config: DiffusionConfig) -> PoseNoiser:
    """The training forward process that ``config.noise`` names: VisDiff (the scheduler) or FixPer."""
    if config.noise == "visdiff":
        return DDIMScheduler(config)
    if config.noise == "fixper":
        return FixPer(config)
    raise ValueError(f"unknown noise process {config.noise!r} (visdiff or fixper)")
