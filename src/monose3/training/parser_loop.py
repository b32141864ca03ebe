"""Training the robot parser (mask + keypoint heatmaps) on whole images synthesised on the fly.

Each step draws scenes as ``monose3 generate`` does (joints, camera, light), cycling through
the scene profiles so small, off-centre and occluded robots are seen as often as centred ones;
renders them on the training device over random backgrounds with distractors and occluders,
and trains on the robot's visible mask and its keypoints' projections. The run stops at a step
count or a wall-clock budget, writes half-precision weight shards every minute (a killed run
loses at most a minute) and continues from shards with ``init``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader
from tqdm import tqdm

from monose3.data.scenes.appearance import load_photos
from monose3.data.scenes.profiles import get_profile
from monose3.errors import Monose3Error
from monose3.geometry.camera import project
from monose3.perception.config import PARSER_KIND, ParserConfig
from monose3.perception.parser import OUTPUT_STRIDE, RobotParser, keypoint_loss, mask_loss
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer
from monose3.training.checkpoints import read_parser
from monose3.training.logs import CsvTensorBoardLog
from monose3.training.samples import GlobalSampleSampler, step_generator
from monose3.training.shards import write_shards
from monose3.training.synthetic import SceneDataset, synthesize_images

TRAIN_PROFILES = ("train", "reallike", "hard")
PARSER_LOG_FIELDS = ["step", "samples", "lr", "mask", "keypoints", "samples_per_s"]
TRUNK_LR_SCALE = 0.3  # the pretrained trunk moves slower than the fresh decoder


@dataclass
class ParserBatch:
    image: torch.Tensor  # [B, 3, H, W] in [0, 1]
    mask: torch.Tensor  # [B, 1, H/2, W/2], the visible fraction of each output cell
    keypoints: torch.Tensor  # [B, K, 2] input pixels


class ParserBatchMaker:
    """The batch of each step: scenes from data-loader workers (one stream per profile, in
    turn), rendered and composed on ``device``."""

    def __init__(self, config: ParserConfig, device: torch.device, start_step: int, workers: int, backgrounds=None):
        self.config, self.device = config, device
        self.robot = RobotModel(config.robot)
        self.renderer = RobotRenderer(self.robot, device)
        self.photos = load_photos(backgrounds, device)
        per_stream = start_step // len(TRAIN_PROFILES) * config.batch_size
        self.streams: list[Iterator] = []
        for i, name in enumerate(TRAIN_PROFILES):
            scenes = SceneDataset(self.robot.spec, name, config.input_size, config.seed * 100 + i)
            loader = DataLoader(
                scenes,
                batch_size=config.batch_size,
                sampler=GlobalSampleSampler(per_stream, config.batch_size),
                num_workers=workers,
                persistent_workers=workers > 0,
                prefetch_factor=4 if workers > 0 else None,
                pin_memory=device.type == "cuda",
            )
            self.streams.append(iter(loader))

    def batch(self, step: int) -> ParserBatch:
        which = step % len(TRAIN_PROFILES)
        scenes = next(self.streams[which])
        profile = get_profile(TRAIN_PROFILES[which])
        gen = step_generator(self.config.seed * 1000 + 17, step, self.device)
        image, visible = synthesize_images(
            self.renderer, scenes, self.config.input_size, profile, self.photos, gen, self.device
        )
        uv = project(self.robot.keypoints(scenes["joints"].numpy(), scenes["pose"].numpy()), scenes["K"].numpy())
        mask = F.avg_pool2d(visible, OUTPUT_STRIDE)
        return ParserBatch(image, mask, torch.as_tensor(uv, dtype=torch.float32, device=self.device))


def parser_losses(model: torch.nn.Module, batch: ParserBatch, config: ParserConfig) -> dict[str, torch.Tensor]:
    mask_logits, kp_logits = model(batch.image)
    return {
        "mask": mask_loss(mask_logits.float(), batch.mask),
        "keypoints": keypoint_loss(kp_logits.float(), batch.keypoints, config.keypoint_sigma),
    }


def parser_optimizer(model: RobotParser, lr: float) -> torch.optim.Optimizer:
    """AdamW with the pretrained trunk's learning rate scaled by :data:`TRUNK_LR_SCALE` (each
    group's ``scale``: a schedule sets ``lr * scale``)."""
    trunk = list(model.trunk.parameters())
    trunk_ids = {id(p) for p in trunk}
    rest = [p for p in model.parameters() if id(p) not in trunk_ids]
    groups = [{"params": trunk, "scale": TRUNK_LR_SCALE}, {"params": rest, "scale": 1.0}]
    return torch.optim.AdamW(groups, lr=lr, weight_decay=1e-4)


