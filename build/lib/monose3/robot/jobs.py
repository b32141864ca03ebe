"""What to render: plain data shared by monose3's renderer and pybullet's (no torch, so that
pybullet's worker processes stay small)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# What frames can be rendered with: monose3's renderer, or pybullet's TinyRenderer / EGL.
RENDERERS = ("torch", "tiny", "egl")


@dataclass(frozen=True)
class Lighting:
    """One directional light, given in the camera frame, plus ambient light.

    ``direction`` points from the surface towards the light; the default, above and behind
    the camera's left shoulder, is the fixed neutral light of render-and-compare.
    """

    direction: tuple[float, float, float] = (-0.3, -0.6, -1.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.55
    diffuse: float = 0.55
    specular: float = 0.15
    shininess: float = 16.0


@dataclass(frozen=True)
class RenderJob:
    """One render for :meth:`RobotRenderer.render_jobs`: joints in the model's order,
    camera-from-base 4x4, K 3x3, (width, height)."""

    joints: np.ndarray
    pose: np.ndarray
    K: np.ndarray
    size: tuple[int, int]
    lighting: Lighting = field(default_factory=Lighting)
