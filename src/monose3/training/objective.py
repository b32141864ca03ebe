"""The training objective of Alg. 1 and one optimiser step on it: Eq. 10 (its rotation part
weighted by ``TrainConfig.rot_weight``) plus, at ``TrainConfig.flow_weight``, the loss of the
design's displacement field. The training loop and the design study step through this alone."""

from __future__ import annotations

from contextlib import nullcontext

import torch

from monose3.errors import Monose3Error
from monose3.method.config import Config
from monose3.method.denoiser import Denoiser, DenoiserOutput
from monose3.method.flow_pose import Surface, field_targets, render_surface
from monose3.method.loss import disentangled_loss, flow_loss


def batch_surface(batch: dict[str, torch.Tensor]) -> Surface:
    """The visible surface of a batch's renders (its ``depth`` at ``pose_ref_t`` through ``K_crop``),
    with the robot's keypoints where the batch has them (``keypoints_ref``: the evidence designs')."""
    surface = render_surface(batch["depth"], batch["pose_ref_t"], batch["K_crop"])
    surface.keypoints_ref = batch.get("keypoints_ref")
    return surface


def objective(
    out: DenoiserOutput, batch: dict[str, torch.Tensor], surface: Surface, config: Config
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss a step minimises and its parts (``xy``, ``rot``, ``z``, and ``flow`` when weighted)."""
    poses = (batch["pose_ref_t"], batch["pose_ref_0"], batch["K_crop"], batch["points_ref"])
    _, parts = disentangled_loss(out.raw.float(), *poses, config.network.render_size[0])
    loss = parts["xy"] + config.train.rot_weight * parts["rot"] + parts["z"]
    if config.train.flow_weight > 0:
        if out.field is None:
            raise Monose3Error("flow_weight > 0 needs a design that predicts a displacement field; set it to 0")
        cells = tuple(out.field.shape[-2:])
        target, mask = field_targets(surface, batch["pose_ref_0"], config.network.render_size, cells)
        parts["flow"] = flow_loss(out.field.float(), target, mask)
        loss = loss + config.train.flow_weight * parts["flow"]
    return loss, parts


def train_step(
    model: Denoiser,
    optimizer: torch.optim.Optimizer,
    batch: dict[str, torch.Tensor],
    config: Config,
    lr: float,
    amp=nullcontext,
) -> tuple[float, dict[str, float]]:
    """One optimiser step of Alg. 1 on a batch (tensors on the model's device); returns the loss and its parts."""
    for group in optimizer.param_groups:
        group["lr"] = lr
    surface = batch_surface(batch)
    with amp():
        out = model(batch["render"], batch["crop"], batch["t"], surface)
    loss, parts = objective(out, batch, surface, config)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), config.train.grad_clip)
    optimizer.step()
    return loss.item(), {k: v.item() for k, v in parts.items()}
