"""Domain-randomised synthetic training data in DREAM format (``monose3 generate``).

Each frame: joints uniform within the limits, a camera around the robot (distance,
azimuth, elevation, roll, intrinsics and where the robot lands in the image all random),
the robot rendered (monose3's renderer, or pybullet's for cross-renderer sets) under random
lighting, composited over a random background with distractor shapes behind and occluders
in front, then colour jitter, blur, noise and a random JPEG quality. The annotation is exact by construction: the
keypoints written are the forward kinematics of the written joints under the written pose.

Frame ``i`` draws all its randomness from ``np.random.SeedSequence([seed, i])``, so a
dataset is byte-identical whatever the number of worker processes, and an interrupted job
can be resumed (``--resume``) without changing a single frame.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import queue
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from monose3.data.dream import DreamDataset, write_camera_settings, write_frame
from monose3.errors import Monose3Error
from monose3.robot import RobotModel, RobotSpec, get_spec, spec_from_files
from monose3.robot.jobs import RENDERERS, Lighting, RenderJob

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp", ".webp")
GENERATION_FILE = "_generation.json"
_MAX_CAMERA_TRIES = 100


@dataclass(frozen=True)
class SceneProfile:
    """How frames are randomised. Angles in degrees, distances in meters (camera to the
    robot's centroid), fractions of the image for offsets.

    ``offcenter``: the robot's centroid lands uniformly within this fraction of the
    half-image around the principal point (0 = centred). ``min_visible``: the fraction of
    robot surface points that must project inside the image (else the camera is resampled).
    """

    name: str
    distance: tuple[float, float] = (0.5, 3.5)
    elevation: tuple[float, float] = (-10.0, 70.0)
    roll_std: float = 8.0
    hfov: tuple[float, float] = (45.0, 75.0)
    aspect_jitter: float = 0.01
    principal_jitter: float = 0.02
    offcenter: float = 0.6
    min_visible: float = 0.5
    distractors: tuple[int, int] = (0, 8)
    occluder_prob: float = 0.3
    max_occlusion: float = 0.3
    low_contrast_prob: float = 0.1
    user_background_prob: float = 0.6
    blur_prob: float = 0.3
    noise_std: tuple[float, float] = (0.0, 8.0)
    color_jitter: float = 0.25
    jpeg_quality: tuple[int, int] = (70, 98)


PROFILES: dict[str, SceneProfile] = {
    # Broad coverage for training.
    "train": SceneProfile(name="train"),
    # Like DREAM-real: a tripod 0.8-1.8 m away, robot mostly centred, moderate clutter.
    "reallike": SceneProfile(
        name="reallike",
        distance=(0.8, 1.8),
        elevation=(0.0, 45.0),
        roll_std=3.0,
        hfov=(50.0, 70.0),
        offcenter=0.25,
        min_visible=0.95,
        distractors=(2, 8),
        occluder_prob=0.15,
        max_occlusion=0.15,
        low_contrast_prob=0.1,
        blur_prob=0.2,
        noise_std=(0.0, 5.0),
        color_jitter=0.15,
        jpeg_quality=(85, 98),
    ),
    # Like RoboKeyGen's scenes: small, off-centre robots, backgrounds close to the robot's
    # colours, frequent occluders.
    "hard": SceneProfile(
        name="hard",
        distance=(1.2, 3.5),
        elevation=(-10.0, 60.0),
        roll_std=6.0,
        offcenter=0.8,
        min_visible=0.4,
        distractors=(3, 12),
        occluder_prob=0.7,
        max_occlusion=0.4,
        low_contrast_prob=0.8,
        blur_prob=0.4,
        noise_std=(2.0, 10.0),
        color_jitter=0.3,
        jpeg_quality=(60, 95),
    ),
}


def get_profile(profile: str | SceneProfile) -> SceneProfile:
    if isinstance(profile, SceneProfile):
        return profile
    if profile not in PROFILES:
        raise Monose3Error(f"unknown profile {profile!r}; choose one of {sorted(PROFILES)}")
    return PROFILES[profile]


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of frame ``index``: independent of the order frames are made in."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


# ---- scene sampling -------------------------------------------------------------------------


_UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = _UP) -> np.ndarray:
    """Camera-from-world rotation (OpenCV axes) of a camera at ``eye`` looking at ``target``, image up ~ ``up``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking straight along up: any horizontal x will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: camera axes in world coordinates


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


@dataclass
class Scene:
    """Everything random about one frame except the pixels."""

    joints: np.ndarray
    pose: np.ndarray
    K: np.ndarray
    lighting: Lighting
    points_cam: np.ndarray  # robot surface points in the camera frame
    visible_fraction: float


def sample_intrinsics(rng: np.random.Generator, profile: SceneProfile, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    hfov = math.radians(rng.uniform(*profile.hfov))
    fx = (w / 2.0) / math.tan(hfov / 2.0)
    fy = fx * (1.0 + rng.normal(0.0, profile.aspect_jitter))
    cx = (w - 1) / 2.0 + rng.normal(0.0, profile.principal_jitter) * w
    cy = (h - 1) / 2.0 + rng.normal(0.0, profile.principal_jitter) * h
    cx, cy = float(np.clip(cx, 0.3 * w, 0.7 * w)), float(np.clip(cy, 0.3 * h, 0.7 * h))
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def sample_lighting(rng: np.random.Generator, camera_from_base: np.ndarray) -> Lighting:
    """Random light direction (mostly from above in the base frame, given in the camera frame),
    a mild colour tint (sometimes a strong one) and shading weights."""
    direction = rng.normal(size=3)
    direction[2] = abs(direction[2]) + 0.2 if rng.random() < 0.85 else direction[2]
    tint = rng.uniform(0.75, 1.0, 3) if rng.random() < 0.8 else rng.uniform(0.4, 1.0, 3)
    direction = camera_from_base[:3, :3] @ (direction / np.linalg.norm(direction))
    return Lighting(
        direction=tuple(float(v) for v in direction),
        color=tuple(float(v) for v in tint / tint.max()),
        ambient=float(rng.uniform(0.3, 0.8)),
        diffuse=float(rng.uniform(0.2, 0.8)),
        specular=float(rng.uniform(0.0, 0.6)),
    )


def sample_scene(rng: np.random.Generator, model: RobotModel, profile: SceneProfile, size: tuple[int, int]) -> Scene:
    """Joints, camera and light of one frame.

    The camera looks at the robot's centroid from a random direction and distance, is rolled,
    then turned about its own centre so the centroid lands at a random pixel (``offcenter``).
    Cameras that put surface points within 10 cm of the lens or show too little of the robot
    are resampled.
    """
    w, h = size
    joints = model.random_joints(rng, 1)[0]
    pts = model.surface_points(joints[None])[0]
    centroid = model.centroid(pts)
    best = None
    for attempt in range(_MAX_CAMERA_TRIES):
        K = sample_intrinsics(rng, profile, size)
        dist = rng.uniform(*profile.distance)
        azim = rng.uniform(0.0, 2.0 * math.pi)
        elev = math.radians(rng.uniform(*profile.elevation))
        eye = centroid + dist * np.array(
            [math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)]
        )
        rot = look_at(eye, centroid)
        roll = math.radians(float(np.clip(rng.normal(0.0, profile.roll_std), -30.0, 30.0)))
        rz = np.array([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0], [0.0, 0.0, 1.0]])
        off = profile.offcenter if attempt < _MAX_CAMERA_TRIES // 2 else profile.offcenter / 2
        # where the centroid lands: within ``off`` of the principal point, and inside the image
        u = float(np.clip(K[0, 2] + rng.uniform(-off, off) * w / 2.0, 0.02 * w, 0.98 * w))
        v = float(np.clip(K[1, 2] + rng.uniform(-off, off) * h / 2.0, 0.02 * h, 0.98 * h))
        ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
        rot = _rotation_between(np.array([0.0, 0.0, 1.0]), ray / np.linalg.norm(ray)) @ rz @ rot
        pose = np.eye(4)
        pose[:3, :3] = rot
        pose[:3, 3] = -rot @ eye
        cam = pts @ rot.T + pose[:3, 3]
        if cam[:, 2].min() < 0.1:
            continue
        uv = cam[:, :2] / cam[:, 2:3] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        frac = float(inside.mean())
        if best is None or frac > best[3]:
            best = (pose, K, cam, frac)
        if frac >= profile.min_visible:
            break
    if best is None:  # pragma: no cover - every camera had the robot within 10 cm of the lens
        raise Monose3Error(f"profile {profile.name}: no valid camera found; increase the distance range")
    pose, K, cam, frac = best
    return Scene(joints, pose, K, sample_lighting(rng, pose), cam, frac)


