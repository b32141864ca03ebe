"""Render-and-compare inputs (Sec. III-C): the crop around the robot at a pose, the crop's
intrinsics, the render at that pose and the image crop, pixel-aligned. Shared by training
and inference."""

from __future__ import annotations

import numpy as np
import torch

from monose3.geometry.camera import crop_boxes, crop_images, crop_intrinsics, project
from monose3.geometry.poses import transform_points

# Points nearer than this (metres) are projected as if this far, so a pose that puts part of the
# robot behind the lens still gives a finite crop box.
NEAR_CLIP = 0.05


def crop_geometry(
    pose_ref: torch.Tensor,
    points_ref: torch.Tensor,
    K: torch.Tensor,
    render_size: tuple[int, int],
    shift: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Crop boxes ``[B, 4]`` and crop intrinsics ``[B, 3, 3]`` for the robot at ``pose_ref``.

    ``pose_ref`` is camera-from-centroid and ``points_ref`` the model points in the centroid
    frame, so the crop is centred on the reference point's projection (RoboPose's rule);
    ``shift`` ``[B, 2]`` moves each box by that fraction of its size (training's crop jitter).
    """
    cam_points = transform_points(pose_ref, points_ref)
    cam_points = torch.cat([cam_points[..., :2], cam_points[..., 2:].clamp_min(NEAR_CLIP)], -1)
    center = pose_ref[:, None, :3, 3].clone()
    center[..., 2] = center[..., 2].clamp_min(NEAR_CLIP)
    uv = project(cam_points, K)
    uv_center = project(center, K)[:, 0]
    boxes = crop_boxes(uv, uv_center, render_size[0] / render_size[1])
    if shift is not None:
        boxes = boxes + (shift.to(boxes) * (boxes[:, 2:] - boxes[:, :2])).repeat(1, 2)
    return boxes, crop_intrinsics(K, boxes, render_size)


def image_to_tensor(image: np.ndarray) -> torch.Tensor:
    """``[H, W, 3]`` uint8 to ``[3, H, W]`` float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float().div_(255.0)


def crop_batch(images: torch.Tensor, boxes: torch.Tensor, render_size: tuple[int, int]) -> torch.Tensor:
    """Crops of the input images ``[B, 3, H, W]`` at ``boxes``, resized to ``render_size``."""
    return crop_images(images, boxes.to(images.dtype), render_size)
