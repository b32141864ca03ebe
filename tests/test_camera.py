"""Camera geometry: projection, RoboPose's crop rule, crop intrinsics against real crop pixels,
image standardisation and intrinsics checks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from monose3.geometry.camera import (
    CROP_MARGIN,
    crop_boxes,
    crop_images,
    crop_intrinsics,
    inside_image,
    intrinsics_matrix,
    project,
    standardize_image,
)
from monose3.robot.jobs import RenderJob

CROP = (320, 240)


def _blob_image(w: int, h: int, centres: np.ndarray, sigma: float = 2.5) -> np.ndarray:
    """Gaussian blobs at sub-pixel (pixel-centre convention) positions."""
    ys, xs = np.mgrid[:h, :w].astype(np.float64)
    img = np.zeros((h, w))
    for u, v in centres:
        img += np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * sigma**2))
    return img


def _peak(img: np.ndarray, near: np.ndarray, radius: int = 12) -> np.ndarray:
    """Intensity-weighted centre of the blob around ``near`` (u, v)."""
    h, w = img.shape
    u0, v0 = np.round(near).astype(int)
    x0, x1 = max(u0 - radius, 0), min(u0 + radius + 1, w)
    y0, y1 = max(v0 - radius, 0), min(v0 + radius + 1, h)
    patch = img[y0:y1, x0:x1]
    ys, xs = np.mgrid[y0:y1, x0:x1]
    return np.array([(patch * xs).sum() / patch.sum(), (patch * ys).sum() / patch.sum()])


def _mask_centroid(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()])


# ---- projection -----------------------------------------------------------------------------


def test_project_matches_opencv():
    rng = np.random.default_rng(20)
    pts = np.c_[rng.uniform(-1, 1, (2, 30, 2)), rng.uniform(0.3, 4, (2, 30, 1))]
    Ks = np.stack([intrinsics_matrix(600, 610, 320.5, 240.2), intrinsics_matrix(300, 290, 100.0, 130.0)])
    uv = project(torch.as_tensor(pts), torch.as_tensor(Ks)).numpy()
    assert uv.shape == (2, 30, 2)
    for b in range(2):
        ref, _ = cv2.projectPoints(pts[b], np.zeros(3), np.zeros(3), Ks[b], None)
        np.testing.assert_allclose(uv[b], ref[:, 0], atol=1e-9)


# ---- crop rule ------------------------------------------------------------------------------


def _robopose_box(uv: np.ndarray, centre: np.ndarray, r: float) -> np.ndarray:
    """REFERENCE.md's statement of RoboPose's rule, written out independently (pixel centres)."""
    lo, hi = uv.min(0), uv.max(0)
    xdist = max(abs(centre[0] - lo[0]), abs(hi[0] - centre[0]))
    ydist = max(abs(centre[1] - lo[1]), abs(hi[1] - centre[1]))
    w = max(xdist, ydist * r) * 2 * 1.4
    h = max(xdist / r, ydist) * 2 * 1.4
    # pixel-centre coordinate c is edge coordinate c + 0.5
    return np.array(
        [centre[0] + 0.5 - w / 2, centre[1] + 0.5 - h / 2, centre[0] + 0.5 + w / 2, centre[1] + 0.5 + h / 2]
    )


def test_crop_boxes_follow_robopose_rule():
    rng = np.random.default_rng(21)
    uv = rng.uniform(0, 1, (6, 2000, 2)) * rng.uniform(50, 400, (6, 1, 2)) + rng.uniform(-100, 400, (6, 1, 2))
    centre = uv.mean(1) + rng.normal(scale=20, size=(6, 2))  # off the points' box centre
    aspect = 640 / 480
    boxes = crop_boxes(torch.as_tensor(uv), torch.as_tensor(centre), aspect).numpy()
    assert boxes.shape == (6, 4)
    assert CROP_MARGIN == 1.4
    for b in range(6):
        np.testing.assert_allclose(boxes[b], _robopose_box(uv[b], centre[b], aspect), atol=1e-9)
        w, h = boxes[b, 2] - boxes[b, 0], boxes[b, 3] - boxes[b, 1]
        assert w / h == pytest.approx(aspect)
        # centred on the reference point's projection (edge coords = pixel centre + 0.5)
        np.testing.assert_allclose((boxes[b, :2] + boxes[b, 2:]) / 2 - 0.5, centre[b], atol=1e-9)
        # every point inside, with the 1.4 margin on the limiting side
        assert np.all(uv[b] + 0.5 > boxes[b, :2]) and np.all(uv[b] + 0.5 < boxes[b, 2:])
        half = np.abs(uv[b] - centre[b]).max(0)
        assert max(w / 2 / half[0], h / 2 / half[1]) >= 1.4 - 1e-9
        assert min(w / 2 / half[0], h / 2 / half[1]) == pytest.approx(1.4)


def test_crop_boxes_not_clamped_to_image():
    uv = torch.tensor([[[-50.0, -30.0], [700.0, 500.0]]])
    box = crop_boxes(uv, torch.tensor([[0.0, 0.0]]), 4 / 3)[0]
    assert box[0] < -50 and box[1] < -30 and box[2] > 700 and box[3] > 500


# ---- crop intrinsics ---------------------------------------------------------------------------------


def _random_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    cx, cy = rng.uniform(100, 540, n), rng.uniform(80, 400, n)
    w = rng.uniform(120, 900, n)  # crop scale from ~2.7x up to ~0.36x down
    h = w * 3 / 4
    return np.c_[cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]


def test_crop_intrinsics_is_the_crop_affine_map():
    rng = np.random.default_rng(22)
    n = 8
    K = np.stack([intrinsics_matrix(*rng.uniform(400, 700, 2), *rng.uniform([280, 200], [360, 280])) for _ in range(n)])
    boxes = _random_boxes(rng, n)
    boxes[:, 3] = boxes[:, 1] + (boxes[:, 2] - boxes[:, 0]) * rng.uniform(0.6, 0.9, n)  # any aspect
    pts = np.c_[rng.uniform(-0.5, 0.5, (n, 40, 2)), rng.uniform(0.5, 3, (n, 40, 1))]
    Kc = crop_intrinsics(torch.as_tensor(K), torch.as_tensor(boxes), CROP).numpy()
    uv = project(torch.as_tensor(pts), torch.as_tensor(K)).numpy()
    uv_crop = project(torch.as_tensor(pts), torch.as_tensor(Kc)).numpy()
    # pixel centre u -> edge u + 0.5 -> crop edge (u + 0.5 - x1) * 320 / w -> crop pixel centre - 0.5
    scale = np.array(CROP) / (boxes[:, 2:] - boxes[:, :2])
    expected = (uv + 0.5 - boxes[:, None, :2]) * scale[:, None] - 0.5
    np.testing.assert_allclose(uv_crop, expected, atol=1e-9)
    assert Kc[0, 0, 1] == 0 and Kc[0, 2, 2] == 1


def test_crop_images_pixels_agree_with_crop_intrinsics():
    """Blobs painted at projected points are found, in the roi_align crop, at the projection
    through the crop intrinsics: the crop and its intrinsics share one pixel convention."""
    rng = np.random.default_rng(23)
    W, H = 640, 480
    K = intrinsics_matrix(520.0, 515.0, 331.3, 236.8)
    n = 6
    boxes = _random_boxes(rng, n)
    worst, found_blobs = 0.0, 0
    imgs, uvs, pts_all = [], [], []
    for b in range(n):
        # points whose projections fall well inside both the image and the crop box
        # a 2x2 grid of well separated blobs in the box, jittered, kept where inside the image
        grid = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]) + rng.uniform(-0.08, 0.08, (4, 2))
        uv_target = grid * (boxes[b, 2:] - boxes[b, :2]) + boxes[b, :2]
        uv_target = uv_target[np.all((uv_target > 20) & (uv_target < [W - 21, H - 21]), axis=1)]
        z = rng.uniform(0.8, 2.5, (len(uv_target), 1))
        pts = np.c_[(uv_target - K[:2, 2]) / [K[0, 0], K[1, 1]] * z, z]
        uv = project(torch.as_tensor(pts[None]), torch.as_tensor(K[None])).numpy()[0]
        imgs.append(_blob_image(W, H, uv, sigma=4.0))
        uvs.append(uv)
        pts_all.append(pts)
    images = torch.as_tensor(np.stack(imgs)[:, None], dtype=torch.float32)
    crops = crop_images(images, torch.as_tensor(boxes), CROP).numpy()[:, 0]
    assert crops.shape == (n, 240, 320)
    Kc = crop_intrinsics(torch.as_tensor(np.repeat(K[None], n, 0)), torch.as_tensor(boxes), CROP).numpy()
    for b in range(n):
        uv_c = project(torch.as_tensor(pts_all[b][None]), torch.as_tensor(Kc[b : b + 1])).numpy()[0]
        scale = 320 / (boxes[b, 2] - boxes[b, 0])
        for p in uv_c:
            if not (15 < p[0] < 305 and 15 < p[1] < 225):
                continue
            found = _peak(crops[b], p, radius=int(np.ceil(4.0 * 4 * scale)) + 2)
            worst = max(worst, float(np.abs(found - p).max()))
            found_blobs += 1
    assert found_blobs >= 10
    assert worst < 0.25, f"blob found {worst:.3f} px from the crop-intrinsics projection"


def test_crop_images_pads_outside_with_zeros():
    img = torch.ones(1, 1, 48, 64)
    box = torch.tensor([[-32.0, 0.0, 32.0, 48.0]])  # left half outside the image
    crop = crop_images(img, box, (64, 48))[0, 0]
    assert crop[:, :30].abs().max() < 1e-6
    assert torch.allclose(crop[:, 34:], torch.ones(48, 30))


def test_crop_of_full_render_matches_render_with_crop_intrinsics(models, renderers, sample_view):
    """RoboPose's loop: crop the 640x480 image around the robot, and render directly with the crop
    intrinsics at 320x240: the two masks coincide."""
    model, renderer = models["panda"], renderers["panda"]
    rng = np.random.default_rng(24)
    checked = 0
    for _ in range(4):
        view = sample_view(model, rng, size=(640, 480), dist=(1.2, 2.5))
        _, full = renderer.render_jobs([RenderJob(view.joints, view.pose, view.K, view.size)])[0]
        uv = view.uv()
        centre = view.uv(model.centroid(view.points)[None])
        box = crop_boxes(torch.as_tensor(uv[None]), torch.as_tensor(centre), 640 / 480)
        Kc = crop_intrinsics(torch.as_tensor(view.K[None]), box, CROP)[0].numpy()
        crop = crop_images(torch.as_tensor(full[None, None], dtype=torch.float32), box, CROP)[0, 0].numpy()
        _, direct = renderer.render_jobs([RenderJob(view.joints, view.pose, Kc, CROP)])[0]
        cropped = crop > 0.5
        if not direct.any():
            continue
        iou = (cropped & direct).sum() / (cropped | direct).sum()
        assert iou > 0.9, f"IoU {iou:.3f}"
        # aligned, not just overlapping: centroids agree to a fraction of a (downscaled) pixel
        scale = 320 / float(box[0, 2] - box[0, 0])
        tol = 0.15 + 0.5 * min(scale, 1.0)
        assert np.abs(_mask_centroid(cropped) - _mask_centroid(direct)).max() < tol
        checked += 1
    assert checked >= 3


# ---- standardize_image ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("size", "K"),
    [
        ((1280, 720), intrinsics_matrix(910.0, 905.0, 641.2, 362.7)),  # 16:9: pad bottom, then halve
        ((640, 360), intrinsics_matrix(455.0, 455.0, 320.4, 180.1)),  # 16:9 at target width: pad only
        ((480, 640), intrinsics_matrix(600.0, 600.0, 240.0, 320.0)),  # portrait: pad right, then shrink
        ((320, 240), intrinsics_matrix(300.0, 302.0, 158.3, 121.9)),  # 4:3, upscale only
        ((640, 480), intrinsics_matrix(615.5, 615.2, 328.3, 251.8)),  # already standard: unchanged
    ],
)
def test_standardize_image_keeps_content_aligned(size, K):
    w, h = size
    rng = np.random.default_rng(25)
    grid = np.stack(np.meshgrid([0.15, 0.5, 0.85], [0.2, 0.8]), -1).reshape(-1, 2) + rng.uniform(-0.05, 0.05, (6, 2))
    uv_target = grid * [w, h]
    z = rng.uniform(1, 2, (6, 1))
    pts = np.c_[(uv_target - K[:2, 2]) / [K[0, 0], K[1, 1]] * z, z]
    uv = pts[:, :2] / pts[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    sigma = 0.012 * w
    image = (_blob_image(w, h, uv, sigma) * 200).astype(np.float32)
    image3 = np.repeat(image[..., None], 3, axis=2)
    out, Ks = standardize_image(image3, K, (640, 480))
    assert out.shape == (480, 640, 3) and out.dtype == image3.dtype
    np.testing.assert_allclose(Ks[2], [0, 0, 1])
    # same aspect for both axes' pixel scale (no distortion from padding)
    assert Ks[0, 0] / K[0, 0] == pytest.approx(Ks[1, 1] / K[1, 1], rel=2e-3)
    uv_new = pts[:, :2] / pts[:, 2:] * [Ks[0, 0], Ks[1, 1]] + Ks[:2, 2]
    scale = Ks[0, 0] / K[0, 0]
    radius = int(np.ceil(4 * sigma * scale)) + 2
    for p in uv_new:
        found = _peak(out[..., 1].astype(np.float64), p, radius)
        assert np.abs(found - p).max() < 0.2, (found, p)
    # padding is black, content is kept (total intensity scales with the area)
    content_w, content_h = w * scale, h * Ks[1, 1] / K[1, 1]
    if content_h < 479:
        assert out[int(np.ceil(content_h)) + 1 :].max() == 0
    if content_w < 639:
        assert out[:, int(np.ceil(content_w)) + 1 :].max() == 0
    assert out.sum() == pytest.approx(image3.sum() * scale**2, rel=0.02)
    if size == (640, 480):
        np.testing.assert_array_equal(out, image3)
        np.testing.assert_allclose(Ks, K)


def test_standardize_image_grayscale_and_uint8():
    img = np.full((360, 640), 255, np.uint8)
    out, _ = standardize_image(img, intrinsics_matrix(500, 500, 320, 180), (640, 480))
    assert out.shape == (480, 640) and out.dtype == np.uint8
    assert out[:360].min() == 255 and out[360:].max() == 0


def test_projection_jacobian_matches_finite_differences():
    import torch

    from monose3.geometry.camera import project, projection_jacobian

    gen = torch.Generator().manual_seed(0)
    points = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, 1.5])
    K = torch.tensor([[[300.0, 0, 160], [0, 310, 120], [0, 0, 1]]], dtype=torch.float64).expand(2, 3, 3)
    jac = projection_jacobian(points, K)
    assert jac.shape == (2, 5, 2, 3)
    for axis in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = 1e-6
        numeric = (project(points + step, K) - project(points - step, K)) / 2e-6
        assert torch.allclose(jac[..., axis], numeric, atol=1e-4)


def test_inside_image_includes_the_border_pixels_outer_edges():
    uv = np.array([[-0.5, -0.5], [639.5, 479.5], [-0.51, 10.0], [10.0, 479.51], [320.0, 240.0]])
    assert inside_image(uv, (640, 480)).tolist() == [True, True, False, False, True]
