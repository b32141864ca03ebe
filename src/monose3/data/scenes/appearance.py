"""The pixels of a synthetic frame around a robot render, batched in torch: backgrounds
(procedural or photographs), distractor shapes, soft robot edges, occluders, colour jitter,
blur, sensor noise and JPEG-like block artefacts.

One implementation for ``monose3 generate`` (frames written to disk, a batch of one) and for
the scenes synthesised on the training device (``monose3 train --synthetic``, the robot
parser), so a :class:`~monose3.data.scenes.profiles.SceneProfile` means the same in both.
Images are ``[B, 3, h, w]`` floats in [0, 1]; masks ``[B, 1, h, w]``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torchvision.ops import roi_align

from monose3.data.inputs import list_backgrounds
from monose3.data.scenes.profiles import SceneProfile
from monose3.errors import Monose3Error

PHOTO_SIZE = (512, 384)  # every photograph is stored at this size; crops are resampled from it
# scikit-image's bundled photographs (no download), the training backgrounds when it is installed.
SKIMAGE_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "camera")
PALETTE_COLOURS = 6  # robot colours a low-contrast scene's background and shapes are drawn near
PALETTE_SPREAD = 25.0 / 255  # how far (std) a colour drawn near the palette strays from it
EDGE_BLUR = (0.4, 0.9)  # px: the soft robot edge of half the scenes (a real camera's optics)
HUE_PROB, HUE_MAX_DEG = 0.3, 24.0  # a hue shift in 30 % of the images, by up to 24 deg


def _uniform(gen: torch.Generator, shape, lo: float, hi: float, device) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=gen, device=device)


def load_photos(
    source: str | Path | Sequence[Path] | None, device: torch.device, bundled: bool = True
) -> torch.Tensor | None:
    """Background photographs ``[N, 3, 384, 512]`` uint8: a folder's images (or these image
    files), else (``bundled``) scikit-image's when it is installed, else None (procedural only)."""
    import cv2

    images = []
    if source is not None:
        files = list_backgrounds(source) if isinstance(source, str | Path) else [Path(p) for p in source]
        for path in files:
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                images.append(bgr[..., ::-1])
        if not images:
            raise Monose3Error(f"no readable images in backgrounds {source}; give .jpg/.png photographs")
    elif bundled:
        try:
            import skimage.data
        except ImportError:
            return None
        for name in SKIMAGE_PHOTOS:
            try:
                img = getattr(skimage.data, name)()
            except Exception:  # noqa: BLE001 - a photo the installed version lacks is skipped
                continue
            images.append(np.stack([img] * 3, -1) if img.ndim == 2 else img[..., :3])
    if not images:
        return None
    resized = [cv2.resize(np.ascontiguousarray(im), PHOTO_SIZE, interpolation=cv2.INTER_AREA) for im in images]
    return torch.from_numpy(np.stack(resized)).permute(0, 3, 1, 2).contiguous().to(device)


