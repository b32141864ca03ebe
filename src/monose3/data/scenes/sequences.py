"""Synthetic sequences (``monose3 generate --sequence``): one scene seen by a static or slowly
orbiting camera while the robot moves along a smooth joint trajectory, in DREAM format.

What a sequence keeps from frame to frame: the camera's intrinsics, the light, the background
with its distractor shapes (drawn once; with the profile's ``low_contrast_prob`` it is drawn
near the robot's own colours, a white robot before a white wall); a moving camera orbits the
robot's centroid about the vertical at ``orbit_deg`` per frame and the background pans with it.
What changes: the joints (a new target pose every ``keyframe_every`` frames, reached by a
smoothstep, every frame keeping the robot in view), the occluders, colour jitter, blur, noise
and JPEG quality, as in single frames. Frame ``i``'s pixels draw from ``frame_rng(seed, i + 1)``,
the scene from ``frame_rng(seed, 0)``. ``_sequence.json`` records how it was made.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from monose3 import atomic
from monose3.data.dream_writer import write_camera_settings, write_frame
from monose3.data.scenes.appearance import compose_frame, robot_palettes, scene_background
from monose3.data.scenes.profiles import SceneProfile, get_profile
from monose3.data.scenes.sampling import frame_rng, sample_scene
from monose3.data.scenes.writer import make_renderer
from monose3.errors import Monose3Error
from monose3.geometry.camera import inside_image, project
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import euler_xyz_to_matrix
from monose3.robot import RobotModel, RobotSpec
from monose3.robot.jobs import RenderJob

SEQUENCE_FILE = "_sequence.json"
CAMERAS = ("static", "moving")
MAX_TRIES = 200  # joint targets (and cameras) drawn before giving up on keeping the robot in view


@dataclass(frozen=True)
class SequenceConfig:
    """How a sequence moves: ``camera`` static or moving (orbiting ``orbit_deg`` per frame), a new
    joint target every ``keyframe_every`` frames."""

    frames: int = 60
    camera: str = "static"
    keyframe_every: int = 15
    orbit_deg: float = 0.4

    def __post_init__(self) -> None:
        if self.camera not in CAMERAS:
            raise Monose3Error(f"unknown sequence camera {self.camera!r}; choose one of {', '.join(CAMERAS)}")
        if self.frames < 2 or self.keyframe_every < 1:
            raise Monose3Error(f"a sequence needs at least 2 frames, got {self.frames}")


def in_view_fraction(model: RobotModel, joints: np.ndarray, pose: np.ndarray, K: np.ndarray, size) -> float:
    """Share of the robot's surface points inside the image (0 if any comes within 10 cm of the lens)."""
    return _visible_share(transform_points(pose, model.surface_points(joints[None])[0]), K, size)


def _visible_share(cam: np.ndarray, K: np.ndarray, size) -> float:
    if cam[:, 2].min() < 0.1:
        return 0.0
    u, v = project(cam, K).T
    w, h = size
    return float(np.mean((u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)))


