"""Pictures people judge a calibration by: overlays, denoising strips, ADD curves, animations.

A pose estimate is easiest to trust (or reject) by eye: the outline of the robot rendered
at the estimated pose drawn over the camera image shows an error of a few millimetres at
once. Everything here works on RGB uint8 arrays and writes files with parent folders
created; plots use matplotlib's Agg canvas so no display is ever needed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import imageio.v3 as iio
import numpy as np

from monose3.atomic import atomic_path
from monose3.errors import Monose3Error
from monose3.geometry.camera import project
from monose3.robot.jobs import RenderJob

if TYPE_CHECKING:  # the renderer imports torch; drawing does not need it
    from monose3.robot.renderer import RobotRenderer

Color = tuple[int, int, int]
FILL_ALPHA = 0.3
GT_COLOR: Color = (255, 0, 0)


def _as_rgb(image: np.ndarray, what: str = "image") -> np.ndarray:
    """A contiguous ``H x W x 3`` uint8 copy; grey and RGBA are converted, bool becomes 0/255."""
    img = np.asarray(image)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.dtype != np.uint8:
        raise Monose3Error(f"{what} must be uint8 RGB (0-255), got dtype {img.dtype}; convert it first")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    elif img.ndim == 3 and img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise Monose3Error(f"{what} must be an H x W x 3 RGB array, got shape {np.shape(image)}")
    return np.ascontiguousarray(img).copy()


def _line_width(shape: tuple[int, ...]) -> int:
    return max(1, round(min(shape[0], shape[1]) / 240))


def _draw_text(img: np.ndarray, text: str) -> None:
    """Text in the top-left corner on a dark box so it reads on any background."""
    scale = max(0.4, min(img.shape[0], img.shape[1]) / 480 * 0.6)
    thick = max(1, round(scale * 1.5))
    font = cv2.FONT_HERSHEY_SIMPLEX
    y = 4
    for line in text.splitlines() or [""]:
        (tw, th), base = cv2.getTextSize(line, font, scale, thick)
        cv2.rectangle(img, (0, y - 2), (tw + 8, y + th + base + 2), (0, 0, 0), -1)
        cv2.putText(img, line, (4, y + th), font, scale, (255, 255, 255), thick, cv2.LINE_AA)
        y += th + base + 6


def _text_scale(img: np.ndarray) -> tuple[float, int]:
    scale = max(0.35, min(img.shape[0], img.shape[1]) / 480 * 0.5)
    return scale, max(1, round(scale * 1.5))


def _draw_legend(img: np.ndarray, entries: Sequence[tuple[str, Color, str]]) -> None:
    """A key in the bottom-left corner: one row per ``(marker, colour, label)``, marker 'dot'
    (a filled circle) or 'cross', on a dark box so it reads on any background."""
    scale, thick = _text_scale(img)
    font = cv2.FONT_HERSHEY_SIMPLEX
    sizes = [cv2.getTextSize(label, font, scale, thick) for _, _, label in entries]
    row = max(th + base for (_, th), base in sizes) + 4
    swatch = row
    width = max(tw for (tw, _), _ in sizes) + swatch + 10
    top = img.shape[0] - row * len(entries) - 4
    cv2.rectangle(img, (0, top), (width, img.shape[0]), (0, 0, 0), -1)
    for i, ((marker, color, label), ((_, th), _)) in enumerate(zip(entries, sizes, strict=True)):
        y = top + 2 + i * row
        centre = (4 + swatch // 2, y + row // 2)
        if marker == "cross":
            cv2.drawMarker(img, centre, color, cv2.MARKER_CROSS, max(5, swatch - 4), thick, cv2.LINE_AA)
        else:
            cv2.circle(img, centre, max(2, swatch // 3), color, -1, cv2.LINE_AA)
        cv2.putText(img, label, (8 + swatch, y + row // 2 + th // 2), font, scale, (255, 255, 255), thick, cv2.LINE_AA)


def _points(uv: np.ndarray | None, what: str) -> np.ndarray:
    if uv is None:
        return np.zeros((0, 2))
    arr = np.asarray(uv, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise Monose3Error(f"{what} must be an array of [K, 2] pixel coordinates (u, v), got shape {arr.shape}")
    return arr[np.all(np.isfinite(arr), axis=1) & np.all(np.abs(arr) < 1e6, axis=1)]


def draw_overlay(
    image: np.ndarray,
    mask: np.ndarray | None,
    keypoints_uv: np.ndarray | None = None,
    color: Color = (0, 255, 0),
    gt_keypoints_uv: np.ndarray | None = None,
    text: str | None = None,
    gt_color: Color = GT_COLOR,
    legend: bool = True,
) -> np.ndarray:
    """The robot mask's outline and a light translucent fill drawn over ``image``.

    Predicted keypoints are dots in ``color``, ground-truth keypoints crosses in ``gt_color``;
    ``text`` is written in the top-left corner and, with ``legend``, a key to the colours in
    the bottom-left one. Returns a new array; ``image`` is untouched.
    """
    out = _as_rgb(image)
    lw = _line_width(out.shape)
    col = np.array(color, dtype=np.float64)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != out.shape[:2]:
            raise Monose3Error(
                f"mask is {m.shape[1]}x{m.shape[0]} but the image is {out.shape[1]}x{out.shape[0]}; "
                "render the robot at the image's resolution and intrinsics"
            )
        m = m.astype(bool)
        out[m] = np.round(out[m] * (1.0 - FILL_ALPHA) + col * FILL_ALPHA).astype(np.uint8)
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, tuple(int(c) for c in color), lw, cv2.LINE_AA)
    radius = lw + 2
    for u, v in _points(gt_keypoints_uv, "gt_keypoints_uv"):
        cv2.drawMarker(
            out, (round(u), round(v)), tuple(int(c) for c in gt_color), cv2.MARKER_CROSS, 3 * radius, lw, cv2.LINE_AA
        )
    for u, v in _points(keypoints_uv, "keypoints_uv"):
        cv2.circle(out, (round(u), round(v)), radius, tuple(int(c) for c in color), -1, cv2.LINE_AA)
    if text:
        _draw_text(out, text)
    if legend:
        entries = []
        if mask is not None or keypoints_uv is not None:
            entries.append(("dot", tuple(int(c) for c in color), "estimate: outline, keypoints"))
        if gt_keypoints_uv is not None:
            entries.append(("cross", tuple(int(c) for c in gt_color), "ground-truth keypoints"))
        if entries:
            _draw_legend(out, entries)
    return out


# ---- files ----------------------------------------------------------------------------------


def save_image(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB image (PNG, JPEG, ... by extension) atomically, creating parent folders."""
    p = Path(path)
    img = _as_rgb(rgb)
    p.parent.mkdir(parents=True, exist_ok=True)
    ext = p.suffix.lower() or ".png"
    try:
        ok, buf = cv2.imencode(ext, cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    except cv2.error:
        ok = False
    if not ok:
        raise Monose3Error(f"cannot write an image with extension {p.suffix!r} ({p}); use .png or .jpg")
    with atomic_path(p) as tmp:
        buf.tofile(tmp)
    return p


def save_animation(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write frames as an animated GIF, or an MP4 (MPEG-4 part 2 via OpenCV) if ``path`` ends in .mp4.

    GIF needs nothing beyond imageio/Pillow; MP4 uses OpenCV's bundled FFmpeg so it does not
    depend on imageio-ffmpeg. All frames must have the same size.
    """
    p = Path(path)
    if len(frames) == 0:
        raise Monose3Error(f"no frames to write to {p}; pass at least one image")
    if not fps > 0:
        raise Monose3Error(f"fps must be positive, got {fps}")
    imgs = [_as_rgb(f, f"frame {i}") for i, f in enumerate(frames)]
    if any(f.shape != imgs[0].shape for f in imgs):
        sizes = sorted({f"{f.shape[1]}x{f.shape[0]}" for f in imgs})
        raise Monose3Error(f"animation frames differ in size ({', '.join(sizes)}); resize them to one size first")
    p.parent.mkdir(parents=True, exist_ok=True)
    ext = p.suffix.lower()
    if ext == ".gif":
        with atomic_path(p) as tmp:
            iio.imwrite(tmp, np.stack(imgs), extension=".gif", duration=1000.0 / fps, loop=0)
        return p
    if ext == ".mp4":
        h, w = imgs[0].shape[:2]
        with atomic_path(p) as tmp:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
            if not writer.isOpened():
                raise Monose3Error(f"this OpenCV build cannot write MP4 ({p}); save the animation as .gif instead")
            try:
                for f in imgs:
                    writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
            finally:
                writer.release()
        return p
    raise Monose3Error(f"unsupported animation format {p.suffix!r} ({p}); use .gif or .mp4")


# ---- composites -----------------------------------------------------------------------------


def image_grid(images: Sequence[np.ndarray], cols: int, pad: int = 0, background: int = 0) -> np.ndarray:
    """Tile images row-major into ``cols`` columns; smaller images are centred in their cell."""
    if len(images) == 0:
        raise Monose3Error("image_grid needs at least one image")
    if cols < 1:
        raise Monose3Error(f"image_grid: cols must be at least 1, got {cols}")
    imgs = [_as_rgb(im, f"image {i}") for i, im in enumerate(images)]
    cell_h = max(im.shape[0] for im in imgs)
    cell_w = max(im.shape[1] for im in imgs)
    cols = min(cols, len(imgs))
    rows = -(-len(imgs) // cols)
    grid = np.full((rows * cell_h + (rows - 1) * pad, cols * cell_w + (cols - 1) * pad, 3), background, dtype=np.uint8)
    for i, im in enumerate(imgs):
        r, c = divmod(i, cols)
        y = r * (cell_h + pad) + (cell_h - im.shape[0]) // 2
        x = c * (cell_w + pad) + (cell_w - im.shape[1]) // 2
        grid[y : y + im.shape[0], x : x + im.shape[1]] = im
    return grid


def _step_color(i: int, n: int) -> Color:
    """Orange for the first (noisiest) step fading to green for the last."""
    t = i / max(n - 1, 1)
    start, end = np.array([255, 140, 0]), np.array([0, 255, 0])
    return tuple(int(v) for v in np.round(start * (1 - t) + end * t))


def denoising_strip(
    image: np.ndarray, masks_per_step: Sequence[np.ndarray], labels: Sequence[str], path: str | Path | None
) -> np.ndarray:
    """One overlay per denoising step side by side (the paper's Fig. 3b), saved to ``path`` if given."""
    if len(masks_per_step) == 0:
        raise Monose3Error("denoising_strip needs at least one mask")
    if len(labels) != len(masks_per_step):
        raise Monose3Error(f"denoising_strip got {len(masks_per_step)} masks but {len(labels)} labels; give one each")
    n = len(masks_per_step)
    tiles = [
        draw_overlay(image, m, color=_step_color(i, n), text=str(lbl), legend=False)
        for i, (m, lbl) in enumerate(zip(masks_per_step, labels, strict=True))
    ]
    strip = image_grid(tiles, cols=n, pad=4, background=255)
    if path is not None:
        save_image(path, strip)
    return strip


def pose_overlays(
    renderer: RobotRenderer,
    images: Sequence[np.ndarray],
    Ks: Sequence[np.ndarray],
    joints: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    texts: Sequence[str | None] | None = None,
    gt_keypoints: Sequence[np.ndarray | None] | None = None,
    max_width: int | None = None,
) -> list[np.ndarray]:
    """The robot rendered at each camera-from-base pose drawn on its image (:func:`draw_overlay`:
    outline, fill, keypoints; camera-frame ground-truth keypoints ``[K, 3]`` as crosses when
    given), all rendered in one batch. ``max_width``: wider tiles are shrunk after drawing."""
    if len(images) == 0:
        return []
    joints = np.stack([np.asarray(q, np.float64) for q in joints])
    poses = np.stack([np.asarray(p, np.float64) for p in poses])
    Ks = [np.asarray(K, np.float64) for K in Ks]
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    jobs = [RenderJob(q, p, K, size) for q, p, K, size in zip(joints, poses, Ks, sizes, strict=True)]
    masks = [mask for _, mask in renderer.render_jobs(jobs)]
    keypoints = renderer.model.keypoints(joints, poses)  # [B, K, 3] in the camera frame
    out = []
    for i, (image, K, mask) in enumerate(zip(images, Ks, masks, strict=True)):
        gt = None if gt_keypoints is None or gt_keypoints[i] is None else _pixels(gt_keypoints[i], K)
        text = None if texts is None else texts[i]
        tile = draw_overlay(image, mask, _pixels(keypoints[i], K), gt_keypoints_uv=gt, text=text)
        if max_width is not None and tile.shape[1] > max_width:
            height = round(tile.shape[0] * max_width / tile.shape[1])
            tile = cv2.resize(tile, (max_width, height), interpolation=cv2.INTER_AREA)
        out.append(tile)
    return out


def _pixels(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel positions of camera-frame points; NaN (not drawn) for points behind the camera."""
    points_cam = np.asarray(points_cam, np.float64)
    uv = project(points_cam, K)
    uv[points_cam[:, 2] <= 0] = np.nan
    return uv
