"""Silhouettes: the IoU of rendered poses with the parser's mask, and the outline
correspondences (a symmetric chamfer) the refinement pulls the render along."""

from __future__ import annotations

from functools import cached_property

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from monose3.geometry.camera import scale_K
from monose3.perception.views import MASK_THRESHOLD, Region, ViewEvidence
from monose3.robot.renderer import RenderOutput, RobotRenderer

OUTLINE_POINTS = 300  # render outline pixels used per iteration
# The silhouette terms' total weights in the solve (each keypoint weighs its confidence, <= 1):
# the silhouette decides, the keypoints break its ties (benchmarks/accuracy.py; 3.5 each: held-out
# AUC 82 / 44 on 30 reallike / hard frames, 25 each: 88 / 48).
RENDER_TO_MASK = 25.0
MASK_TO_RENDER = 25.0
OUTLINE_SCALE = 0.015  # Cauchy scale of outline residuals, fraction of the view's width


def render_silhouettes(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                       size: tuple[int, int]) -> torch.Tensor:  # fmt: skip
    """The silhouettes ``[H, h, w]`` (bool) of ``poses`` in ``view``, rendered at ``size`` (one batch)."""
    n = len(poses)
    K = torch.from_numpy(scale_K(view.K, view.size, size))[None].expand(n, 3, 3)
    return renderer.silhouettes(np.repeat(joints[None], n, 0), torch.from_numpy(poses), K, size)


def render_in_view(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence) -> RenderOutput:
    """``poses`` ``[H, 4, 4]`` rendered unshaded in ``view`` at its size (one batch): the masks
    :func:`render_silhouettes` gives, with depth and face ids."""
    n = len(poses)
    K = torch.from_numpy(view.K)[None].expand(n, 3, 3)
    return renderer.render(np.repeat(joints[None], n, 0), torch.from_numpy(poses), K, view.size, shade=False)


def mask_ious(silhouettes: torch.Tensor, view: ViewEvidence) -> np.ndarray:
    """IoU ``[H]`` of each silhouette ``[H, h, w]`` with the view's mask, brought to their size,
    inside the image (:meth:`ViewEvidence.valid_region`: a robot the image cuts is compared where it is seen)."""
    size = silhouettes.shape[-2:]
    mask = F.interpolate(view.mask[None, None], size=tuple(size), mode="bilinear", align_corners=False)[0, 0]
    x0, y0, x1, y1 = view.valid_region((size[1], size[0]))
    silhouettes = silhouettes[:, y0:y1, x0:x1]
    mask = (mask[y0:y1, x0:x1] > MASK_THRESHOLD).to(silhouettes.device)
    inter = (silhouettes & mask).flatten(1).sum(1).float()
    union = (silhouettes | mask).flatten(1).sum(1).float().clamp_min(1)
    return (inter / union).cpu().numpy()


def silhouette_ious(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                    size: tuple[int, int]) -> np.ndarray:  # fmt: skip
    """IoU ``[H]`` of each pose's rendered silhouette with the view's mask, compared at ``size``."""
    return mask_ious(render_silhouettes(renderer, joints, poses, view, size), view)


class Outline:
    """The outline pixels of a binary mask ``[h, w]`` and, for every pixel, the nearest of them.
    With ``valid`` (x0, y0, x1, y1: the view's pixels inside the image), only the outline inside
    it: where the image's border cuts the mask there is no outline of the robot."""

    def __init__(self, mask: np.ndarray, valid: Region | None = None):
        x0, y0, x1, y1 = valid or (0, 0, mask.shape[1], mask.shape[0])
        inner = np.ascontiguousarray(mask[y0:y1, x0:x1], np.uint8)
        self._outline = np.zeros(mask.shape, np.uint8)
        # erode's default border leaves the mask's pixels on the region's border uneroded: no outline there
        self._outline[y0:y1, x0:x1] = inner - cv2.erode(inner, np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero(self._outline)  # raster order, as distanceTransformWithLabels numbers them
        self.pixels = np.stack([xs, ys], -1).astype(np.float64)

    def __len__(self) -> int:
        return len(self.pixels)

    @cached_property
    def _nearest(self) -> np.ndarray:
        """For every pixel, the index of the nearest outline pixel: a distance transform, made on
        first use (the edges need only the outline's pixels)."""
        _, labels = cv2.distanceTransformWithLabels(1 - self._outline, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        return labels - 1

    def nearest(self, uv: np.ndarray) -> np.ndarray:
        """Index ``[N]`` of the outline pixel nearest to each of ``uv`` ``[N, 2]`` (the outline is not empty)."""
        u = np.clip(np.round(uv[:, 0]).astype(int), 0, self._nearest.shape[1] - 1)
        v = np.clip(np.round(uv[:, 1]).astype(int), 0, self._nearest.shape[0] - 1)
        return self._nearest[v, u]


def outline_surface_points(pixels: np.ndarray, depth: np.ndarray, pose: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The surface points ``[N, 3]`` (base frame) that a render at ``pose`` shows at its outline
    ``pixels`` ``[N, 2]``: each pixel back-projected through the render's ``depth``, then R^T (X - t)."""
    xs, ys = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    z = depth[ys, xs].astype(np.float64)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], -1)
    return (cam - pose[:3, 3]) @ pose[:3, :3]


def _subsample(n: int, rng: np.random.Generator) -> np.ndarray:
    return rng.choice(n, OUTLINE_POINTS, replace=False) if n > OUTLINE_POINTS else np.arange(n)


def outline_terms(target: Outline, render_mask: np.ndarray, depth: np.ndarray, pose: np.ndarray, K: np.ndarray,
                  scale: float, rng: np.random.Generator,
                  valid: Region | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The silhouette's residual terms for one pose: (surface points in the base frame ``[N, 3]``,
    the pixels they should project to ``[N, 2]``, weights ``[N]``), a symmetric chamfer between
    the render's outline and the mask's. Each render outline pixel is pulled to the nearest mask
    outline pixel (weight :data:`RENDER_TO_MASK`: an occluder cuts the mask, not the render, so
    this direction is the less trustworthy one), and each mask outline pixel pulls the nearest
    render outline pixel (:data:`MASK_TO_RENDER`). Cauchy weights of scale ``scale`` pixels.
    The render's outline is taken inside ``valid`` only, as the ``target``'s should be."""
    rendered = Outline(render_mask, valid)
    if not len(rendered) or not len(target):
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    base = outline_surface_points(rendered.pixels, depth, pose, K)
    fwd = _subsample(len(rendered), rng)
    fwd_goal = target.pixels[target.nearest(rendered.pixels[fwd])]
    rev_goal = target.pixels[_subsample(len(target), rng)]
    rev = rendered.nearest(rev_goal)
    points = np.concatenate([base[fwd], base[rev]])
    goals = np.concatenate([fwd_goal, rev_goal])
    dist = np.linalg.norm(goals - np.concatenate([rendered.pixels[fwd], rendered.pixels[rev]]), axis=-1)
    share = np.concatenate([np.full(len(fwd), RENDER_TO_MASK / len(fwd)), np.full(len(rev), MASK_TO_RENDER / len(rev))])
    return points, goals, share / (1 + (dist / scale) ** 2)