# ---- pixels -------------------------------------------------------------------------------


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


def _draw_shapes(
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
            _draw_shapes(rng, img, int(rng.integers(10, 40)), palette, scale=0.7)
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
        _draw_shapes(rng, bg, n_distract, palette if rng.random() < 0.5 else None, scale=0.5)
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


# ---- workers ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Job:
    out: str
    seed: int
    size: tuple[int, int]
    profile: SceneProfile
    spec: RobotSpec
    backgrounds: tuple[str, ...]
    backend: str


def make_renderer(model: RobotModel, backend: str):
    """monose3's own renderer ('torch'), or pybullet's TinyRenderer/EGL as an independent one."""
    if backend == "torch":
        from monose3.robot.renderer import RobotRenderer

        return _TorchJobs(RobotRenderer(model))
    from monose3.robot.reference import Renderer

    return Renderer(model, backend)


class _TorchJobs:
    """The batched renderer behind the one-job ``render`` / ``close`` interface of pybullet's."""

    def __init__(self, renderer):
        self.renderer = renderer

    def render(self, job: RenderJob) -> tuple[np.ndarray, np.ndarray]:
        return self.renderer.render_jobs([job])[0]

    def close(self) -> None:
        self.renderer.release()


class FrameMaker:
    """Renders and writes frames of one job (one per process: a pybullet client is not shareable)."""

    def __init__(self, job: _Job):
        self.job = job
        self.model = RobotModel(job.spec)
        self.renderer = make_renderer(self.model, job.backend)
        self.backgrounds = BackgroundSource([Path(p) for p in job.backgrounds])

    def make(self, index: int) -> tuple[np.ndarray, Scene, dict]:
        rng = frame_rng(self.job.seed, index)
        scene = sample_scene(rng, self.model, self.job.profile, self.job.size)
        robot_rgb, mask = self.renderer.render(
            RenderJob(scene.joints, scene.pose, scene.K, self.job.size, scene.lighting)
        )
        img, info = compose_frame(rng, robot_rgb, mask, self.job.profile, self.backgrounds)
        info["quality"] = int(rng.integers(self.job.profile.jpeg_quality[0], self.job.profile.jpeg_quality[1] + 1))
        return img, scene, info

    def write(self, index: int) -> int:
        img, scene, info = self.make(index)
        write_frame(
            self.job.out,
            index,
            img,
            scene.K,
            self.model.joint_dict(scene.joints),
            scene.pose,
            robot=self.model,
            quality=info["quality"],
            visibility=round(scene.visible_fraction * (1.0 - info["occluded"]), 4),
        )
        return index

    def close(self) -> None:
        self.renderer.close()


def _worker_main(job: _Job, tasks: mp.Queue, results: mp.Queue) -> None:
    """A worker process: one pybullet client, frames taken from ``tasks`` until ``None``.

    Every outcome is reported on ``results`` (index, or an error text), so the parent never
    waits on a worker that failed.
    """
    cv2.setNumThreads(1)
    if job.backend == "torch":  # one process per core: more threads each would only contend
        import torch

        torch.set_num_threads(1)
    try:
        maker = FrameMaker(job)
    except BaseException as err:  # noqa: BLE001 - reported to the parent, which raises
        results.put(("error", None, f"{type(err).__name__}: {err}"))
        return
    try:
        while (index := tasks.get()) is not None:
            try:
                maker.write(index)
            except BaseException as err:  # noqa: BLE001
                results.put(("error", index, f"{type(err).__name__}: {err}"))
                return
            results.put(("done", index, ""))
    finally:
        maker.close()


def _run_workers(job: _Job, todo: list[int], workers: int, bar) -> None:
    """Make ``todo`` over ``workers`` spawned processes; raise if one fails or dies."""
    ctx = mp.get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    for i in todo:
        tasks.put(i)
    for _ in range(workers):
        tasks.put(None)
    procs = [ctx.Process(target=_worker_main, args=(job, tasks, results), daemon=True) for _ in range(workers)]
    for p in procs:
        p.start()
    remaining = len(todo)
    try:
        while remaining:
            try:
                kind, index, text = results.get(timeout=1.0)
            except queue.Empty:
                dead = [p for p in procs if p.exitcode not in (None, 0)]
                if dead or all(p.exitcode is not None for p in procs):
                    raise Monose3Error(
                        f"a generate worker process exited (code {dead[0].exitcode if dead else 0}) before finishing; "
                        "when calling generate_dataset from a script, put the call under "
                        "`if __name__ == '__main__':` (worker processes re-import the script), or pass workers=0"
                    ) from None
                continue
            if kind == "error":
                where = f"frame {index}" if index is not None else "start-up"
                raise Monose3Error(f"generate worker failed at {where}: {text}")
            remaining -= 1
            bar.update()
    finally:
        for p in procs:
            if remaining:
                p.terminate()
            p.join(timeout=10)
        tasks.close()
        results.close()


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


def _existing_frames(out: Path) -> set[int]:
    if not out.is_dir():
        return set()
    done = set()
    for e in os.scandir(out):
        stem = e.name[:-5] if e.name.endswith(".json") else ""
        if stem.isdigit() and (out / f"{stem}.rgb.jpg").is_file():
            done.add(int(stem))
    return done


def generate_dataset(
    out: str | Path,
    num: int,
    seed: int = 0,
    robot: str | RobotSpec = "panda",
    workers: int | None = None,
    profile: str | SceneProfile = "train",
    backgrounds: str | Path | None = None,
    size: tuple[int, int] = (640, 480),
    *,
    resume: bool = False,
    backend: str = "torch",
    progress: bool = True,
) -> Path:
    """Generate ``num`` frames into ``out`` (DREAM layout, per-frame intrinsics); returns ``out``.

    ``workers``: processes (None = one per CPU core, 0 = in this process). The output does not
    depend on it. ``resume=True`` keeps the complete frames already in ``out`` and makes the
    rest (the result is identical to an uninterrupted run with the same settings).
    """
    out = Path(out)
    spec = get_spec(robot)
    prof = get_profile(profile)
    if int(num) < 1:
        raise Monose3Error(f"--num must be at least 1, got {num}")
    w, h = (int(v) for v in size)
    if w < 64 or h < 64:
        raise Monose3Error(f"image size {w}x{h} is too small; use at least 64x64 (e.g. 640x480)")
    if workers is not None and workers < 0:
        raise Monose3Error(f"--workers must be >= 0, got {workers}")
    if out.exists() and not out.is_dir():
        raise Monose3Error(f"--out {out} is a file; give a folder path")
    bg_files = list_backgrounds(backgrounds)
    settings = {
        "num": int(num),
        "seed": int(seed),
        "robot": spec.name,
        "profile": asdict(prof),
        "size": [w, h],
        "backgrounds": [str(p) for p in bg_files],
        "renderer": backend,
    }
    done = _existing_frames(out)
    if done and not resume:
        raise Monose3Error(
            f"{out} already holds {len(done)} frames; choose a new --out folder, delete it, "
            "or pass --resume to finish an interrupted run"
        )
    if resume and (out / GENERATION_FILE).is_file():
        previous = json.loads((out / GENERATION_FILE).read_text())
        current = json.loads(json.dumps(settings))
        if {k: v for k, v in previous.items() if k != "num"} != {k: v for k, v in current.items() if k != "num"}:
            raise Monose3Error(
                f"--resume: {out} was generated with different settings ({out / GENERATION_FILE}); "
                "rerun with the same --seed/--robot/--profile/--size/--backgrounds or use a new folder"
            )
    out.mkdir(parents=True, exist_ok=True)
    nominal_f = (w / 2.0) / math.tan(math.radians(60.0) / 2.0)
    write_camera_settings(out, np.array([[nominal_f, 0, (w - 1) / 2], [0, nominal_f, (h - 1) / 2], [0, 0, 1]]), w, h)
    (out / GENERATION_FILE).write_text(json.dumps(settings, indent=1))
    todo = [i for i in range(int(num)) if i not in done]
    if backend not in RENDERERS:
        raise Monose3Error(f"unknown renderer {backend!r}; choose one of {', '.join(RENDERERS)}")
    if backend != "torch":
        from monose3.robot.reference import resolve_backend

        resolve_backend(backend)  # a missing pybullet fails here, before any work
    job = _Job(str(out), int(seed), (w, h), prof, spec, tuple(str(p) for p in bg_files), backend)
    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    workers = min(workers, len(todo))
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=f"generate {out.name}", unit="frame", disable=not progress or not todo)
    if not todo:
        pass
    elif workers == 0:
        maker = FrameMaker(job)
        try:
            for i in todo:
                maker.write(i)
                bar.update()
        finally:
            maker.close()
    else:
        _run_workers(job, todo, workers, bar)
    bar.close()
    return out


