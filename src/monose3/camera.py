"""Camera geometry: projection, RoboPose's crop box, crop intrinsics and the batched crop.

Pixel convention: OpenCV, pixel u's centre is at coordinate u. Boxes are in "edge"
coordinates (pixel u spans [u, u+1]), which is what ``roi_align(aligned=True)`` expects.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torchvision.ops import roi_align

from monose3.errors import Monose3Error

CROP_MARGIN = 1.4


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3x3 pinhole matrix K."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of camera-frame ``[B, N, 3]`` points with ``[B, 3, 3]`` K to ``[B, N, 2]``."""
    z = points[..., 2:3].clamp_min(1e-6)
    uv = points[..., :2] / z
    return uv * K[:, None, [0, 1], [0, 1]] + K[:, None, [0, 1], [2, 2]]


def crop_boxes(uv_points: torch.Tensor, uv_center: torch.Tensor, aspect: float) -> torch.Tensor:
    """RoboPose's crop rule: ``[B, 4]`` boxes (x1, y1, x2, y2, edge coordinates).

    Centred on the reference point's projection ``uv_center`` ``[B, 2]``; half-size from the
    largest distance to the projected points' box edges, grown to ``aspect`` (w/h) and by
    1.4. Not clamped to the image: roi_align pads with zeros, as the render does.
    """
    lo, hi = uv_points.min(1).values, uv_points.max(1).values
    dist = torch.maximum((uv_center - lo).abs(), (hi - uv_center).abs())
    xdist, ydist = dist[:, 0], dist[:, 1]
    width = torch.maximum(xdist, ydist * aspect) * 2 * CROP_MARGIN
    height = torch.maximum(xdist / aspect, ydist) * 2 * CROP_MARGIN
    cx, cy = uv_center[:, 0] + 0.5, uv_center[:, 1] + 0.5
    return torch.stack([cx - width / 2, cy - height / 2, cx + width / 2, cy + height / 2], dim=1)


def crop_intrinsics(K: torch.Tensor, boxes: torch.Tensor, out_size: tuple[int, int]) -> torch.Tensor:
    """Intrinsics of each crop resized to ``out_size`` (w, h): a point projects to the same
    crop pixel through these as through K followed by the crop (``crop_images``)."""
    out_w, out_h = out_size
    sx = (boxes[:, 2] - boxes[:, 0]) / out_w
    sy = (boxes[:, 3] - boxes[:, 1]) / out_h
    Kc = K.clone()
    Kc[:, 0, 0] = K[:, 0, 0] / sx
    Kc[:, 1, 1] = K[:, 1, 1] / sy
    Kc[:, 0, 2] = (K[:, 0, 2] - boxes[:, 0] + 0.5) / sx - 0.5
    Kc[:, 1, 2] = (K[:, 1, 2] - boxes[:, 1] + 0.5) / sy - 0.5
    return Kc


def crop_images(images: torch.Tensor, boxes: torch.Tensor, out_size: tuple[int, int]) -> torch.Tensor:
    """Bilinear crops ``[B, C, h, w]`` of ``[B, C, H, W]`` float images (one box per image).

    ``sampling_ratio=2`` averages 2x2 samples per output pixel, which anti-aliases strong
    down-scaling without moving the pixel centres.
    """
    out_w, out_h = out_size
    rois = torch.cat([torch.arange(len(boxes), dtype=boxes.dtype, device=boxes.device)[:, None], boxes], 1)
    return roi_align(images, rois.to(images.dtype), (out_h, out_w), 1.0, sampling_ratio=2, aligned=True)


def standardize_image(image: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bring an image to ``size`` (w, h): zero-pad to its aspect (right/bottom), then resize.

    Returns the new image and its intrinsics; padding keeps every pixel of the input.
    """
    h, w = image.shape[:2]
    out_w, out_h = size
    target = out_w / out_h
    pad_w, pad_h = max(w, int(round(h * target))), max(h, int(round(w / target)))
    if (pad_w, pad_h) != (w, h):
        canvas = np.zeros((pad_h, pad_w, *image.shape[2:]), image.dtype)
        canvas[:h, :w] = image
        image = canvas
    scale = out_w / pad_w
    if (pad_w, pad_h) != (out_w, out_h):
        image = cv2.resize(image, (out_w, out_h), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    Ks = K.astype(np.float64).copy()
    Ks[0, 0] *= out_w / pad_w
    Ks[1, 1] *= out_h / pad_h
    Ks[0, 2] = (K[0, 2] + 0.5) * out_w / pad_w - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * out_h / pad_h - 0.5
    return image, Ks


def check_intrinsics(K: np.ndarray, width: int, height: int, source: str = "camera") -> None:
    """Reject intrinsics that cannot belong to a ``width`` x ``height`` image."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise Monose3Error(f"{source}: intrinsics must be finite fx, fy, cx, cy")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fx <= 0 or fy <= 0:
        raise Monose3Error(f"{source}: focal lengths must be positive (fx={fx}, fy={fy})")
    if not (0 < cx < width and 0 < cy < height):
        raise Monose3Error(
            f"{source}: principal point ({cx:.1f}, {cy:.1f}) lies outside the {width}x{height} image; "
            "the intrinsics do not match this image (check its resolution)"
        )
