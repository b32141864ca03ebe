"""The robot parser's evidence as the ``evidence`` denoiser reads it (render-and-compare against
the parser's mask and keypoints instead of the image's pixels; not in the paper).

The evidence comes from outside this package (``monose3.estimator`` parses the image; training
reads it from a cache of the parser's outputs): a mask of robot probability over a box of the
standardised image, and keypoints with confidences. At a pose H_t both sides are brought to the
RoboPose crop around it, pixel-aligned, as the paper brings the image and the render:

* the evidence: the mask resampled into the crop, and a Gaussian blob per keypoint (weighted by
  its confidence) at the crop pixel the parser saw it;
* the render: the robot's silhouette at H_t, and a blob per keypoint where H_t projects it.

One channel per keypoint on both sides (:data:`KEYPOINT_CHANNELS`, zero-padded), so the network
can tell which keypoint is which: that is what fixes the rotation.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from monose3.geometry.camera import crop_images, project
from monose3.robot import RobotModel

KEYPOINT_CHANNELS = 8  # keypoint maps per side (the Panda has 7, DREAM's Kuka 8); more are refused
KEYPOINT_SIGMA = 1.5  # the blobs' standard deviation, crop pixels
EVIDENCE_CHANNELS = 1 + KEYPOINT_CHANNELS  # per side: the mask (or silhouette), then the keypoints


@dataclass
class Evidence:
    """The parser's evidence for B images, in the standardised image (the network's input size)."""

    mask: torch.Tensor  # [B, 1, h, w] robot probability over ``box``
    box: torch.Tensor  # [B, 4] x1, y1, x2, y2 (edge coordinates) of the image that the mask covers
    keypoints: torch.Tensor  # [B, K, 2] pixel centres in the image
    confidence: torch.Tensor  # [B, K] in [0, 1]

    def map(self, fn) -> Evidence:
        """The same evidence with ``fn`` applied to each tensor (``repeat_interleave``, ``to``...)."""
        return Evidence(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})


def keypoints_ref(robot: RobotModel, joints: np.ndarray, centroid: np.ndarray | torch.Tensor) -> torch.Tensor:
    """The robot's keypoints ``[B, K, 3]`` at ``joints`` ``[B, n]`` in the centroid frame (the base
    frame moved to ``centroid`` ``[B, 3]``): what the evidence designs pull onto the parser's."""
    return torch.from_numpy(robot.keypoints(joints)) - torch.as_tensor(centroid, dtype=torch.float64)[:, None]


def keypoint_maps(uv: torch.Tensor, weights: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[B, KEYPOINT_CHANNELS, h, w]`` Gaussian blobs (:data:`KEYPOINT_SIGMA`) at crop pixels
    ``uv`` ``[B, K, 2]``, each scaled by its weight ``[B, K]``; channels past K are zero."""
    b, k = weights.shape
    if k > KEYPOINT_CHANNELS:
        raise ValueError(f"the evidence design takes at most {KEYPOINT_CHANNELS} keypoints, got {k}")
    w, h = size
    xs = torch.arange(w, dtype=uv.dtype, device=uv.device)
    ys = torch.arange(h, dtype=uv.dtype, device=uv.device)
    gx = torch.exp(-((xs - uv[..., 0:1]) ** 2) / (2 * KEYPOINT_SIGMA**2))  # [B, K, w]
    gy = torch.exp(-((ys - uv[..., 1:2]) ** 2) / (2 * KEYPOINT_SIGMA**2))  # [B, K, h]
    blobs = gy[..., :, None] * gx[..., None, :] * weights[..., None, None].to(uv.dtype)
    return torch.cat([blobs, blobs.new_zeros(b, KEYPOINT_CHANNELS - k, h, w)], 1)


def to_crop_pixels(uv: torch.Tensor, boxes: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Image pixel centres ``[B, K, 2]`` to pixels of the crops ``boxes`` ``[B, 4]`` resized to
    ``size`` (the mapping :func:`~monose3.geometry.camera.crop_intrinsics` applies)."""
    scale = torch.stack([(boxes[:, 2] - boxes[:, 0]) / size[0], (boxes[:, 3] - boxes[:, 1]) / size[1]], 1)
    return (uv + 0.5 - boxes[:, None, :2]) / scale[:, None] - 0.5


def evidence_crops(evidence: Evidence, boxes: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """The evidence side ``[B, EVIDENCE_CHANNELS, h, w]`` in the crops ``boxes`` ``[B, 4]`` (edge
    coordinates of the standardised image) at ``size`` (w, h): the mask, then the keypoint blobs."""
    mask = evidence.mask.float()
    per_pixel = torch.stack([(evidence.box[:, 2] - evidence.box[:, 0]) / mask.shape[-1],
                             (evidence.box[:, 3] - evidence.box[:, 1]) / mask.shape[-2]], 1)  # fmt: skip
    rois = (boxes.to(evidence.box) - evidence.box[:, :2].repeat(1, 2)) / per_pixel.repeat(1, 2)
    crops = crop_images(mask, rois.to(mask), size)
    uv = to_crop_pixels(evidence.keypoints.to(boxes), boxes, size)
    return torch.cat([crops, keypoint_maps(uv.float(), evidence.confidence.float(), size)], 1)


def render_maps(silhouette: torch.Tensor, keypoints_cam: torch.Tensor, K_crop: torch.Tensor) -> torch.Tensor:
    """The render side ``[B, EVIDENCE_CHANNELS, h, w]``: the silhouette ``[B, h, w]`` (or
    ``[B, 1, h, w]``) at H_t and a blob where each camera-frame keypoint ``[B, K, 3]`` projects
    through the crop's intrinsics ``[B, 3, 3]``."""
    sil = silhouette.float().reshape(len(silhouette), 1, *silhouette.shape[-2:])
    size = (sil.shape[-1], sil.shape[-2])
    uv = project(keypoints_cam, K_crop.to(keypoints_cam)).float()
    return torch.cat([sil, keypoint_maps(uv, torch.ones(uv.shape[:2], device=uv.device), size)], 1)
