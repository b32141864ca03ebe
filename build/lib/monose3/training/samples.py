"""Training samples for Alg. 1, made a batch at a time on the training device: a step t, the
noisy pose H_t from the forward process, the crop of the image around the robot at H_t and the
render at H_t, pixel-aligned.

Frames come from DREAM folders (:class:`FrameDataset`, decoded in data-loader workers) or are
synthesised on the fly (:mod:`monose3.training.synthetic`). Every random draw is a function of
(seed, step) or (seed, sample number), so a resumed run sees the samples the uninterrupted
run would have seen.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from monose3.geometry.camera import standardize_image
from monose3.method.config import Config
from monose3.method.pose_space import base_frame, centroid_frame
from monose3.method.render_compare import crop_batch, crop_geometry
from monose3.method.scheduler import PoseNoiser
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer


def max_timestep(step: int, config: Config) -> int:
    """The largest t a training step draws: ``TrainConfig.t_max`` raised linearly to T over
    ``t_curriculum_steps`` (T throughout without a curriculum, as in the paper)."""
    T, tc = config.diffusion.num_steps, config.train
    start = T if tc.t_max is None else min(tc.t_max, T)
    if tc.t_curriculum_steps <= 0:
        return start
    return round(start + (T - start) * min(1.0, step / tc.t_curriculum_steps))


def step_generator(seed: int, step: int, device: torch.device | str = "cpu") -> torch.Generator:
    """The random stream of one optimiser step (one per device kind: CPU and CUDA streams differ)."""
    state = int(np.random.SeedSequence([seed, step]).generate_state(1)[0])
    return torch.Generator(device=device).manual_seed(state)


class FrameDataset(Dataset):
    """DREAM frames by *global* sample number (any non-negative int), epoch-shuffled: the image
    brought to the preset's input size (uint8 ``[3, H, W]``), its K, the pose and joints."""

    def __init__(self, frames: Sequence, config: Config, seed: int = 0):
        if len(frames) == 0:
            raise ValueError("no training frames")
        self.frames, self.config, self.seed = frames, config, seed

    def __len__(self) -> int:
        return len(self.frames)

    @lru_cache(maxsize=2)  # noqa: B019 - the dataset lives as long as its workers
    def _epoch_order(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.frames))

    def frame_index(self, sample: int) -> int:
        return int(self._epoch_order(sample // len(self.frames))[sample % len(self.frames)])

    def __getitem__(self, sample: int) -> dict[str, torch.Tensor]:
        frame = self.frames[self.frame_index(sample)]
        image, K = standardize_image(frame.load_image(), frame.K, self.config.network.input_size)
        return {
            "image": torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1),
            "K": torch.from_numpy(K),
            "pose": torch.from_numpy(np.asarray(frame.pose, np.float64)),
            "joints": torch.from_numpy(np.asarray(frame.joints, np.float64)),
        }


@dataclass
class NoisyViews:
    """The forward process applied to a batch, and the crop it implies (all float64, CPU)."""

    t: torch.Tensor  # [B] steps in 1..T
    pose_ref_0: torch.Tensor  # [B, 4, 4] camera-from-centroid, ground truth
    pose_ref_t: torch.Tensor  # [B, 4, 4] H_t
    centroid: torch.Tensor  # [B, 3] base frame
    points_ref: torch.Tensor  # [B, P, 3] model points in the centroid frame
    boxes: torch.Tensor  # [B, 4] crop boxes in the standardised image
    K_crop: torch.Tensor  # [B, 3, 3]


def noisy_views(
    robot: RobotModel,
    noiser: PoseNoiser,
    config: Config,
    pose: torch.Tensor,
    joints: np.ndarray,
    K: torch.Tensor,
    generator: torch.Generator,
    t_max: int | None = None,
) -> NoisyViews:
    """Draw t ~ U{1..t_max} (default T) and H_t ~ q(H_t | H_0) (Sec. III-B) for camera-from-base
    ``pose`` ``[B, 4, 4]``, and the crop around H_t (moved by ``TrainConfig.crop_jitter``)."""
    net = config.network
    n = len(pose)
    points = torch.from_numpy(robot.surface_points(joints))
    centroid = torch.from_numpy(robot.centroid(points.numpy()))
    points_ref = points - centroid[:, None]
    size = torch.tensor([net.input_size], dtype=torch.float64).repeat(n, 1)
    pose_ref_0 = centroid_frame(pose.double(), centroid)
    t = torch.randint(1, (t_max or config.diffusion.num_steps) + 1, (n,), generator=generator)
    pose_ref_t = noiser.add_noise(pose_ref_0, t, K.double(), size, generator)
    jitter = config.train.crop_jitter
    shift = (torch.rand(n, 2, generator=generator, dtype=torch.float64) * 2 - 1) * jitter if jitter else None
    boxes, K_crop = crop_geometry(pose_ref_t, points_ref, K.double(), net.render_size, shift)
    return NoisyViews(t, pose_ref_0, pose_ref_t, centroid, points_ref, boxes, K_crop)


def denoising_batch(
    views: NoisyViews, crops: torch.Tensor, joints: np.ndarray, renderer: RobotRenderer
) -> dict[str, torch.Tensor]:
    """What :func:`monose3.training.loop.train_step` eats: the render at H_t beside the crop."""
    device = crops.device
    size = (crops.shape[-1], crops.shape[-2])
    pose_t = base_frame(views.pose_ref_t, views.centroid).to(device)
    render = renderer.render(joints, pose_t, views.K_crop.to(device), size)
    return {
        "render": render.rgb,
        "depth": render.depth,
        "crop": crops,
        "t": views.t.to(device),
        "pose_ref_t": views.pose_ref_t.float().to(device),
        "pose_ref_0": views.pose_ref_0.float().to(device),
        "K_crop": views.K_crop.float().to(device),
        "points_ref": views.points_ref.float().to(device),
    }


def frames_batch(
    frames: dict[str, torch.Tensor],
    robot: RobotModel,
    renderer: RobotRenderer,
    noiser: PoseNoiser,
    config: Config,
    generator: torch.Generator,
    device: torch.device,
    t_max: int | None = None,
) -> dict[str, torch.Tensor]:
    """A training batch from a collated :class:`FrameDataset` batch (t up to ``t_max``, default T)."""
    joints = frames["joints"].numpy()
    views = noisy_views(robot, noiser, config, frames["pose"], joints, frames["K"], generator, t_max)
    images = frames["image"].to(device, non_blocking=True).float().div_(255.0)
    crops = crop_batch(images, views.boxes.to(device), config.network.render_size)
    return denoising_batch(views, crops, joints, renderer)


class GlobalSampleSampler(Sampler[int]):
    """Yields global sample numbers from ``start``: rank r of w takes its slice of each global
    batch, so the union over ranks is the same stream as one process with a w-times batch."""

    def __init__(self, start: int, batch_size: int, rank: int = 0, world_size: int = 1, total: int | None = None):
        self.start, self.batch_size, self.rank, self.world_size, self.total = start, batch_size, rank, world_size, total

    def __iter__(self) -> Iterator[int]:
        global_batch = self.batch_size * self.world_size
        step = self.start // global_batch
        while self.total is None or step * global_batch < self.total:
            base = step * global_batch + self.rank * self.batch_size
            yield from range(base, base + self.batch_size)
            step += 1

    def __len__(self) -> int:  # only meaningful when total is set
        return max(0, ((self.total or 0) - self.start) // self.world_size)