def robot_palettes(gen: torch.Generator, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """:data:`PALETTE_COLOURS` colours of each rendered robot ``[B, P, 3]`` (pixels of ``rgb`` in
    ``mask``; grey where the robot is not in view): backgrounds close to them are the hard case."""
    b = len(rgb)
    weights = mask.flatten(1).float() + 1e-6
    pick = torch.multinomial(weights, PALETTE_COLOURS, replacement=True, generator=gen)
    colours = torch.gather(rgb.flatten(2), 2, pick[:, None].expand(b, 3, -1)).transpose(1, 2)
    return torch.where(mask.flatten(1).any(1)[:, None, None], colours, torch.full_like(colours, 0.5))


def random_colours(gen: torch.Generator, n: int, device, palette: torch.Tensor | None = None) -> torch.Tensor:
    """``[n, 3, 1, 1]`` colours: uniform, or near a random colour of each image's ``palette``
    ``[n, P, 3]`` where its rows are not NaN (the low-contrast scenes)."""
    colours = torch.rand(n, 3, generator=gen, device=device)
    if palette is not None:
        pick = torch.randint(0, palette.shape[1], (n,), generator=gen, device=device)
        near = palette[torch.arange(n, device=device), pick] + PALETTE_SPREAD * torch.randn(
            n, 3, generator=gen, device=device
        )
        colours = torch.where(near.isnan(), colours, near.clamp(0, 1))
    return colours[:, :, None, None]


def smooth_noise(gen: torch.Generator, n: int, size: tuple[int, int], channels: int, device) -> torch.Tensor:
    """Value noise in [0, 1] ``[n, c, h, w]``: a coarse random grid and a finer one, upsampled."""
    w, h = size
    out = torch.zeros(n, channels, h, w, device=device)
    for cells, amp in ((3, 1.0), (12, 0.4)):
        coarse = torch.rand(n, channels, max(2, cells * h // w), cells, generator=gen, device=device)
        out += amp * F.interpolate(coarse, size=(h, w), mode="bicubic", align_corners=False)
    return (out / 1.4).clamp(0, 1)


def _grid(n: int, size: tuple[int, int], device) -> tuple[torch.Tensor, torch.Tensor]:
    w, h = size
    y, x = torch.meshgrid(
        torch.linspace(-1, 1, h, device=device) * h / w, torch.linspace(-1, 1, w, device=device), indexing="ij"
    )
    return x.expand(n, 1, h, w), y.expand(n, 1, h, w)


def backgrounds(
    gen: torch.Generator,
    n: int,
    size: tuple[int, int],
    photos: torch.Tensor | None,
    device,
    photo_prob: float | torch.Tensor = 0.0,
    palette: torch.Tensor | None = None,
) -> torch.Tensor:
    """``[n, 3, h, w]`` random backgrounds: shaded colour fields, gradients, smooth noise,
    stripes and checkers in colours near ``palette`` (:func:`random_colours`), or, with
    ``photo_prob`` (one for all or ``[n]``), random crops of ``photos``."""
    w, h = size
    c1, c2 = random_colours(gen, n, device, palette), random_colours(gen, n, device, palette)
    x, y = _grid(n, size, device)
    ang = _uniform(gen, (n, 1, 1, 1), 0, math.pi, device)
    along = x * torch.cos(ang) + y * torch.sin(ang)
    freq = _uniform(gen, (n, 1, 1, 1), 2, 25, device)
    stripes = torch.sin(freq * math.pi * along)
    checker = stripes * torch.sin(freq * math.pi * (y * torch.cos(ang) - x * torch.sin(ang)))
    noise = smooth_noise(gen, n, size, 3, device)
    kinds = [
        c1 + (noise[:, :1] - 0.5) * 0.4,  # colour field with slow shading
        c1 + (c2 - c1) * (along * 0.5 + 0.5).clamp(0, 1),  # gradient
        c1 + (c2 - c1) * noise,  # smooth noise between two colours
        c1 + (c2 - c1) * (stripes > 0).float(),
        c1 + (c2 - c1) * (checker > 0).float(),
    ]
    kind = torch.randint(0, len(kinds), (n,), generator=gen, device=device)
    out = torch.zeros(n, 3, h, w, device=device)
    for k, img in enumerate(kinds):
        sel = kind == k
        out[sel] = img.expand(n, 3, h, w)[sel]
    photo = torch.rand(n, generator=gen, device=device) < photo_prob
    if photos is not None and photo.any():
        out[photo] = photo_crops(gen, photos, int(photo.sum()), size, device)
    return out.clamp(0, 1)


def photo_crops(gen: torch.Generator, photos: torch.Tensor, n: int, size: tuple[int, int], device) -> torch.Tensor:
    """``n`` random crops of random photographs at ``size``, half of them mirrored."""
    w, h = size
    pw, ph = PHOTO_SIZE
    idx = torch.randint(0, len(photos), (n,), generator=gen, device=device)
    crop_w = _uniform(gen, (n,), 0.3, 1.0, device) * min(pw, ph * w / h)
    crop_h = crop_w * h / w
    x0 = torch.rand(n, generator=gen, device=device) * (pw - crop_w)
    y0 = torch.rand(n, generator=gen, device=device) * (ph - crop_h)
    rois = torch.stack([torch.arange(n, device=device).float(), x0, y0, x0 + crop_w, y0 + crop_h], 1)
    crops = roi_align(photos[idx].float() / 255, rois, (h, w), 1.0, sampling_ratio=2, aligned=True)
    mirror = torch.rand(n, generator=gen, device=device) < 0.5
    return torch.where(mirror[:, None, None, None], crops.flip(-1), crops)


def shape_masks(gen: torch.Generator, n: int, size: tuple[int, int], centre, radius, device) -> torch.Tensor:
    """One random ellipse, rectangle or bar per image ``[n, 1, h, w]`` (float 0/1), at ``centre``
    ``[n, 2]`` in [-1, 1] coordinates with size ``radius`` ``[n]``."""
    x, y = _grid(n, size, device)
    ang = _uniform(gen, (n, 1, 1, 1), 0, math.pi, device)
    dx, dy = x - centre[:, 0, None, None, None], y - centre[:, 1, None, None, None]
    u = dx * torch.cos(ang) + dy * torch.sin(ang)
    v = -dx * torch.sin(ang) + dy * torch.cos(ang)
    r = radius[:, None, None, None]
    aspect = _uniform(gen, (n, 1, 1, 1), 0.15, 1.0, device)
    kind = torch.randint(0, 3, (n, 1, 1, 1), generator=gen, device=device)
    ellipse = (u / r) ** 2 + (v / (r * aspect)) ** 2 < 1
    rect = (u.abs() < r) & (v.abs() < r * aspect)
    bar = (u.abs() < 2.5 * r) & (v.abs() < 0.12 * r)
    return torch.where(kind == 0, ellipse, torch.where(kind == 1, rect, bar)).float()


@dataclass
class Shapes:
    """How :func:`paint_shapes` draws: ``counts`` ``[n]`` shapes on each image, of radius
    ``scale`` (fractions of the width); ``centre_at`` ``[n, 2]`` gathers them there (occluders
    near the robot); colours near ``palette``; textured with smooth noise when ``textured``."""

    counts: torch.Tensor
    scale: tuple[float, float]
    centre_at: torch.Tensor | None = None
    palette: torch.Tensor | None = None
    textured: bool = False


def paint_shapes(
    gen: torch.Generator, img: torch.Tensor, shapes: Shapes, robot: torch.Tensor | None = None, max_hidden: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Paint ``shapes`` onto ``img``; a shape that would hide more than ``max_hidden`` of the
    ``robot`` mask (with those painted before it) is left out. Returns the image and where it
    was painted ``[n, 1, h, w]``."""
    n, _, h, w = img.shape
    device = img.device
    painted = torch.zeros(n, 1, h, w, device=device)
    area = robot.sum((1, 2, 3)).clamp_min(1) if robot is not None else None
    for k in range(int(shapes.counts.max()) if len(shapes.counts) else 0):
        on = (shapes.counts > k).float()[:, None, None, None]
        centre = _uniform(gen, (n, 2), -1, 1, device) * torch.tensor([1.0, h / w], device=device)
        if shapes.centre_at is not None:
            centre = shapes.centre_at + 0.3 * (centre - shapes.centre_at)
        radius = _uniform(gen, (n,), *shapes.scale, device)
        mask = shape_masks(gen, n, (w, h), centre, radius, device) * on
        if robot is not None:
            hidden = (torch.maximum(painted, mask) * robot).sum((1, 2, 3)) / area
            mask = mask * (hidden <= max_hidden).float()[:, None, None, None]
        colour = random_colours(gen, n, device, shapes.palette)
        if shapes.textured:
            colour = colour + (smooth_noise(gen, n, (w, h), 1, device) - 0.5) * _uniform(
                gen, (n, 1, 1, 1), 0, 0.25, device
            )
        img = img * (1 - mask) + colour.clamp(0, 1) * mask
        painted = torch.maximum(painted, mask)
    return img, painted


def gaussian_blur(img: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Per-image Gaussian blur (``sigma`` ``[B]`` pixels; 0 = none), separable, as a grouped conv."""
    b, c, h, w = img.shape
    radius = 3
    x = torch.arange(-radius, radius + 1, device=img.device, dtype=img.dtype)
    k = torch.exp(-(x[None] ** 2) / (2 * sigma.clamp_min(1e-3)[:, None] ** 2))
    k = torch.where(sigma[:, None] > 0.05, k, (x[None] == 0).to(img.dtype))
    k = (k / k.sum(1, keepdim=True)).repeat_interleave(c, 0)  # [B*c, 2r+1]
    flat = F.pad(img.reshape(1, b * c, h, w), (radius, radius, radius, radius), mode="replicate")
    flat = F.conv2d(flat, k[:, None, None, :], groups=b * c)
    flat = F.conv2d(flat, k[:, None, :, None], groups=b * c)
    return flat.reshape(b, c, h, w)


_JPEG_LUMA = torch.tensor(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ],
    dtype=torch.float32,
)


def jpeg_like(img: torch.Tensor, quality: torch.Tensor) -> torch.Tensor:
    """JPEG's lossy step on 8x8 blocks (DCT, quantise with the standard table at ``quality``
    ``[B]`` in 1..100, inverse DCT), per RGB channel; sizes not divisible by 8 are padded."""
    b, c, h, w = img.shape
    ph, pw = (-h) % 8, (-w) % 8
    x = F.pad(img, (0, pw, 0, ph), mode="replicate") * 255 - 128
    n = torch.arange(8, dtype=img.dtype, device=img.device)
    dct = torch.cos((2 * n[None] + 1) * n[:, None] * math.pi / 16) * torch.where(n == 0, 1 / math.sqrt(8), 0.5)[:, None]
    blocks = x.unfold(2, 8, 8).unfold(3, 8, 8)  # [B, c, H/8, W/8, 8, 8]
    coef = dct @ blocks @ dct.T
    scale = torch.where(quality < 50, 50 / quality, 2 - quality / 50).clamp_min(0.01)
    table = (_JPEG_LUMA.to(img) * scale[:, None, None, None, None, None]).clamp_min(1)
    blocks = dct.T @ (torch.round(coef / table) * table) @ dct
    out = blocks.permute(0, 1, 2, 4, 3, 5).reshape(b, c, h + ph, w + pw)[..., :h, :w]
    return ((out + 128) / 255).clamp(0, 1)


def shift_hue(img: torch.Tensor, degrees: torch.Tensor) -> torch.Tensor:
    """Rotate each image's colours about the grey axis by ``degrees`` ``[B]`` (a hue shift)."""
    axis = torch.full((3,), 1 / math.sqrt(3), dtype=img.dtype, device=img.device)
    theta = torch.deg2rad(degrees.to(img.dtype))[:, None, None]
    cross = torch.tensor([[0, -1, 1], [1, 0, -1], [-1, 1, 0]], dtype=img.dtype, device=img.device) / math.sqrt(3)
    eye = torch.eye(3, dtype=img.dtype, device=img.device)
    rot = torch.cos(theta) * eye + torch.sin(theta) * cross + (1 - torch.cos(theta)) * torch.outer(axis, axis)
    return torch.einsum("bij,bjhw->bihw", rot, img).clamp(0, 1)


def augment(gen: torch.Generator, img: torch.Tensor, profile: SceneProfile, jpeg: bool = True) -> torch.Tensor:
    """Colour jitter (brightness, contrast, saturation, hue), blur, sensor noise and, with
    ``jpeg``, JPEG artefacts (a frame written to disk gets real ones instead)."""
    n, device = img.shape[0], img.device
    j = profile.color_jitter
    bright, contrast, sat = (_uniform(gen, (n, 1, 1, 1), 1 - j, 1 + j, device) for _ in range(3))
    mean = img.mean((1, 2, 3), keepdim=True)
    img = (img - mean) * contrast + mean * bright
    grey = img.mean(1, keepdim=True)
    img = (grey + (img - grey) * sat).clamp(0, 1)
    hue = torch.rand(n, generator=gen, device=device) < HUE_PROB
    img = shift_hue(img, torch.where(hue, _uniform(gen, (n,), -HUE_MAX_DEG, HUE_MAX_DEG, device), 0.0))
    blur = torch.rand(n, generator=gen, device=device) < profile.blur_prob
    img = gaussian_blur(img, torch.where(blur, _uniform(gen, (n,), 0.4, 1.5, device), torch.zeros(n, device=device)))
    std = _uniform(gen, (n, 1, 1, 1), *profile.noise_std, device) / 255
    img = (img + std * torch.randn(img.shape, generator=gen, device=device)).clamp(0, 1)
    if not jpeg:
        return img
    return jpeg_like(img, _uniform(gen, (n,), *profile.jpeg_quality, device).round())


def scene_background(
    gen: torch.Generator,
    n: int,
    size: tuple[int, int],
    profile: SceneProfile,
    photos: torch.Tensor | None,
    device,
    photo_share: float | torch.Tensor = 1.0,
    palette: torch.Tensor | None = None,
) -> torch.Tensor:
    """What stands behind the robot ``[n, 3, h, w]``: a background (a photograph with
    ``profile.user_background_prob`` times ``photo_share``) and the profile's distractor shapes."""
    img = backgrounds(gen, n, size, photos, device, profile.user_background_prob * photo_share, palette)
    lo, hi = profile.distractors
    counts = torch.randint(lo, hi + 1, (n,), generator=gen, device=device)
    return paint_shapes(gen, img, Shapes(counts, (0.05, 0.4), palette=palette))[0]


@dataclass
class Composite:
    """A composed scene before augmentation: ``image`` ``[B, 3, h, w]``, the robot's visible
    (unoccluded) ``mask`` ``[B, 1, h, w]``, the fraction of the robot occluders hide ``[B]``
    and which scenes drew their colours near the robot's (``low_contrast`` ``[B]``)."""

    image: torch.Tensor
    mask: torch.Tensor
    occluded: torch.Tensor
    low_contrast: torch.Tensor


def compose(
    gen: torch.Generator,
    robot_rgb: torch.Tensor,
    robot_mask: torch.Tensor,
    profile: SceneProfile,
    photos: torch.Tensor | None,
    occluder_centre: torch.Tensor,
    background: torch.Tensor | None = None,
) -> Composite:
    """The robot renders ``robot_rgb`` ``[B, 3, h, w]`` (``robot_mask`` ``[B, 1, h, w]``) over a
    background with distractors, with soft edges in half the scenes, then occluders gathered
    near ``occluder_centre`` ``[B, 2]`` ([-1, 1] coordinates) hiding at most
    ``profile.max_occlusion`` of the robot. A ``profile.low_contrast_prob`` share of the scenes
    draws background and shapes near the robot's own colours (and no photograph). A given
    ``background`` ``[B, 3, h, w]`` replaces the drawn one (a static camera's scene)."""
    n, _, h, w = robot_rgb.shape
    device = robot_rgb.device
    robot = robot_mask.float()
    low = torch.rand(n, generator=gen, device=device) < profile.low_contrast_prob
    palette = torch.where(low[:, None, None], robot_palettes(gen, robot_rgb, robot), float("nan"))
    if background is None:
        background = scene_background(gen, n, (w, h), profile, photos, device, torch.where(low, 0.0, 1.0), palette)
    img = background
    soft = torch.rand(n, generator=gen, device=device) < 0.5
    alpha = gaussian_blur(robot, torch.where(soft, _uniform(gen, (n,), *EDGE_BLUR, device), 0.0))
    img = img * (1 - alpha) + robot_rgb * alpha
    occluded_scene = torch.rand(n, generator=gen, device=device) < profile.occluder_prob
    counts = torch.where(occluded_scene, torch.randint(1, 4, (n,), generator=gen, device=device), 0)
    occluders = Shapes(counts, (0.05, 0.25), occluder_centre, palette, textured=True)
    img, occluded = paint_shapes(gen, img, occluders, robot, profile.max_occlusion)
    hidden = (occluded * robot).sum((1, 2, 3)) / robot.sum((1, 2, 3)).clamp_min(1)
    return Composite(img, robot * (1 - occluded), hidden, low)


def mask_centre(mask: torch.Tensor) -> torch.Tensor:
    """The centre ``[B, 2]`` of each mask's pixels in [-1, 1] x [-h/w, h/w] coordinates (0 where empty)."""
    b, _, h, w = mask.shape
    x, y = _grid(b, (w, h), mask.device)
    total = mask.sum((1, 2, 3)).clamp_min(1e-6)
    return torch.stack([(x * mask).sum((1, 2, 3)) / total, (y * mask).sum((1, 2, 3)) / total], 1)


def compose_frame(
    rng: np.random.Generator,
    robot_rgb: np.ndarray,
    mask: np.ndarray,
    profile: SceneProfile,
    photos: torch.Tensor | None,
    background: torch.Tensor | None = None,
) -> tuple[np.ndarray, float]:
    """One frame to write to disk from a robot render (``robot_rgb`` ``H x W x 3`` uint8, ``mask``
    ``H x W``): :func:`compose` then :func:`augment` without JPEG (the file brings its own),
    drawn from ``rng``. Returns the RGB uint8 image and the fraction of the robot occluded."""
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    rgb = torch.from_numpy(np.ascontiguousarray(robot_rgb)).permute(2, 0, 1)[None].float() / 255
    robot = torch.from_numpy(np.ascontiguousarray(mask))[None, None].float()
    scene = compose(gen, rgb, robot, profile, photos, mask_centre(robot), background)
    img = augment(gen, scene.image, profile, jpeg=False)
    return (img[0].permute(1, 2, 0) * 255).round().to(torch.uint8).numpy(), float(scene.occluded[0])
