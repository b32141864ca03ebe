"""Image edges: where, along its normal, each outline pixel of a render meets an edge of the
image itself.

Not in the paper. The parser's mask places the robot's outline to about a pixel, and for a
small, distant robot a pixel of outline is a percent of its size, so a percent of its depth
(30 mm at 3 m). The image's own edges are sharper where the robot stands out from the
background. This is the classic contour-tracking step (RAPID; Harris, 1992): from the pose the
mask fit converged to, each render outline pixel searches a few pixels along its normal for
the image's nearest strong colour change, and is pulled there. The mask keeps the fit in its
basin; the edges give it sub-pixel precision. Where the robot barely differs from the background,
the edges are weak and weigh little, and the mask decides.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from monose3.perception.silhouette import Outline, outline_surface_points
from monose3.perception.views import Region

EDGE_POINTS = 400  # render outline pixels searched per iteration
SEARCH_RADIUS = 3.0  # view pixels along the normal, each way
SEARCH_STEP = 1.0  # one pixel: differences of linearly interpolated samples are then the image's own
STRONG_EDGE = 0.15  # colour change (RGB in [0, 1]) over one pixel that counts as a full-weight edge
WEAK_EDGE = 0.04  # below this there is no edge to pull to
EDGE_SCALE = 1.5  # Cauchy scale of the pull, view pixels
NORMAL_SIGMA = 1.5  # pixels: the render's mask is smoothed this much before its gradient gives the normals


def outline_normals(mask: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Outward unit normals ``[N, 2]`` of the binary ``mask`` at its outline ``pixels`` ``[N, 2]``
    (zero where the smoothed mask has no gradient)."""
    soft = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), NORMAL_SIGMA)
    xs, ys = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    grad = np.stack([cv2.Sobel(soft, cv2.CV_32F, 1, 0)[ys, xs], cv2.Sobel(soft, cv2.CV_32F, 0, 1)[ys, xs]], -1)
    norm = np.linalg.norm(grad, axis=-1, keepdims=True)
    return np.where(norm > 1e-6, -grad / np.maximum(norm, 1e-6), 0.0)