# ---- preview --------------------------------------------------------------------------------


def draw_keypoints(img: np.ndarray, uv: np.ndarray, color: tuple[int, int, int] = (0, 255, 0)) -> np.ndarray:
    """Keypoints joined in chain order (base to hand) on a copy of an RGB image."""
    out = img.copy()
    scale = max(1, round(max(img.shape[:2]) / 320))
    pts = [(int(round(u)), int(round(v))) for u, v in uv]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        cv2.line(out, a, b, (255, 255, 0), scale, cv2.LINE_AA)
    for k, p in enumerate(pts):
        cv2.circle(out, p, 3 * scale, (255, 0, 0) if k == 0 else color, -1, cv2.LINE_AA)
    return out


def save_preview_grid(
    folder: str | Path,
    path: str | Path,
    rows: int = 3,
    cols: int = 4,
    robot: str | RobotSpec = "panda",
    tile_width: int = 320,
) -> Path:
    """A ``rows`` x ``cols`` grid of the first frames of a DREAM folder with their keypoints drawn."""
    ds = DreamDataset(folder, robot)
    n = min(len(ds), rows * cols)
    tiles = []
    for i in range(n):
        frame = ds[i]
        img = draw_keypoints(frame.load_image(), frame.keypoints_2d)
        s = tile_width / img.shape[1]
        img = cv2.resize(img, (tile_width, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA)
        cv2.putText(img, frame.name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    th = max(t.shape[0] for t in tiles)
    grid = np.zeros((rows * th + (rows - 1) * 4, cols * tile_width + (cols - 1) * 4, 3), np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        grid[r * (th + 4) : r * (th + 4) + tile.shape[0], c * (tile_width + 4) : c * (tile_width + 4) + tile_width] = (
            tile
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
        raise Monose3Error(f"could not write {path}; check the folder is writable and the suffix is .png/.jpg")
    return path


# ---- command line ---------------------------------------------------------------------------


# The options live in the torch-free monose3.apps.arguments (fast --help and input errors).
from monose3.apps.arguments import add_generate_arguments  # noqa: E402, F401


def run_generate(args: argparse.Namespace) -> int:
    robot: str | RobotSpec = args.robot
    if args.urdf or args.keypoints:
        if not (args.urdf and args.keypoints):
            raise Monose3Error("a custom robot needs both --urdf and --keypoints")
        robot = spec_from_files(args.urdf, args.keypoints)
    start = time.perf_counter()
    out = generate_dataset(
        args.out,
        args.num,
        args.seed,
        robot,
        args.workers,
        args.profile,
        args.backgrounds,
        args.size,
        resume=args.resume,
        backend=args.renderer,
    )
    elapsed = time.perf_counter() - start
    print(f"wrote {args.num} frames to {out} in {elapsed:.1f} s ({args.num / max(elapsed, 1e-9):.1f} frames/s)")
    if args.preview:
        print(f"preview: {save_preview_grid(out, args.preview, robot=robot)}")
    return 0


__all__ = [
    "PROFILES",
    "BackgroundSource",
    "FrameMaker",
    "Scene",
    "SceneProfile",
    "add_generate_arguments",
    "compose_frame",
    "frame_rng",
    "generate_dataset",
    "get_profile",
    "run_generate",
    "sample_scene",
    "save_preview_grid",
]
