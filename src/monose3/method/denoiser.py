"""The render-and-compare pose denoiser of Sec. III-C: the contract every design keeps.

A design (``monose3.method.designs``, one class per ``NetworkConfig.design``) maps the render
at H_t, the image crop and the step t to the raw outputs of the pose update (Eq. 9,
:func:`~monose3.method.update.raw_to_update`), and, where it predicts one, the displacement
field between render and crop. The estimator and the training loop call every design alike:
``model(render, crop, t, surface) -> DenoiserOutput``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import nn

from monose3.geometry.rotations import matrix_to_rotation_6d, rotvec_to_matrix
from monose3.method.config import ROTATION_OUTPUTS, NetworkConfig
from monose3.method.flow_pose import Surface
from monose3.method.update import IDENTITY_6D

NUM_OUTPUTS = 9  # v_xy (2), dR 6D (6), v_z (1)


@dataclass
class DenoiserOutput:
    """``raw``: ``[B, 9]`` raw outputs of the update (Eq. 9). ``field``: the predicted
    displacement field ``[B, 2, h', w']`` (``[B, 3, h', w']`` with the log of its Laplace
    scale) for designs that predict one (:attr:`Denoiser.predicts_field`), else None."""

    raw: torch.Tensor
    field: torch.Tensor | None = None


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps ``[B]`` to ``[B, dim]`` (C_emb, Sec. III-C)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


def timestep_of(emb: torch.Tensor) -> torch.Tensor:
    """The steps ``[B]`` that :func:`timestep_embedding` embedded as ``emb`` ``[B, dim]`` (read off
    its slowest sine and cosine: exact for t below pi times 10000 ** (1 - 2 / dim))."""
    half = emb.shape[1] // 2
    slowest = math.exp(-math.log(10000.0) * (half - 1) / half)
    return torch.atan2(emb[:, half - 1], emb[:, -1]) / slowest


def so3_raw(raw: torch.Tensor) -> torch.Tensor:
    """Raw outputs whose rotation part is read as a rotation vector (``raw[:, 2:5]``, radians)
    instead of a 6D offset, returned in the 6D layout :func:`raw_to_update` reads (exact: the
    6D of a rotation matrix is orthonormal already). Unlike the 6D offset, the rotation vector
    has no directions that leave dR unchanged: in those (the 6D columns' lengths and their
    mutual angle) the loss has zero gradient, and Adam turns the float noise there into
    full-size steps (measured: raw std ~0.3 on the two 6D diagonal entries after 1000 steps)."""
    rot = matrix_to_rotation_6d(rotvec_to_matrix(raw[:, 2:5])) - IDENTITY_6D.to(raw)
    return torch.cat([raw[:, :2], rot, raw[:, 8:]], dim=1)


class Denoiser(nn.Module):
    """Base of every design: embeds t (C_emb), lets the design compare render and crop
    (:meth:`compare`), and reads the rotation outputs as ``config.rotation_output`` says."""

    predicts_field: ClassVar[bool] = False  # whether DenoiserOutput.field is set (TrainConfig.flow_weight)
    # What it compares: "pixels" (the render's and the image's) or "parser" (the silhouette and
    # keypoints at H_t against the robot parser's mask and keypoints: method.evidence).
    inputs: ClassVar[str] = "pixels"
    channels: ClassVar[int] = 3  # of the render and of the crop each
    rotation_outputs: ClassVar[tuple[str, ...]] = ROTATION_OUTPUTS  # the rotation outputs it can be read with

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        if config.rotation_output not in ROTATION_OUTPUTS:
            raise ValueError(f"unknown rotation output {config.rotation_output!r}; choose one of {ROTATION_OUTPUTS}")
        if config.rotation_output not in self.rotation_outputs:
            raise ValueError(
                f"the {config.design} design solves its rotation from the field; use rotation_output="
                f"{self.rotation_outputs[0]!r}"
            )

    def compare(self, render: torch.Tensor, crop: torch.Tensor, emb: torch.Tensor, surface: Surface) -> DenoiserOutput:
        raise NotImplementedError

    def forward(self, render: torch.Tensor, crop: torch.Tensor, t: torch.Tensor, surface: Surface) -> DenoiserOutput:
        """``render``, ``crop``: ``[B, 3, h, w]`` in [0, 1]; ``t``: ``[B]`` steps; ``surface``: the
        render's visible surface (:func:`~monose3.method.flow_pose.render_surface`)."""
        emb = timestep_embedding(t, self.config.time_embedding_dim).to(render.dtype)
        out = self.compare(render, crop, emb, surface)
        if self.config.rotation_output == "so3":
            out.raw = so3_raw(out.raw)
        return out
