"""Sampling one synthetic frame's scene: joints, camera (pose and intrinsics) and lighting.

Frame ``i`` draws all its randomness from ``np.random.SeedSequence([seed, i])`` (:func:`frame_rng`),
so a dataset does not depend on the order or the process its frames are made in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monose3.data.scenes.profiles import SceneProfile
from monose3.errors import Monose3Error
from monose3.geometry.camera import intrinsics_matrix, project
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import euler_xyz_to_matrix, skew
from monose3.robot import RobotModel
from monose3.robot.jobs import Lighting

MAX_CAMERA_TRIES = 100


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of frame ``index``: independent of the order frames are made in."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


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


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    k = skew(v)
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
    return intrinsics_matrix(fx, fy, cx, cy)


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
    for attempt in range(MAX_CAMERA_TRIES):
        K = sample_intrinsics(rng, profile, size)
        dist = rng.uniform(*profile.distance)
        azim = rng.uniform(0.0, 2.0 * math.pi)
        elev = math.radians(rng.uniform(*profile.elevation))
        eye = centroid + dist * np.array(
            [math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)]
        )
        rot = look_at(eye, centroid)
        roll = math.radians(float(np.clip(rng.normal(0.0, profile.roll_std), -30.0, 30.0)))
        rz = euler_xyz_to_matrix(np.array([0.0, 0.0, roll]))
        off = profile.offcenter if attempt < MAX_CAMERA_TRIES // 2 else profile.offcenter / 2
        # where the centroid lands: within ``off`` of the principal point, and inside the image
        u = float(np.clip(K[0, 2] + rng.uniform(-off, off) * w / 2.0, 0.02 * w, 0.98 * w))
        v = float(np.clip(K[1, 2] + rng.uniform(-off, off) * h / 2.0, 0.02 * h, 0.98 * h))
        ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
        rot = rotation_between(np.array([0.0, 0.0, 1.0]), ray / np.linalg.norm(ray)) @ rz @ rot
        pose = make_pose(rot, -rot @ eye)
        cam = transform_points(pose, pts)
        if cam[:, 2].min() < 0.1:
            continue
        uv = project(cam, K)
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
