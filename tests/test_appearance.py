"""The one scene appearance of generate and train --synthetic (data/scenes/appearance.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from monose3.data.scenes.appearance import (
    augment,
    compose,
    compose_frame,
    jpeg_like,
    mask_centre,
    robot_palettes,
    shift_hue,
)
from monose3.data.scenes.profiles import PROFILES


def _robot(n: int = 4, size: tuple[int, int] = (64, 48)) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat orange 'robot' filling a box in the middle of each image."""
    w, h = size
    mask = torch.zeros(n, 1, h, w)
    mask[:, :, h // 4 : 3 * h // 4, w // 3 : 2 * w // 3] = 1
    rgb = torch.tensor([0.9, 0.5, 0.1]).view(1, 3, 1, 1).expand(n, 3, h, w) * mask
    return rgb, mask


def test_occluders_never_hide_more_of_the_robot_than_the_profile_allows():
    rgb, mask = _robot(64)
    profile = replace(PROFILES["train"], occluder_prob=1.0, max_occlusion=0.2)
    scene = compose(torch.Generator().manual_seed(0), rgb, mask, profile, None, mask_centre(mask))
    assert (scene.occluded <= 0.2 + 1e-6).all() and (scene.occluded > 0).any()
    hidden = 1 - scene.mask.sum((1, 2, 3)) / mask.sum((1, 2, 3))
    assert torch.allclose(hidden, scene.occluded, atol=1e-6)


def test_low_contrast_scenes_draw_their_background_near_the_robots_colours():
    rgb, mask = _robot(16)
    palette = robot_palettes(torch.Generator().manual_seed(0), rgb, mask)
    assert torch.allclose(palette, torch.tensor([0.9, 0.5, 0.1]).expand(16, 6, 3))
    bare = replace(PROFILES["train"], distractors=(0, 0), occluder_prob=0.0, color_jitter=0.0)
    near, far = (replace(bare, low_contrast_prob=p) for p in (1.0, 0.0))
    outside = (1 - mask).bool().expand(-1, 3, -1, -1)
    errors = []
    for profile in (near, far):
        scene = compose(torch.Generator().manual_seed(1), rgb, mask, profile, None, mask_centre(mask))
        colour = torch.tensor([0.9, 0.5, 0.1]).view(1, 3, 1, 1).expand_as(scene.image)
        errors.append((scene.image - colour).abs()[outside].mean())
        assert bool(scene.low_contrast.all()) == (profile is near)
    assert errors[0] < 0.5 * errors[1]


def test_jpeg_like_keeps_flat_blocks_and_quantises_texture_harder_at_low_quality():
    flat = torch.full((1, 3, 16, 16), 0.5)
    assert torch.allclose(jpeg_like(flat, torch.tensor([50.0])), flat, atol=1 / 255)
    texture = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    errors = (jpeg_like(texture, torch.tensor([95.0, 10.0])) - texture).abs().mean((1, 2, 3))
    assert errors[0] < errors[1]


def test_a_hue_shift_keeps_greys_and_turns_colours():
    img = torch.tensor([[0.5, 0.5, 0.5], [0.9, 0.2, 0.1]]).view(2, 3, 1, 1)
    assert torch.allclose(shift_hue(img, torch.zeros(2)), img, atol=1e-6)
    turned = shift_hue(img, torch.full((2,), 120.0))
    assert torch.allclose(turned[0], img[0], atol=1e-6)
    assert torch.allclose(turned[1].flatten(), torch.tensor([0.1, 0.9, 0.2]), atol=1e-5)  # R->G->B->R


def test_augment_is_seeded_and_jpeg_optional():
    img = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    profile = PROFILES["hard"]
    a = augment(torch.Generator().manual_seed(5), img, profile)
    b = augment(torch.Generator().manual_seed(5), img, profile)
    assert torch.equal(a, b) and a.shape == img.shape and a.min() >= 0 and a.max() <= 1
    assert not torch.equal(augment(torch.Generator().manual_seed(5), img, profile, jpeg=False), a)


def test_a_written_frame_is_the_same_for_the_same_draw():
    rgb, mask = _robot(1, (80, 60))
    robot_rgb = (rgb[0].permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
    frames = [compose_frame(np.random.default_rng(7), robot_rgb, mask[0, 0].bool().numpy(), PROFILES["train"], None)]
    frames.append(
        compose_frame(np.random.default_rng(7), robot_rgb, mask[0, 0].bool().numpy(), PROFILES["train"], None)
    )
    (img, occluded), (again, _) = frames
    assert img.dtype == np.uint8 and img.shape == (60, 80, 3) and 0 <= occluded <= 1
    np.testing.assert_array_equal(img, again)