def find_edges(image: np.ndarray, pixels: np.ndarray, normals: np.ndarray,
               valid: Region | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """For each pixel, the offset along its normal (view pixels, sub-pixel) of the edge of
    ``image`` ``[h, w, 3]`` (float32 in [0, 1]) that it crosses within :data:`SEARCH_RADIUS`
    (the local maximum of colour change that is strongest once weighed by nearness), and that
    change's size (0 where the search leaves ``valid``, x0, y0, x1, y1: by default the image)."""
    x0, y0, x1, y1 = valid or (0, 0, image.shape[1], image.shape[0])
    steps = np.arange(-SEARCH_RADIUS, SEARCH_RADIUS + SEARCH_STEP / 2, SEARCH_STEP)
    xs = (pixels[:, None, 0] + steps * normals[:, None, 0]).astype(np.float32)
    ys = (pixels[:, None, 1] + steps * normals[:, None, 1]).astype(np.float32)
    profiles = cv2.remap(image, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # [N, S, 3]
    inside = (xs >= x0) & (xs <= x1 - 1) & (ys >= y0) & (ys <= y1 - 1)
    change = np.linalg.norm(profiles[:, 1:] - profiles[:, :-1], axis=-1)  # between samples, at steps + STEP/2
    change[~(inside[:, 1:] & inside[:, :-1])] = 0.0
    # Of the profile's local maxima (the edges it crosses), the strongest once weighed by
    # nearness: an edge inside the robot, a little further, does not win over its outline.
    padded = np.pad(change, ((0, 0), (1, 1)))
    crossed = (change >= padded[:, :-2]) & (change >= padded[:, 2:])
    at = steps[:-1] + SEARCH_STEP / 2 - 0.5  # each change's offset from the render's silhouette edge
    rows, peak = np.arange(len(change)), (crossed * change / (1 + (at / EDGE_SCALE) ** 2)).argmax(1)
    inner = peak.clip(1, change.shape[1] - 2)
    left, mid, right = change[rows, inner - 1], change[rows, peak], change[rows, inner + 1]
    curve = left - 2 * mid + right
    # the vertex of the parabola through the peak and its neighbours (none at the search's ends)
    vertex = np.where((inner == peak) & (curve < -1e-9), 0.5 * (left - right) / np.minimum(curve, -1e-9), 0.0)
    return steps[peak] + SEARCH_STEP * (0.5 + vertex), mid


def _pull_weight(offset: np.ndarray, strength: np.ndarray, found: np.ndarray) -> np.ndarray:
    """How much a pull of ``offset`` pixels to an image edge of ``strength`` counts, in [0, 1]:
    the strength capped at :data:`STRONG_EDGE`, times a Cauchy of the distance; 0 where there
    is no weak edge or nothing was ``found``."""
    found = found & (strength >= WEAK_EDGE)
    return found * np.minimum(strength / STRONG_EDGE, 1.0) / (1 + (offset / EDGE_SCALE) ** 2)


def _edge_pulls(image: np.ndarray, render_mask: np.ndarray, pixels: np.ndarray,
                valid: Region | None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """For each of the render's outline ``pixels``: the pixel its silhouette edge should move to
    ``[N, 2]``, and how much that pull counts ``[N]`` in [0, 1] (the edge's strength, capped at
    :data:`STRONG_EDGE`, times a Cauchy of its distance; 0 where there is no edge)."""
    normals = outline_normals(render_mask, pixels)
    offset, strength = find_edges(image, pixels, normals, valid)
    # An outline pixel lies inside the silhouette, whose edge is half a pixel further out: that
    # edge, not the pixel's centre, goes to the image's edge.
    offset = offset - 0.5
    return pixels + offset[:, None] * normals, _pull_weight(offset, strength, normals.any(-1))


def edge_terms(image: np.ndarray, render_mask: np.ndarray, depth: np.ndarray, pose: np.ndarray, K: np.ndarray,
               weight: float, rng: np.random.Generator,
               valid: Region | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The edges' residual terms for one pose, as :func:`~monose3.perception.silhouette.outline_terms`
    gives the mask's: (surface points in the base frame ``[N, 3]``, the pixels they should project
    to ``[N, 2]``, weights ``[N]`` summing to at most ``weight``), for :data:`EDGE_POINTS` of the
    render's outline pixels inside ``valid`` (the view's pixels inside the image)."""
    rendered = Outline(render_mask, valid)
    if not len(rendered):
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    pixels = rendered.pixels[rng.choice(len(rendered), min(EDGE_POINTS, len(rendered)), replace=False)]
    goals, pull = _edge_pulls(image, render_mask, pixels, valid)
    return outline_surface_points(pixels, depth, pose, K), goals, weight * pull / len(pixels)


def edge_agreement(image: np.ndarray, render_mask: np.ndarray, valid: Region | None = None) -> tuple[float, float]:
    """How well the render's outline lies on the image's own edges, over all its outline pixels:
    (support, distance). Support in [0, 1] is the mean pull weight (1: every pixel on a strong
    edge within half a pixel or so); distance is the pulls' weighted RMS length in view pixels
    (inf: no edge along the outline). Independent of the parser, so a pose fitted to a wrong mask
    shows here (the ``reliable`` flag reads the distance). Only the outline inside ``valid``
    counts: the image's border is no edge of the robot."""
    rendered = Outline(render_mask, valid)
    if not len(rendered):
        return 0.0, math.inf
    goals, weight = _edge_pulls(image, render_mask, rendered.pixels, valid)
    if weight.sum() <= 0:
        return 0.0, math.inf
    squared = ((goals - rendered.pixels) ** 2).sum(-1)
    return float(weight.mean()), float(np.sqrt((weight * squared).sum() / weight.sum()))


INNER_POINTS = 300  # inner edge pixels of the render searched per iteration
INNER_COLOR_STEP = 0.08  # colour change per pixel (Sobel) of the unlit render that marks an inner edge
INNER_DEPTH_STEP = 0.02  # depth change per pixel (m) that marks one (a link in front of another)
INNER_DEPTH_SCALE = 10.0  # depth (m) to colour units when the render's own edges are located
_BOX_MARGIN = 6  # pixels around the silhouette's box: the searches along the normals stay inside


def inner_edges(colors: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges of a render inside its silhouette, at least two pixels from its outline: where
    its unlit ``colors`` change (a black joint on a white link) and where its ``depth`` steps (a
    link in front of another). Their pixels ``[N, 2]`` and unit normals ``[N, 2]``."""
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    gray, z = colors.mean(-1).astype(np.float32), depth.astype(np.float32)
    gx, gy = cv2.Sobel(gray, cv2.CV_32F, 1, 0) / 8, cv2.Sobel(gray, cv2.CV_32F, 0, 1) / 8
    zx, zy = cv2.Sobel(z, cv2.CV_32F, 1, 0) / 8, cv2.Sobel(z, cv2.CV_32F, 0, 1) / 8
    colour = np.hypot(gx, gy) > INNER_COLOR_STEP
    ys, xs = np.nonzero(inner & (colour | (np.hypot(zx, zy) > INNER_DEPTH_STEP)))
    by_colour = colour[ys, xs]
    normal = np.stack([np.where(by_colour, gx[ys, xs], zx[ys, xs]), np.where(by_colour, gy[ys, xs], zy[ys, xs])], -1)
    return np.stack([xs, ys], -1).astype(np.float64), normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def _inner_pulls(image: np.ndarray, colors: np.ndarray, depth: np.ndarray, mask: np.ndarray, valid: Region | None,
                 rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """For :data:`INNER_POINTS` of the render's inner edge pixels (:func:`inner_edges`, of the
    unlit ``colors`` ``[h, w, 3]``) drawn by ``rng``, or without one all of them: the pixels ``[N, 2]``, the
    pixels they should move to (by how far, along their normal, the image's edge lies from the
    render's own) and how much each pull counts (:func:`_pull_weight`, where the render shows
    an edge too)."""
    none = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return none
    x0, y0, x1, y1 = valid or (0, 0, mask.shape[1], mask.shape[0])
    lo = np.maximum([xs.min() - _BOX_MARGIN, ys.min() - _BOX_MARGIN], [x0, y0])
    hi = np.minimum([xs.max() + _BOX_MARGIN + 1, ys.max() + _BOX_MARGIN + 1], [x1, y1])
    if (hi - lo < 5).any():  # (next to) nothing of the render inside the image
        return none
    box = np.s_[lo[1] : hi[1], lo[0] : hi[0]]
    pixels, normals = inner_edges(colors[box], depth[box], mask[box])
    if not len(pixels):
        return none
    if rng is not None:
        pick = rng.choice(len(pixels), min(INNER_POINTS, len(pixels)), replace=False)
        pixels, normals = pixels[pick], normals[pick]
    own = np.concatenate([colors[box], INNER_DEPTH_SCALE * depth[box][..., None]], -1).astype(np.float32)
    at_render, own_strength = find_edges(own, pixels, normals)
    pixels = pixels + lo
    at_image, strength = find_edges(image, pixels, normals, valid)
    offset = at_image - at_render
    return pixels, pixels + offset[:, None] * normals, _pull_weight(offset, strength, own_strength >= WEAK_EDGE)


def inner_edge_terms(image: np.ndarray, colors: np.ndarray, depth: np.ndarray, mask: np.ndarray,
                     pose: np.ndarray, K: np.ndarray, weight: float, rng: np.random.Generator,
                     valid: Region | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Residual terms, as :func:`edge_terms` gives them, for :data:`INNER_POINTS` of the
    render's edges inside its silhouette (:func:`_inner_pulls`)."""
    pixels, goals, pull = _inner_pulls(image, colors, depth, mask, valid, rng)
    if not len(pixels):
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    return outline_surface_points(pixels, depth, pose, K), goals, weight * pull / len(pixels)


def inner_edge_support(image: np.ndarray, colors: np.ndarray, depth: np.ndarray, mask: np.ndarray,
                       valid: Region | None = None) -> float:  # fmt: skip
    """How well the render's edges inside its silhouette lie on the image's, in [0, 1]: the
    mean pull weight over all of them (:func:`_inner_pulls`; 0 where it has none), as
    :func:`edge_agreement`'s support is for the outline."""
    pull = _inner_pulls(image, colors, depth, mask, valid)[2]
    return float(pull.mean()) if len(pull) else 0.0
