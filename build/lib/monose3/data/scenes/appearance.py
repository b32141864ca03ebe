"""The pixels of a synthetic frame: backgrounds, distractor shapes, occluders, augmentation,
and the composite of a robot render over them (:func:`compose_frame`)."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from monose3.data.scenes.profiles import SceneProfile
from monose3.errors import Monose3Error

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp", ".webp")


def _random_color(rng: np.random.Generator, palette: np.ndarray | None = None, spread: float = 25.0) -> np.ndarray:
    if palette is not None and len(palette):
        base = palette[rng.integers(len(palette))]
        return np.clip(base + rng.normal(0.0, spread, 3), 0, 255)
    return rng.uniform(0, 255, 3)


def _grid(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    w, h = size
    return np.meshgrid(np.linspace(-1, 1, w, dtype=np.float32), np.linspace(-1, 1, h, dtype=np.float32) * (h / w))


def _smooth_noise(rng: np.random.Generator, size: tuple[int, int], channels: int = 3) -> np.ndarray:
    """Multi-octave value noise in [0, 1] (a cheap stand-in for Perlin noise)."""
    w, h = size
    out = np.zeros((h, w, channels), np.float32)
    amp, total = 1.0, 0.0
    for cells in (int(rng.integers(2, 5)), int(rng.integers(6, 16)), int(rng.integers(20, 60))):
        small = rng.random((max(2, cells * h // w), cells, channels), dtype=np.float32)
        up = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).reshape(h, w, channels)
        out += amp * up
        total += amp
        amp *= float(rng.uniform(0.3, 0.6))
    return np.clip(out / total, 0.0, 1.0)


def draw_shapes(
    rng: np.random.Generator, img: np.ndarray, count: int, palette: np.ndarray | None, scale: float = 1.0
) -> None:
    """Random filled polygons, ellipses, rectangles and thick lines, in place (uint8 image)."""
    h, w = img.shape[:2]
    for _ in range(count):
        color = tuple(float(c) for c in _random_color(rng, palette))
        kind = rng.integers(4)
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(0.03, 0.25) * max(w, h) * scale
        if kind == 0:
            n = int(rng.integers(3, 8))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = r * rng.uniform(0.4, 1.0, n)
            poly = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)
            cv2.fillPoly(img, [poly], color, lineType=cv2.LINE_AA)
        elif kind == 1:
            axes = (int(r), int(r * rng.uniform(0.3, 1.0)))
            cv2.ellipse(img, (int(cx), int(cy)), axes, float(rng.uniform(0, 180)), 0, 360, color, -1, cv2.LINE_AA)
        elif kind == 2:
            p1 = (int(cx - r), int(cy - r * rng.uniform(0.2, 1.0)))
            p2 = (int(cx + r), int(cy + r * rng.uniform(0.2, 1.0)))
            cv2.rectangle(img, p1, p2, color, -1)
        else:
            ang = rng.uniform(0, np.pi)
            d = np.array([np.cos(ang), np.sin(ang)]) * r * 2
            p1, p2 = (int(cx - d[0]), int(cy - d[1])), (int(cx + d[0]), int(cy + d[1]))
            cv2.line(img, p1, p2, color, max(1, int(rng.uniform(0.02, 0.15) * r)), cv2.LINE_AA)


class BackgroundSource:
    """Random backgrounds: colour fields, gradients, smooth noise, stripes/checkers, shapes,
    and (optionally) random crops of the user's images (a few decoded images are cached)."""

    def __init__(self, files: list[Path] | None = None, cache_size: int = 12):
        self.files = list(files or [])
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache_size = cache_size

    def _user_image(self, rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray | None:
        i = int(rng.integers(len(self.files)))
        img = self._cache.get(i)
        if img is None:
            bgr = cv2.imread(str(self.files[i]), cv2.IMREAD_COLOR)
            if bgr is None:
                return None
            img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            limit = 2 * max(size)
            if max(img.shape[:2]) > limit:  # keep the cache small; crops are downscaled anyway
                s = limit / max(img.shape[:2])
                img = cv2.resize(img, (int(img.shape[1] * s), int(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
            self._cache[i] = img
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        w, h = size
        ih, iw = img.shape[:2]
        crop_w = min(iw, ih * w / h) * rng.uniform(0.4, 1.0)
        crop_h = crop_w * h / w
        x0, y0 = rng.uniform(0, iw - crop_w), rng.uniform(0, ih - crop_h)
        crop = img[int(y0) : int(y0 + crop_h), int(x0) : int(x0 + crop_w)]
        out = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
        return out[:, ::-1].copy() if rng.random() < 0.5 else out

    def sample(
        self, rng: np.random.Generator, size: tuple[int, int], palette: np.ndarray | None = None, user_prob: float = 0.0
    ) -> np.ndarray:
        """An RGB uint8 background; ``palette`` (colours, ``[P, 3]``) steers it towards those colours."""
        w, h = size
        if self.files and rng.random() < user_prob:
            img = self._user_image(rng, size)
            if img is not None:
                return img
        c1, c2 = (_random_color(rng, palette).astype(np.float32) for _ in range(2))
        kind = rng.integers(5)
        if kind == 0:  # colour field with a slow shading
            shade = _smooth_noise(rng, size, 1) - 0.5
            img = c1[None, None, :] + shade * rng.uniform(10, 60)
        elif kind == 1:  # linear or radial gradient
            x, y = _grid(size)
            if rng.random() < 0.5:
                ang = rng.uniform(0, 2 * np.pi)
                t = (x * np.cos(ang) + y * np.sin(ang)) * 0.5 + 0.5
            else:
                cx, cy = rng.uniform(-1, 1, 2)
                t = np.sqrt((x - cx) ** 2 + (y - cy) ** 2) / rng.uniform(0.5, 2.0)
            t = np.clip(t, 0, 1)[..., None]
            img = c1 * (1 - t) + c2 * t
        elif kind == 2:  # smooth noise, coloured or between two colours
            n = _smooth_noise(rng, size, 3 if rng.random() < 0.5 else 1)
            img = c1 * (1 - n) + c2 * n
        elif kind == 3:  # stripes or checkers
            x, y = _grid(size)
            ang, freq = rng.uniform(0, np.pi), rng.uniform(2, 25)
            s = np.sin(freq * np.pi * (x * np.cos(ang) + y * np.sin(ang)))
            if rng.random() < 0.5:
                s = s * np.sin(freq * np.pi * (-x * np.sin(ang) + y * np.cos(ang)))
            t = (s > 0).astype(np.float32)[..., None] if rng.random() < 0.6 else (s[..., None] * 0.5 + 0.5)
            img = c1 * (1 - t) + c2 * t
        else:  # many shapes on a colour field
            img = np.empty((h, w, 3), np.uint8)
            img[:] = np.clip(c1, 0, 255).astype(np.uint8)
            draw_shapes(rng, img, int(rng.integers(10, 40)), palette, scale=0.7)
            return img
        return np.clip(img, 0, 255).astype(np.uint8)


def _robot_palette(rgb: np.ndarray, mask: np.ndarray, rng: np.random.Generator, n: int = 6) -> np.ndarray | None:
    """A few colours of the rendered robot (backgrounds close to them are the hard case)."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return None
    pick = rng.integers(len(ys), size=n)
    return rgb[ys[pick], xs[pick]].astype(np.float64)


def _add_occluders(
    rng: np.random.Generator, img: np.ndarray, mask: np.ndarray, profile: SceneProfile, palette: np.ndarray | None
) -> float:
    """Shapes in front of the robot, each kept only while the total hidden robot area stays under
    ``profile.max_occlusion``. Returns the hidden fraction."""
    area = int(mask.sum())
    if area == 0:
        return 0.0
    ys, xs = np.nonzero(mask)
    x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
    extent = max(x1 - x0, y1 - y0, 8)
    hidden = np.zeros(mask.shape, bool)
    h, w = mask.shape
    for _ in range(int(rng.integers(1, 4))):
        occ = np.zeros((h, w), np.uint8)
        cx, cy = rng.uniform(x0, x1 + 1), rng.uniform(y0, y1 + 1)
        r = rng.uniform(0.08, 0.35) * extent
        kind = rng.integers(3)
        if kind == 0:
            n = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            poly = np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], 1).astype(np.int32)
            cv2.fillPoly(occ, [poly], 1)
        elif kind == 1:
            cv2.ellipse(
                occ, (int(cx), int(cy)), (int(r), int(r * rng.uniform(0.3, 1))), rng.uniform(0, 180), 0, 360, 1, -1
            )
        else:  # a bar crossing the robot (cable, table edge, pole)
            ang = rng.uniform(0, np.pi)
            d = np.array([np.cos(ang), np.sin(ang)]) * extent
            cv2.line(occ, (int(cx - d[0]), int(cy - d[1])), (int(cx + d[0]), int(cy + d[1])), 1, max(2, int(r * 0.4)))
        occ = occ.astype(bool)
        if ((hidden | occ) & mask).sum() > profile.max_occlusion * area:
            continue
        hidden |= occ
        color = _random_color(rng, palette if rng.random() < 0.5 else None)
        texture = (_smooth_noise(rng, (w, h), 1)[..., 0] - 0.5) * rng.uniform(0, 60)
        img[occ] = np.clip(color[None, :] + texture[occ][:, None], 0, 255).astype(np.uint8)
    return float((hidden & mask).sum() / area)


def _augment(rng: np.random.Generator, img: np.ndarray, profile: SceneProfile) -> np.ndarray:
    """Colour jitter (brightness, contrast, saturation, hue), blur and sensor noise.

    Written with OpenCV's whole-image operations: this runs once per frame at full size.
    """
    j = profile.color_jitter
    out = img
    if j > 0:
        bright, contrast, sat = rng.uniform(1 - j, 1 + j, 3)
        mean = float(np.mean(cv2.mean(img)[:3]))
        # brightness then contrast about the mean, as one affine map
        out = cv2.convertScaleAbs(img, alpha=bright * contrast, beta=bright * mean * (1 - contrast))
        gray = cv2.cvtColor(cv2.cvtColor(out, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
        out = cv2.addWeighted(out, float(sat), gray, float(1 - sat), 0.0)  # saturation (saturating uint8)
        if rng.random() < 0.3:  # hue
            hsv = cv2.cvtColor(out, cv2.COLOR_RGB2HSV)
            hsv[..., 0] = ((hsv[..., 0].astype(np.int16) + int(rng.integers(-12, 13))) % 180).astype(np.uint8)
            out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if rng.random() < profile.blur_prob:
        out = cv2.GaussianBlur(out, (0, 0), float(rng.uniform(0.4, 1.5)))
    std = rng.uniform(*profile.noise_std)
    if std > 0.5 and rng.random() < 0.7:
        noise = rng.standard_normal(out.shape, dtype=np.float32) * np.float32(std)
        out = cv2.add(out, noise, dtype=cv2.CV_8U)  # rounds and saturates to 0..255
    return np.ascontiguousarray(out)


def compose_frame(
    rng: np.random.Generator,
    robot_rgb: np.ndarray,
    mask: np.ndarray,
    profile: SceneProfile,
    backgrounds: BackgroundSource,
) -> tuple[np.ndarray, dict]:
    """The final image from a robot render: background, distractors, soft edges, occluders, augmentation."""
    h, w = mask.shape
    low_contrast = rng.random() < profile.low_contrast_prob
    palette = _robot_palette(robot_rgb, mask, rng) if low_contrast else None
    bg = backgrounds.sample(rng, (w, h), palette, 0.0 if low_contrast else profile.user_background_prob)
    n_distract = int(rng.integers(profile.distractors[0], profile.distractors[1] + 1))
    if n_distract:
        draw_shapes(rng, bg, n_distract, palette if rng.random() < 0.5 else None, scale=0.5)
    soften = float(rng.uniform(0.4, 0.9)) if rng.random() < 0.5 else 0.0
    img = bg
    ys, xs = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    if len(ys):  # blend only around the robot (soft edges spread by < 4 px)
        y0, y1 = max(ys[0] - 4, 0), min(ys[-1] + 5, h)
        x0, x1 = max(xs[0] - 4, 0), min(xs[-1] + 5, w)
        alpha = mask[y0:y1, x0:x1].astype(np.float32)
        if soften:
            alpha = cv2.GaussianBlur(alpha, (0, 0), soften)
        alpha = alpha[..., None]
        fg, back = robot_rgb[y0:y1, x0:x1].astype(np.float32), bg[y0:y1, x0:x1].astype(np.float32)
        img[y0:y1, x0:x1] = (fg * alpha + back * (1 - alpha) + 0.5).astype(np.uint8)
    hidden = _add_occluders(rng, img, mask, profile, palette) if rng.random() < profile.occluder_prob else 0.0
    img = _augment(rng, img, profile)
    return img, {"low_contrast": bool(low_contrast), "occluded": hidden, "distractors": n_distract}


def list_backgrounds(folder: str | Path | None) -> list[Path]:
    if folder is None:
        return []
    folder = Path(folder)
    if not folder.is_dir():
        raise Monose3Error(f"backgrounds folder not found: {folder} (pass a folder of .jpg/.png images)")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_EXTS and p.is_file())
    if not files:
        raise Monose3Error(f"no images ({', '.join(IMAGE_EXTS)}) in backgrounds folder {folder}")
    return files
