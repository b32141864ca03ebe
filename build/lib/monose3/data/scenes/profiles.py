"""Scene profiles: how synthetic frames are randomised (one preset system for scenes)."""

from __future__ import annotations

from dataclasses import dataclass

from monose3.errors import Monose3Error


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
    # Sanity scenes (benchmarks/denoiser_designs.py --sanity): the robot 0.9-1.6 m away, centred
    # and fully in view; no distractors, occluders, photographs, blur, noise, colour jitter or JPEG loss.
    "clean": SceneProfile(
        name="clean",
        distance=(0.9, 1.6),
        offcenter=0.2,
        min_visible=0.98,
        distractors=(0, 0),
        occluder_prob=0.0,
        low_contrast_prob=0.0,
        user_background_prob=0.0,
        blur_prob=0.0,
        noise_std=(0.0, 0.0),
        color_jitter=0.0,
        jpeg_quality=(98, 98),
    ),
}


def get_profile(profile: str | SceneProfile) -> SceneProfile:
    if isinstance(profile, SceneProfile):
        return profile
    if profile not in PROFILES:
        raise Monose3Error(f"unknown profile {profile!r}; choose one of {sorted(PROFILES)}")
    return PROFILES[profile]