def smooth_trajectory(keyframes: np.ndarray, frames: int, every: int) -> np.ndarray:
    """``[frames, n]`` joints through ``keyframes`` ``[k, n]``, one every ``every`` frames, eased
    in and out between them (smoothstep: no velocity jump at a keyframe)."""
    t = np.arange(frames) / every
    k = np.minimum(t.astype(int), len(keyframes) - 2)
    s = np.clip(t - k, 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    return keyframes[k] + s[:, None] * (keyframes[k + 1] - keyframes[k])


def orbit(pose: np.ndarray, centre: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """``[N, 4, 4]`` camera-from-base poses of a camera at ``pose`` turned by ``degrees`` ``[N]``
    about the vertical through ``centre`` (base frame): the world turned the other way."""
    out = []
    for deg in degrees:
        turn = euler_xyz_to_matrix(np.array([0.0, 0.0, -math.radians(float(deg))]))
        out.append(pose @ make_pose(turn, centre - turn @ centre))
    return np.stack(out)


def sample_sequence(rng: np.random.Generator, model: RobotModel, profile: SceneProfile,
                    size: tuple[int, int], config: SequenceConfig) -> dict:  # fmt: skip
    """The scene, camera path and joint trajectory of one sequence: ``joints`` ``[N, n]``,
    ``poses`` ``[N, 4, 4]`` (camera-from-base), ``K``, ``lighting``, ``centre``. Every frame,
    not only the joint targets, keeps the robot in view (:func:`frame_in_view`): a target is
    drawn again until the way to it does."""
    count = math.ceil((config.frames - 1) / config.keyframe_every) + 1
    step = config.orbit_deg if config.camera == "moving" else 0.0
    for _ in range(MAX_TRIES):
        scene = sample_scene(rng, model, profile, size)
        centre = model.centroid(model.surface_points(scene.joints[None]))[0]
        poses = orbit(scene.pose, centre, step * np.arange(config.frames))
        keys = [scene.joints]
        while len(keys) < count:
            first = (len(keys) - 1) * config.keyframe_every
            frames = range(first + 1, min(first + config.keyframe_every, config.frames - 1) + 1)
            for _ in range(MAX_TRIES):
                q = model.random_joints(rng, 1)[0]
                way = smooth_trajectory(np.stack([keys[-1], q]), config.keyframe_every + 1, config.keyframe_every)
                if all(frame_in_view(model, way[i - first], poses[i], scene.K, size, profile) for i in frames):
                    keys.append(q)
                    break
            else:
                break
        if len(keys) == count:
            joints = smooth_trajectory(np.stack(keys), config.frames, config.keyframe_every)
            return {"joints": joints, "poses": poses, "K": scene.K, "lighting": scene.lighting, "centre": centre}
    raise Monose3Error(f"profile {profile.name}: no camera kept the robot in view along a sequence")


def frame_in_view(model: RobotModel, joints: np.ndarray, pose: np.ndarray, K: np.ndarray, size,
                  profile: SceneProfile) -> bool:  # fmt: skip
    """Whether a frame shows the profile's ``min_visible`` share of the robot with its centroid
    inside the image: where the centroid leaves it, an estimate counts as out of view, however
    good (``reliability.pose_in_view``)."""
    surface = model.surface_points(joints[None])[0]
    if _visible_share(transform_points(pose, surface), K, size) < profile.min_visible:
        return False
    return bool(inside_image(project(transform_points(pose, model.centroid(surface)[None]), K)[0], size))


def sequence_background(rng: np.random.Generator, profile: SceneProfile, size: tuple[int, int], first_render,
                        photos: torch.Tensor | None) -> tuple[torch.Tensor, bool]:  # fmt: skip
    """The sequence's one background ``[1, 3, h, w]`` (twice as wide, for a moving camera to pan
    over) and whether it was drawn near the robot's colours (low contrast)."""
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    low = bool(rng.random() < profile.low_contrast_prob)
    rgb = torch.from_numpy(np.ascontiguousarray(first_render[0])).permute(2, 0, 1)[None].float() / 255
    mask = torch.from_numpy(np.ascontiguousarray(first_render[1]))[None, None].float()
    palette = robot_palettes(gen, rgb, mask) if low else None
    w, h = size
    wide = scene_background(gen, 1, (2 * w, h), profile, None if low else photos, "cpu", 0.0 if low else 1.0, palette)
    return wide, low


def write_sequence(out: str | Path, config: SequenceConfig, seed: int = 0, robot: str | RobotSpec = "panda",
                   profile: str | SceneProfile = "reallike", size: tuple[int, int] = (640, 480),
                   backend: str = "torch", photos: torch.Tensor | None = None) -> Path:  # fmt: skip
    """Write one sequence as a DREAM folder (``NNNNNN.rgb.jpg`` + ``NNNNNN.json`` per frame,
    ``_camera_settings.json``, ``_sequence.json``); returns the folder."""
    out = Path(out)
    model = RobotModel(robot)
    profile = get_profile(profile)
    path = sample_sequence(frame_rng(seed, 0), model, profile, size, config)
    renderer = make_renderer(model, backend)
    try:
        views = zip(path["joints"], path["poses"], strict=True)
        renders = [renderer.render(RenderJob(q, p, path["K"], size, path["lighting"])) for q, p in views]
    finally:
        renderer.close()
    background, low = sequence_background(frame_rng(seed, 0), profile, size, renders[0], photos)
    per_frame = replace(profile, distractors=(0, 0))  # the distractors are in the background
    pan = path["K"][0, 0] * math.radians(config.orbit_deg) if config.camera == "moving" else 0.0
    w = size[0]
    for i, (rgb, mask) in enumerate(renders):
        x = int(round(w / 2 + i * pan)) % w  # a moving camera pans over the wide background
        frng = frame_rng(seed, i + 1)
        img, occluded = compose_frame(frng, rgb, mask, per_frame, None, background[..., x : x + w])
        quality = int(frng.integers(profile.jpeg_quality[0], profile.jpeg_quality[1] + 1))
        visible = in_view_fraction(model, path["joints"][i], path["poses"][i], path["K"], size)
        write_frame(out, i, img, path["K"], model.joint_dict(path["joints"][i]), path["poses"][i], robot=model,
                    quality=quality, visibility=round(visible * (1.0 - occluded), 4))  # fmt: skip
    write_camera_settings(out, path["K"], *size)
    info = {"seed": seed, "profile": profile.name, "size": list(size), "low_contrast": low,
            "renderer": backend, **asdict(config)}  # fmt: skip
    atomic.write_text(out / SEQUENCE_FILE, json.dumps(info, indent=1))
    return out