def train_parser(
    config: ParserConfig,
    out: str | Path,
    minutes: float | None = None,
    steps: int | None = None,
    init: str | Path | None = None,
    workers: int = 0,
    backgrounds: str | Path | None = None,
    progress: bool = True,
    anneal: bool = False,
) -> dict:
    """Train to ``steps`` or for ``minutes`` (whichever first); returns the last shard metadata.
    ``anneal``: after the warm-up the learning rate follows a cosine to zero over the budget
    (the share of ``minutes`` or of the steps spent), for a run that ends a training schedule."""
    if minutes is None and steps is None:
        raise Monose3Error("give the parser's training a budget: --minutes or --steps")
    started = time.perf_counter()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(config.seed)
    out = Path(out)
    step = samples = 0
    if init is not None:
        model, meta = read_parser(init)
        model.train()
        step, samples = int(meta["step"]), int(meta["samples"])
    else:
        model = RobotParser(config)
    model = model.to(device)
    optimizer = parser_optimizer(model, config.lr)
    maker = ParserBatchMaker(config, device, step, workers, backgrounds)
    amp = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if device.type == "cuda" else nullcontext
    log = CsvTensorBoardLog(out, step, PARSER_LOG_FIELDS)
    first, last_shard, last_row, window = step, time.perf_counter(), time.perf_counter(), []
    bar = tqdm(desc="parser", unit="step", disable=not progress)
    meta = {}
    while steps is None or step < steps:
        if minutes is not None and time.perf_counter() - started > minutes * 60:
            break
        batch = maker.batch(step)
        lr = config.lr * min(1.0, (step - first + 1) / config.warmup_steps)
        if anneal:
            spent = (time.perf_counter() - started) / (minutes * 60) if minutes else 0.0
            spent = max(spent, (step - first) / (steps - first) if steps else 0.0)
            lr *= 0.5 * (1 + math.cos(math.pi * min(spent, 1.0)))
        for group in optimizer.param_groups:
            group["lr"] = lr * group["scale"]
        with amp():
            parts = parser_losses(model, batch, config)
        loss = parts["mask"] + config.keypoint_weight * parts["keypoints"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optimizer.step()
        step, samples = step + 1, samples + config.batch_size
        window.append({k: v.item() for k, v in parts.items()})
        bar.update(1)
        if step % 20 == 0:
            means = {k: float(np.mean([w[k] for w in window])) for k in window[0]}
            rate = 20 * config.batch_size / (time.perf_counter() - last_row)
            log.write({"step": step, "samples": samples, "lr": lr, "samples_per_s": rate, **means})
            last_row = time.perf_counter()
            bar.set_postfix(means)
            window = []
        if time.perf_counter() - last_shard > 60:
            meta = _save(model, out, config, step, samples)
            last_shard = time.perf_counter()
    bar.close()
    log.close()
    if step > first:
        meta = _save(model, out, config, step, samples)
    return meta


def _save(model: RobotParser, out: Path, config: ParserConfig, step: int, samples: int) -> dict:
    meta = {"kind": PARSER_KIND, "parser": asdict(config), "step": step, "samples": samples}
    write_shards(out, model.state_dict(), meta)
    return meta
