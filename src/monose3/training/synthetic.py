"""Synthetic training images made on the training device, nothing on disk.

A scene (joints, camera, intrinsics, light) is drawn exactly as ``monose3 generate`` draws
frame ``i`` (:func:`monose3.data.scenes.sampling.sample_scene`), cheaply, in data-loader workers. The
"real" image is then rendered straight into the crop that the forward process implies (the
robot at its true pose seen through the crop's intrinsics, which is the crop of a full-size
render without the resampling) and given the appearance ``monose3 generate`` gives its frames
(:mod:`monose3.data.scenes.appearance`), with the zero padding where the crop leaves the image.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from monose3.data.scenes.appearance import Composite, augment, compose
from monose3.data.scenes.profiles import SceneProfile, get_profile
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.robot import RobotModel, RobotSpec
from monose3.robot.renderer import LightingBatch, RobotRenderer
from monose3.training.samples import NoisyViews


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
) -> Composite:
    """The robot of each scene seen through ``K`` ``[B, 3, 3]`` at ``size`` (each link's colour
    tinted a little), composed by :func:`monose3.data.scenes.appearance.compose`."""
    n = len(K)
    links = len(renderer.model.links)
    tint = torch.empty(n, links, 3, device=device).uniform_(0.8, 1.15, generator=gen)
    tint = tint * torch.empty(n, 1, 1, device=device).uniform_(0.75, 1.2, generator=gen)
    light = _light_batch(scenes, device)
    robot = renderer.render(scenes["joints"].numpy(), scenes["pose"].to(device), K.to(device), size, light, tint)
    return compose(gen, robot.rgb, robot.mask[:, None], profile, photos, occluder_centre)


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
    scene = compose_scenes(renderer, scenes, views.K_crop, size, profile, photos, gen, device, centre)
    # The camera's image is what gets jittered; the crop's zero padding comes after.
    return augment(gen, scene.image, profile) * _inside_image(views, size, image_size, device)


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
    scene = compose_scenes(renderer, scenes, K, size, profile, photos, gen, device, centre.clamp(-1, 1))
    return augment(gen, scene.image, profile), scene.mask
