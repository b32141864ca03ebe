"""The pose that a displacement field implies (the ``flow-solve`` denoiser; not in the paper).

The render at H_t shows the robot's visible surface, and its depth gives each rendered pixel
a 3D point on the robot. The network predicts where that surface moves between the render
(at H_t) and the crop (at H_0), per cell, with a confidence per cell (:func:`field_targets`
is its target). The robot is rigid for given joints, so that field fixes the rigid update:
each surface point is moved by the field where it lies, and the pose that best reprojects the
points there (weighted least squares over pixels, a few damped Gauss-Newton steps from H_t,
differentiable) is the denoiser's H_0. Its update (Eq. 9) goes through Eq. 10 as any design's,
so the loss trains the field end to end.

Rotation and translation are both read from where the render's parts have to move, i.e. from
comparing render and crop (docs/DESIGNS.md, round 4). Pixel convention: OpenCV, pixel u's
centre at u; cells bin edge coordinates (pixel u spans [u, u + 1]).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from monose3.geometry.camera import project
from monose3.geometry.pose_solve import solve_pose
from monose3.geometry.poses import make_pose, transform_points
from monose3.method.pose_space import MIN_DEPTH

SURFACE_STRIDE = 2  # every 2nd rendered pixel in x and y becomes a surface point


@dataclass
class Surface:
    """Visible surface points of the render at H_t, on a fixed pixel grid (batched, with a mask)."""

    points_ref: torch.Tensor  # [B, N, 3] in the centroid frame of H_t
    uv: torch.Tensor  # [B, N, 2] their pixels in the crop (pixel centres)
    valid: torch.Tensor  # [B, N] bool: the render shows robot there
    pose_ref_t: torch.Tensor  # [B, 4, 4] H_t, camera-from-centroid, that the render shows
    K_crop: torch.Tensor  # [B, 3, 3] the crop's intrinsics
    # [B, K, 3] the robot's keypoints in the centroid frame (the evidence designs read them)
    keypoints_ref: torch.Tensor | None = None


def render_surface(
    depth: torch.Tensor, pose_ref_t: torch.Tensor, K_crop: torch.Tensor, stride: int = SURFACE_STRIDE
) -> Surface:
    """The render's visible surface: pixels of ``depth`` ``[B, H, W]`` (metres along z, 0 where
    empty) on a ``stride`` grid, back-projected with K_crop ``[B, 3, 3]`` and brought into the
    centroid frame of ``pose_ref_t`` ``[B, 4, 4]`` (camera-from-centroid)."""
    z = depth[:, stride // 2 :: stride, stride // 2 :: stride].to(pose_ref_t.dtype)
    b, h, w = z.shape
    v, u = torch.meshgrid(
        *(torch.arange(n, dtype=z.dtype, device=z.device) * stride + stride // 2 for n in (h, w)), indexing="ij"
    )
    uv = torch.stack([u, v], -1).reshape(1, h * w, 2).expand(b, -1, -1)
    z = z.reshape(b, h * w)
    rays = (uv - K_crop[:, None, :2, 2]) / torch.stack([K_crop[:, 0, 0], K_crop[:, 1, 1]], -1)[:, None]
    cam = torch.cat([rays, torch.ones_like(z)[..., None]], -1) * z[..., None]
    rot, trans = pose_ref_t[:, :3, :3], pose_ref_t[:, :3, 3]
    points = (cam - trans[:, None]) @ rot  # R^T (X - t), row vectors
    return Surface(points, uv, z > 0, pose_ref_t, K_crop)


def field_targets(
    surface: Surface, pose_ref_0: torch.Tensor, render_size: tuple[int, int], cells: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The displacement field the network is trained to predict: per cell of a ``cells`` = (h, w)
    grid, the mean move of the render's visible surface points in it, from their pixel in the
    render (H_t) to their pixel under H_0, in units of the render width. Returns ``field``
    ``[B, 2, h, w]`` and the cells that hold surface, ``mask [B, 1, h, w]``."""
    (width, height), (h, w) = render_size, cells
    shift = (project(transform_points(pose_ref_0, surface.points_ref), surface.K_crop) - surface.uv) / width
    col = ((surface.uv[..., 0] + 0.5) * w / width).floor().long().clamp(0, w - 1)
    row = ((surface.uv[..., 1] + 0.5) * h / height).floor().long().clamp(0, h - 1)
    b = len(shift)
    index = (torch.arange(b, device=row.device)[:, None] * h + row) * w + col
    index = torch.where(surface.valid, index, b * h * w).reshape(-1)  # a spare bin for empty pixels
    sums = torch.zeros(b * h * w + 1, 2, dtype=shift.dtype, device=shift.device)
    sums.index_add_(0, index, shift.reshape(-1, 2))
    counts = torch.zeros(b * h * w + 1, dtype=shift.dtype, device=shift.device)
    counts.index_add_(0, index, torch.ones_like(index, dtype=shift.dtype))
    field = (sums[:-1] / counts[:-1, None].clamp(min=1)).reshape(b, h, w, 2).permute(0, 3, 1, 2)
    return field, (counts[:-1] > 0).reshape(b, 1, h, w)


def sample_field(field: torch.Tensor, uv: torch.Tensor, render_size: tuple[int, int]) -> torch.Tensor:
    """Bilinear samples ``[B, N, C]`` of a per-cell field ``[B, C, h, w]`` at crop pixels ``uv``
    ``[B, N, 2]`` (pixel centres of a ``render_size`` = (w, h) crop)."""
    width, height = render_size
    grid = torch.stack([2.0 * (uv[..., 0] + 0.5) / width - 1.0, 2.0 * (uv[..., 1] + 0.5) / height - 1.0], dim=-1)
    values = nn.functional.grid_sample(field, grid[:, :, None].to(field.dtype), align_corners=False)
    return values[..., 0].transpose(1, 2)


def pose_from_field(
    field: torch.Tensor,
    confidence: torch.Tensor,
    surface: Surface,
    render_size: tuple[int, int],
    prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """The H_0 ``[B, 4, 4]`` (camera-from-centroid) that a displacement field implies.

    ``field`` ``[B, 2, h, w]``: per cell, the move (units of the render width) of the robot's
    visible surface from the render (H_t) to the crop (H_0); ``confidence`` ``[B, 1, h, w]``
    (>= 0): how far to trust each cell. Each point of ``surface`` is moved by the field where
    it lies, and the pose is solved by :func:`solve_pose` from H_t (with ``prior`` on the
    update, ``[B, 6]`` precisions, optional); its depth is kept at
    :data:`~monose3.method.pose_space.MIN_DEPTH` or more, as every pose the diffusion makes."""
    # Normalised convolution: the field weighted by its confidence, divided by the confidence,
    # so a point near the robot's outline is not pulled toward the empty cells beside it.
    sampled = sample_field(torch.cat([field * confidence, confidence], 1), surface.uv, render_size)
    weights = sampled[..., 2] * surface.valid.to(sampled.dtype)
    target = surface.uv + sampled[..., :2] / sampled[..., 2:].clamp_min(1e-6) * render_size[0]
    pose = solve_pose(surface.pose_ref_t, surface.K_crop, surface.points_ref, target, weights, prior)
    depth = pose[:, 2, 3].clamp_min(MIN_DEPTH)
    return make_pose(pose[:, :3, :3], torch.cat([pose[:, :2, 3], depth[:, None]], 1))
