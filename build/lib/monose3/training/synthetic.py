"""Synthetic training images made on the training device, nothing on disk.

A scene (joints, camera, intrinsics, light) is drawn exactly as ``monose3 generate`` draws
frame ``i`` (:func:`monose3.data.scenes.sampling.sample_scene`), cheaply, in data-loader workers. The
"real" image is then rendered straight into the crop that the forward process implies (the
robot at its true pose seen through the crop's intrinsics, which is the crop of a full-size
render without the resampling), over a random background, with distractors, occluders, the
zero padding where the crop leaves the image, colour jitter, blur, sensor noise and JPEG-like
block artefacts, all batched in torch.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset
from torchvision.ops import roi_align

from monose3.data.scenes.appearance import IMAGE_EXTS, list_backgrounds
from monose3.data.scenes.profiles import SceneProfile, get_profile
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.errors import Monose3Error
from monose3.robot import RobotModel, RobotSpec
from monose3.robot.renderer import LightingBatch, RobotRenderer
from monose3.training.samples import NoisyViews

PHOTO_SIZE = (512, 384)  # every photograph is stored at this size; crops are resampled from it
# scikit-image's bundled photographs (no download), used as backgrounds when it is installed.
SKIMAGE_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry", "camera")


class SceneDataset(Dataset):
    """Scene ``i`` of a seed: the pose, intrinsics (at ``size``), joints and light that
    ``monose3 generate`` would draw for frame ``i`` (float64 tensors)."""

    def __init__(self, robot: RobotSpec, profile: str | SceneProfile, size: tuple[int, int], seed: int):
        self.spec, self.profile, self.size, self.seed = robot, get_profile(profile), size, seed
        self._model: RobotModel | None = None

    def __len__(self) -> int:  # scenes are unlimited; the sampler decides which are drawn
        return 2**62

    def __getitem__(self, sample: int) -> dict[str, torch.Tensor]:
        if self._model is None:
            self._model = RobotModel(self.spec)
        scene = sample_scene(frame_rng(self.seed, sample), self._model, self.profile, self.size)
        light = scene.lighting
        as_t = lambda x: torch.as_tensor(np.asarray(x, np.float64))  # noqa: E731
        return {
            "pose": as_t(scene.pose),
            "K": as_t(scene.K),
            "joints": as_t(scene.joints),
            "light_direction": as_t(light.direction),
            "light_color": as_t(light.color),
            "light_terms": as_t([light.ambient, light.diffuse, light.specular, light.shininess]),
        }


def _uniform(gen: torch.Generator, shape, lo: float, hi: float, device) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=gen, device=device)


def load_photos(folder: str | Path | None, device: torch.device) -> torch.Tensor | None:
    """Background photographs ``[N, 3, 384, 512]``: a user folder's images, else scikit-image's
    bundled ones when it is installed, else None (procedural backgrounds only)."""
    import cv2

    images = []
    if folder is not None:
        for path in list_backgrounds(folder):
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                images.append(bgr[..., ::-1])
        if not images:
            raise Monose3Error(f"no readable images ({', '.join(IMAGE_EXTS)}) in backgrounds folder {folder}")
    else:
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
    resized = [cv2.resize(np.ascontiguousarray(im), PHOTO_SIZE, interpolation=cv2.INTER_AREA) for im in images]
    return torch.from_numpy(np.stack(resized)).permute(0, 3, 1, 2).float().div(255).to(device)


def _smooth_noise(gen, n: int, size: tuple[int, int], channels: int, device) -> torch.Tensor:
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


def backgrounds(gen, n: int, size: tuple[int, int], photos: torch.Tensor | None, device) -> torch.Tensor:
    """``[n, 3, h, w]`` random backgrounds: shaded colour fields, gradients, smooth noise,
    stripes and checkers, and random crops of photographs when there are any."""
    w, h = size
    c1 = torch.rand(n, 3, 1, 1, generator=gen, device=device)
    c2 = torch.rand(n, 3, 1, 1, generator=gen, device=device)
    x, y = _grid(n, size, device)
    ang = _uniform(gen, (n, 1, 1, 1), 0, math.pi, device)
    along = x * torch.cos(ang) + y * torch.sin(ang)
    freq = _uniform(gen, (n, 1, 1, 1), 2, 25, device)
    stripes = torch.sin(freq * math.pi * along)
    checker = stripes * torch.sin(freq * math.pi * (y * torch.cos(ang) - x * torch.sin(ang)))
    noise = _smooth_noise(gen, n, size, 3, device)
    kinds = [
        c1 + (noise[:, :1] - 0.5) * 0.4,  # colour field with slow shading
        c1 + (c2 - c1) * (along * 0.5 + 0.5).clamp(0, 1),  # gradient
        c1 + (c2 - c1) * noise,  # smooth noise between two colours
        c1 + (c2 - c1) * (stripes > 0).float(),
        c1 + (c2 - c1) * (checker > 0).float(),
    ]
    kind = torch.randint(0, len(kinds) + (photos is not None), (n,), generator=gen, device=device)
    out = torch.zeros(n, 3, h, w, device=device)
    for k, img in enumerate(kinds):
        sel = kind == k
        out[sel] = img.expand(n, 3, h, w)[sel]
    if photos is not None and (sel := kind == len(kinds)).any():
        out[sel] = _photo_crops(gen, photos, int(sel.sum()), size, device)
    return out.clamp(0, 1)


def _photo_crops(gen, photos: torch.Tensor, n: int, size: tuple[int, int], device) -> torch.Tensor:
    w, h = size
    pw, ph = PHOTO_SIZE
    idx = torch.randint(0, len(photos), (n,), generator=gen, device=device).float()
    crop_w = _uniform(gen, (n,), 0.3, 1.0, device) * min(pw, ph * w / h)
    crop_h = crop_w * h / w
    x0 = torch.rand(n, generator=gen, device=device) * (pw - crop_w)
    y0 = torch.rand(n, generator=gen, device=device) * (ph - crop_h)
    rois = torch.stack([idx, x0, y0, x0 + crop_w, y0 + crop_h], 1)
    return roi_align(photos, rois, (h, w), 1.0, sampling_ratio=2, aligned=True)


def _shape_masks(gen, n: int, size: tuple[int, int], centre, radius, device) -> torch.Tensor:
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


def _paint_shapes(
    gen, img: torch.Tensor, count: int, prob: float, scale: tuple[float, float], centre_at=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Paint up to ``count`` shapes in flat random colours onto ``img`` (each with ``prob``);
    returns the image and where it was painted ``[n, 1, h, w]``."""
    n, _, h, w = img.shape
    device = img.device
    painted = torch.zeros(n, 1, h, w, device=device)
    for _ in range(count):
        on = (torch.rand(n, 1, 1, 1, generator=gen, device=device) < prob).float()
        centre = _uniform(gen, (n, 2), -1, 1, device) * torch.tensor([1.0, h / w], device=device)
        if centre_at is not None:
            centre = centre_at + 0.3 * (centre - centre_at)
        radius = _uniform(gen, (n,), *scale, device)
        mask = _shape_masks(gen, n, (w, h), centre, radius, device) * on
        color = torch.rand(n, 3, 1, 1, generator=gen, device=device)
        img = img * (1 - mask) + color * mask
        painted = torch.maximum(painted, mask)
    return img, painted


