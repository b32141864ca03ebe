"""The pinhole camera: the :class:`Intrinsics` type (the only place K is built, validated and
rescaled), projection, RoboPose's crop box, crop intrinsics and the batched crop.

Pixel convention: OpenCV, pixel u's centre is at coordinate u. Boxes are in "edge"
coordinates (pixel u spans [u, u+1]), which is what ``roi_align(aligned=True)`` expects.
Only :func:`crop_images` needs torch (imported when called), so readers of camera files
stay torch-free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.arrays import array_module

CROP_MARGIN = 1.4  # RoboPose: the crop box is the robot's extent about its centre, grown by 1.4
PROJECTION_EPS_DEPTH = 1e-6  # metres: projection divides by at least this (points behind the camera stay finite)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3x3 pinhole matrix K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def is_number(value: Any) -> bool:
    """A real number (Python or numpy), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _number(value: Any, key: str, source: str) -> float:
    if not is_number(value):
        raise Monose3Error(f"{source}: '{key}' must be a number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (OpenCV, pixel-centre convention) and the image size they belong to."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the matrix
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (self.width, self.height)

    def to_dict(self) -> dict[str, float | int]:
        """Our JSON layout, readable by ``monose3.data.inputs.load_camera``."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def checked(cls, fx: Any, fy: Any, cx: Any, cy: Any, width: Any, height: Any, source: str = "camera") -> Intrinsics:
        """Validate and build: the invariants of a pinhole camera (positive whole image size,
        finite positive focal lengths, the principal point inside the image); every check names
        the value that is wrong. Whether the values are plausible for a real camera is the input
        checks' call (``monose3.data.validation.check_K``)."""
        fx, fy, cx, cy = (_number(v, k, source) for v, k in ((fx, "fx"), (fy, "fy"), (cx, "cx"), (cy, "cy")))
        w, h = _number(width, "width", source), _number(height, "height", source)
        if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
            raise Monose3Error(f"{source}: image width/height must be positive whole pixels, got {width}x{height}")
        if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
            raise Monose3Error(f"{source}: intrinsics must be finite numbers (fx={fx}, fy={fy}, cx={cx}, cy={cy})")
        if fx <= 0 or fy <= 0:
            raise Monose3Error(
                f"{source}: focal lengths must be positive pixels (fx={fx:g}, fy={fy:g}); fix the calibration"
            )
        if not (0 < cx < w and 0 < cy < h):
            raise Monose3Error(
                f"{source}: principal point ({cx:g}, {cy:g}) lies outside the {w:g}x{h:g} image; "
                f"give intrinsics calibrated at {w:g}x{h:g}"
            )
        return cls(fx, fy, cx, cy, int(w), int(h))

    @classmethod
    def from_K(cls, K: Any, width: int, height: int, source: str = "camera") -> Intrinsics:  # noqa: N802
        """Build and validate from a 3x3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (zero skew)."""
        try:
            K = np.asarray(K, dtype=np.float64)
        except (TypeError, ValueError):
            raise Monose3Error(f"{source} must be a 3x3 camera matrix of numbers, got {K!r}") from None
        if K.shape != (3, 3):
            raise Monose3Error(
                f"{source} must be a 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.shape}"
            )
        if not np.isfinite(K).all():
            raise Monose3Error(f"{source} contains NaN or infinity; give finite intrinsics in pixels")
        if not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 1e-9:
            raise Monose3Error(
                f"{source} must have the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; got rows {K.tolist()}"
            )
        if abs(K[0, 1]) > 1e-6 * max(abs(K[0, 0]), 1.0):
            raise Monose3Error(f"{source}: camera matrix has non-zero skew {K[0, 1]:g}; give a zero-skew calibration")
        return cls.checked(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, source)


def scale_camera(camera: Intrinsics, width: int, height: int) -> Intrinsics:
    """The same camera resized to ``width`` x ``height`` (pixel-centre convention).

    Only valid when the image was *resized* (not cropped) from the calibrated resolution,
    which is why it is never applied implicitly.
    """
    if not (int(width) == width and int(height) == height and width > 0 and height > 0):
        raise Monose3Error(f"scale_camera: width/height must be positive whole pixels, got {width}x{height}")
    K = scale_K(camera.K, camera.size, (int(width), int(height)))
    return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height))


