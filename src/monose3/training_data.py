"""Training samples for Alg. 1: a frame, a step t, the noisy pose H_t from the forward process,
and the render at H_t beside the image crop, made inside the data-loader workers.

Every sample is a pure function of (seed, global sample number), so a resumed run sees
exactly the samples the uninterrupted run would have seen.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from functools import lru_cache

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from monose3.camera import standardize_image
from monose3.config import Config
from monose3.diffusion import base_frame, centroid_frame, make_noiser
from monose3.render import Renderer
from monose3.robot import RobotModel
from monose3.views import crop_batch, crop_geometry, image_to_tensor, render_jobs


class DenoisingSamples(Dataset):
    """Map-style dataset indexed by the *global* sample number (any non-negative int)."""

    def __init__(self, frames: Sequence, config: Config, seed: int = 0):
        if len(frames) == 0:
            raise ValueError("no training frames")
        self.frames = frames
        self.config = config
        self.seed = seed
        self.robot = RobotModel(config.robot)
        self.noiser = make_noiser(config.diffusion)
        self._renderer: Renderer | None = None

    def __len__(self) -> int:
        return len(self.frames)

    @lru_cache(maxsize=2)  # noqa: B019 - the dataset lives as long as its workers
    def _epoch_order(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.frames))

    def frame_index(self, sample: int) -> int:
        return int(self._epoch_order(sample // len(self.frames))[sample % len(self.frames)])

    @property
    def renderer(self) -> Renderer:
        # Created lazily so that each data-loader worker process owns its pybullet client.
        if self._renderer is None:
            self._renderer = Renderer(self.robot)
        return self._renderer

    def __getitem__(self, sample: int) -> dict[str, torch.Tensor]:
        net, steps = self.config.network, self.config.diffusion.num_steps
        frame = self.frames[self.frame_index(sample)]
        gen = torch.Generator().manual_seed(int(np.random.SeedSequence([self.seed, sample]).generate_state(1)[0]))
        image, K = standardize_image(frame.load_image(), frame.K, net.input_size)
        joints = np.asarray(frame.joints, dtype=np.float64)
        points = self.robot.surface_points(joints[None])[0]
        centroid = torch.from_numpy(self.robot.centroid(points))[None]
        points_ref = torch.from_numpy(points)[None] - centroid[:, None]
        K_t = torch.from_numpy(K)[None]
        size = torch.tensor([net.input_size], dtype=torch.float64)
        pose_ref_0 = centroid_frame(torch.from_numpy(np.asarray(frame.pose, dtype=np.float64))[None], centroid)
        t = torch.randint(1, steps + 1, (1,), generator=gen)
        pose_ref_t = self.noiser(pose_ref_0, t, K_t, size, gen)
        boxes, K_crop = crop_geometry(pose_ref_t, points_ref, K_t, net.render_size)
        job = render_jobs(joints[None], base_frame(pose_ref_t, centroid), K_crop, net.render_size)[0]
        render, _ = self.renderer.render(job)
        crop = crop_batch(image_to_tensor(image)[None], boxes, net.render_size)[0]
        return {
            "render": image_to_tensor(render),
            "crop": crop,
            "t": t[0],
            "pose_ref_t": pose_ref_t[0].float(),
            "pose_ref_0": pose_ref_0[0].float(),
            "K_crop": K_crop[0].float(),
            "points_ref": points_ref[0].float(),
        }


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