def _inside_image(views: NoisyViews, size: tuple[int, int], image_size: tuple[int, int], device) -> torch.Tensor:
    """``[B, 1, h, w]``: crop pixels that fall inside the standardised image (roi_align pads the rest with zeros)."""
    w, h = size
    boxes = views.boxes.float().to(device)
    sx = (boxes[:, 2] - boxes[:, 0]) / w
    sy = (boxes[:, 3] - boxes[:, 1]) / h
    u = boxes[:, 0, None] + (torch.arange(w, device=device)[None] + 0.5) * sx[:, None]
    v = boxes[:, 1, None] + (torch.arange(h, device=device)[None] + 0.5) * sy[:, None]
    inside_u = (u >= 0) & (u <= image_size[0])
    inside_v = (v >= 0) & (v <= image_size[1])
    return (inside_v[:, :, None] & inside_u[:, None, :]).float()[:, None]


def _gaussian_blur(img: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
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


def augment(gen, img: torch.Tensor, profile: SceneProfile) -> torch.Tensor:
    """Colour jitter (brightness, contrast, saturation), blur, sensor noise and JPEG artefacts."""
    n, device = img.shape[0], img.device
    j = profile.color_jitter
    bright, contrast, sat = (_uniform(gen, (n, 1, 1, 1), 1 - j, 1 + j, device) for _ in range(3))
    mean = img.mean((1, 2, 3), keepdim=True)
    img = (img - mean) * contrast + mean * bright
    grey = img.mean(1, keepdim=True)
    img = (grey + (img - grey) * sat).clamp(0, 1)
    blur = torch.rand(n, generator=gen, device=device) < profile.blur_prob
    img = _gaussian_blur(img, torch.where(blur, _uniform(gen, (n,), 0.4, 1.5, device), torch.zeros(n, device=device)))
    std = _uniform(gen, (n, 1, 1, 1), *profile.noise_std, device) / 255
    img = img + std * torch.randn(img.shape, generator=gen, device=device)
    quality = _uniform(gen, (n,), *profile.jpeg_quality, device).round()
    return jpeg_like(img.clamp(0, 1), quality)


def _light_batch(scenes: dict[str, torch.Tensor], device: torch.device) -> LightingBatch:
    terms = scenes["light_terms"].float().to(device)
    return LightingBatch(
        direction=scenes["light_direction"].float().to(device),
        color=scenes["light_color"].float().to(device),
        ambient=terms[:, 0],
        diffuse=terms[:, 1],
        specular=terms[:, 2],
        shininess=terms[:, 3],
    )


def compose_scenes(
    renderer: RobotRenderer,
    scenes: dict[str, torch.Tensor],
    K: torch.Tensor,
    size: tuple[int, int],
    profile: SceneProfile,
    photos: torch.Tensor | None,
    gen: torch.Generator,
    device: torch.device,
    occluder_centre: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The robot of each scene seen through ``K`` ``[B, 3, 3]`` at ``size``, over a random
    background with distractors, then occluders near ``occluder_centre`` ``[B, 2]`` ([-1, 1]
    coordinates); returns the image before augmentation ``[B, 3, h, w]`` and the robot's
    visible (unoccluded) mask ``[B, 1, h, w]``."""
    n = len(K)
    links = len(renderer.model.links)
    tint = _uniform(gen, (n, links, 3), 0.8, 1.15, device) * _uniform(gen, (n, 1, 1), 0.75, 1.2, device)
    light = _light_batch(scenes, device)
    robot = renderer.render(scenes["joints"].numpy(), scenes["pose"].to(device), K.to(device), size, light, tint)
    img = backgrounds(gen, n, size, photos, device)
    img, _ = _paint_shapes(gen, img, profile.distractors[1], 0.5, (0.05, 0.4))
    alpha = robot.mask[:, None].float()
    img = img * (1 - alpha) + robot.rgb * alpha
    img, occluded = _paint_shapes(gen, img, 2, profile.occluder_prob / 2, (0.05, 0.25), centre_at=occluder_centre)
    return img, alpha * (1 - occluded)


def synthesize_crops(
    renderer: RobotRenderer,
    scenes: dict[str, torch.Tensor],
    views: NoisyViews,
    size: tuple[int, int],
    image_size: tuple[int, int],
    profile: SceneProfile,
    photos: torch.Tensor | None,
    gen: torch.Generator,
    device: torch.device,
) -> torch.Tensor:
    """The image crops ``[B, 3, h, w]`` a camera would have given for these scenes, at the crops
    ``views`` defines (what ``crop_batch`` cuts from a real image)."""
    centre = torch.zeros(len(views.t), 2, device=device)  # the crop is centred on the robot at H_t
    img, _ = compose_scenes(renderer, scenes, views.K_crop, size, profile, photos, gen, device, centre)
    # The camera's image is what gets jittered; the crop's zero padding comes after.
    return augment(gen, img, profile) * _inside_image(views, size, image_size, device)


def synthesize_images(
    renderer: RobotRenderer,
    scenes: dict[str, torch.Tensor],
    size: tuple[int, int],
    profile: SceneProfile,
    photos: torch.Tensor | None,
    gen: torch.Generator,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Whole camera images ``[B, 3, h, w]`` of these scenes (intrinsics ``scenes["K"]`` at
    ``size``) and the robot's visible mask ``[B, 1, h, w]``: the robot parser's training pairs."""
    K = scenes["K"].float().to(device)
    pose = scenes["pose"].float().to(device)
    uv = (K @ pose[:, :3, 3:])[:, :, 0]  # the base's pixel: occluders gather near the robot
    w, h = size
    centre = torch.stack([uv[:, 0] / uv[:, 2] / w * 2 - 1, (uv[:, 1] / uv[:, 2] / h * 2 - 1) * h / w], 1)
    img, visible = compose_scenes(renderer, scenes, K, size, profile, photos, gen, device, centre.clamp(-1, 1))
    return augment(gen, img, profile), visible