def scale_K(K: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:  # noqa: N802
    """K of an image of ``size`` (w, h) resized to ``new_size``: pixel centres map as (u + 0.5) s - 0.5."""
    (w, h), (new_w, new_h) = size, new_size
    out = np.asarray(K, np.float64).copy()
    out[0, 0], out[1, 1] = K[0, 0] * (new_w / w), K[1, 1] * (new_h / h)
    out[0, 2], out[1, 2] = (K[0, 2] + 0.5) * new_w / w - 0.5, (K[1, 2] + 0.5) * new_h / h - 0.5
    return out


def project(points, K):
    """Pinhole projection of camera-frame points ``[..., N, 3]`` with K ``[..., 3, 3]`` to
    pixels ``[..., N, 2]`` (numpy or torch); depths are clamped to ``PROJECTION_EPS_DEPTH``."""
    xp = array_module(points)
    z = xp.clip(points[..., 2:3], PROJECTION_EPS_DEPTH, None)
    focal = xp.stack([K[..., 0, 0], K[..., 1, 1]], -1)[..., None, :]
    return points[..., :2] / z * focal + K[..., None, :2, 2]


def inside_image(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Whether each pixel position ``uv`` ``[..., 2]`` (pixel centres at integers) lies in an
    image of ``size`` (w, h), the border pixels' outer edges included."""
    return (uv >= -0.5).all(-1) & (uv <= np.asarray(size, float) - 0.5).all(-1)


def projection_jacobian(points, K):
    """d(pixel)/d(point) ``[..., N, 2, 3]`` of :func:`project` at camera-frame points ``[..., N, 3]``
    with K ``[..., 3, 3]`` (torch); depths clamped as :func:`project` clamps them."""
    import torch

    x, y = points[..., 0], points[..., 1]
    z = points[..., 2].clamp_min(PROJECTION_EPS_DEPTH)
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    zero = torch.zeros_like(z)
    rows = [fx / z, zero, -fx * x / z**2, zero, fy / z, -fy * y / z**2]
    return torch.stack(rows, -1).reshape(*z.shape, 2, 3)


def crop_boxes(uv_points, uv_center, aspect: float):
    """RoboPose's crop rule: ``[B, 4]`` boxes (x1, y1, x2, y2, edge coordinates), torch.

    Centred on the reference point's projection ``uv_center`` ``[B, 2]``; half-size from the
    largest distance to the projected points' box edges, grown to ``aspect`` (w/h) and by
    1.4. Not clamped to the image: roi_align pads with zeros, as the render does.
    """
    xp = array_module(uv_points)
    lo, hi = uv_points.min(1).values, uv_points.max(1).values
    dist = xp.maximum((uv_center - lo).abs(), (hi - uv_center).abs())
    xdist, ydist = dist[:, 0], dist[:, 1]
    width = xp.maximum(xdist, ydist * aspect) * 2 * CROP_MARGIN
    height = xp.maximum(xdist / aspect, ydist) * 2 * CROP_MARGIN
    cx, cy = uv_center[:, 0] + 0.5, uv_center[:, 1] + 0.5
    return xp.stack([cx - width / 2, cy - height / 2, cx + width / 2, cy + height / 2], 1)


def crop_intrinsics(K, boxes, out_size: tuple[int, int]):
    """Intrinsics ``[B, 3, 3]`` of each crop resized to ``out_size`` (w, h): a point projects to
    the same crop pixel through these as through K followed by the crop (:func:`crop_images`)."""
    out_w, out_h = out_size
    sx = (boxes[:, 2] - boxes[:, 0]) / out_w
    sy = (boxes[:, 3] - boxes[:, 1]) / out_h
    Kc = K.clone()
    Kc[:, 0, 0] = K[:, 0, 0] / sx
    Kc[:, 1, 1] = K[:, 1, 1] / sy
    Kc[:, 0, 2] = (K[:, 0, 2] - boxes[:, 0] + 0.5) / sx - 0.5
    Kc[:, 1, 2] = (K[:, 1, 2] - boxes[:, 1] + 0.5) / sy - 0.5
    return Kc


def crop_images(images, boxes, out_size: tuple[int, int]):
    """Bilinear crops ``[B, C, h, w]`` of ``[B, C, H, W]`` float tensors (one box per image).

    ``sampling_ratio=2`` averages 2x2 samples per output pixel, which anti-aliases strong
    down-scaling without moving the pixel centres.
    """
    import torch
    from torchvision.ops import roi_align

    out_w, out_h = out_size
    rois = torch.cat([torch.arange(len(boxes), dtype=boxes.dtype, device=boxes.device)[:, None], boxes], 1)
    return roi_align(images, rois.to(images.dtype), (out_h, out_w), 1.0, sampling_ratio=2, aligned=True)


def padded_size(image_size: tuple[int, int], size: tuple[int, int]) -> tuple[int, int]:
    """(w, h) of an ``image_size`` image zero-padded (right/bottom) to the aspect of ``size``, as
    :func:`standardize_image` pads it before resizing to ``size``."""
    (w, h), target = image_size, size[0] / size[1]
    return max(w, int(round(h * target))), max(h, int(round(w / target)))


def standardized_K(K: np.ndarray, image_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """K of an ``image_size`` image after :func:`standardize_image` to ``size``."""
    return scale_K(K, padded_size(image_size, size), size)


def standardize_image(image: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bring an image to ``size`` (w, h): zero-pad to its aspect (right/bottom), then resize.

    Returns the new image and its intrinsics; padding keeps every pixel of the input.
    """
    h, w = image.shape[:2]
    out_w, out_h = size
    pad_w, pad_h = padded_size((w, h), size)
    if (pad_w, pad_h) != (w, h):
        canvas = np.zeros((pad_h, pad_w, *image.shape[2:]), image.dtype)
        canvas[:h, :w] = image
        image = canvas
    scale = out_w / pad_w
    if (pad_w, pad_h) != (out_w, out_h):
        image = cv2.resize(image, (out_w, out_h), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    return image, standardized_K(K, (w, h), size)
