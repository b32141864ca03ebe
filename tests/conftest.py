"""Shared fixtures: one RobotModel and one renderer per robot for the whole session (URDF and
mesh loading are the slow parts), pybullet's renderers where pybullet is installed, and a
sampler of random views of the robot."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from monose3.data.scenes.sampling import look_at as look_at_rotation
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix
from monose3.method.config import NetworkConfig, get_preset, with_section
from monose3.method.designs import build_denoiser
from monose3.method.flow_pose import Surface, render_surface
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer
from monose3.training.checkpoints import save_checkpoint

ROBOTS = ("panda", "kuka")


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-from-base pose (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    pose = np.eye(4)
    pose[:3, :3] = look_at_rotation(np.asarray(eye, float), np.asarray(target, float), np.asarray(up, float))
    pose[:3, 3] = -pose[:3, :3] @ eye
    return pose


def project_np(points: np.ndarray, pose: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Reference pinhole projection of base-frame ``[N, 3]`` points (plain numpy, no monose3)."""
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    return cam[:, :2] / cam[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


@dataclass
class View:
    """A random robot configuration seen by a random camera."""

    joints: np.ndarray
    pose: np.ndarray
    K: np.ndarray
    size: tuple[int, int]
    points: np.ndarray  # surface points, base frame
    keypoints: np.ndarray  # base frame

    def uv(self, points: np.ndarray | None = None) -> np.ndarray:
        return project_np(self.points if points is None else points, self.pose, self.K)

    def fully_in_view(self, points: np.ndarray | None = None, margin: float = 1.0) -> bool:
        uv = self.uv(points)
        w, h = self.size
        return bool(
            (uv.min(0) >= margin).all() and uv[:, 0].max() <= w - 1 - margin and uv[:, 1].max() <= h - 1 - margin
        )


@pytest.fixture(scope="session")
def models() -> dict[str, RobotModel]:
    return {name: RobotModel(name) for name in ROBOTS}


@pytest.fixture(scope="session")
def renderers(models: dict[str, RobotModel]) -> dict[str, RobotRenderer]:
    return {name: RobotRenderer(model) for name, model in models.items()}


@pytest.fixture(scope="session")
def pybullet_renderers(models: dict[str, RobotModel]) -> Iterator[dict]:
    """pybullet's TinyRenderer per robot: the independent reference (skipped without pybullet)."""
    pytest.importorskip("pybullet")
    from monose3.robot.reference import Renderer

    rend = {name: Renderer(model, "tiny") for name, model in models.items()}
    yield rend
    for r in rend.values():
        r.close()


@pytest.fixture(scope="session")
def sample_view() -> Callable[..., View]:
    """``sample_view(model, rng, size=(320, 240), dist=(0.7, 3.0))``: a camera 0.7-3 m from the
    robot's reference point looking at it (random roll, small aim jitter), random K whose
    principal point may sit well off-centre."""

    def sample(
        model: RobotModel,
        rng: np.random.Generator,
        size: tuple[int, int] = (320, 240),
        dist: tuple[float, float] = (0.7, 3.0),
    ) -> View:
        w, h = size
        q = model.random_joints(rng, 1)
        points = model.surface_points(q)[0]
        centre = model.centroid(points)
        direction = rng.normal(size=3)
        eye = centre + rng.uniform(*dist) * direction / np.linalg.norm(direction)
        pose = look_at(eye, centre + rng.normal(scale=0.03, size=3), rng.normal(size=3))
        f = rng.uniform(0.8, 1.3) * w
        K = np.array(
            [
                [f, 0.0, rng.uniform(0.35, 0.65) * w],
                [0.0, f * rng.uniform(0.97, 1.03), rng.uniform(0.35, 0.65) * h],
                [0.0, 0.0, 1.0],
            ]
        )
        return View(q[0], pose, K, size, points, model.keypoints(q)[0])

    return sample


@pytest.fixture(scope="session")
def tiny_dream(tmp_path_factory):
    """Six small generated DREAM frames (160x120), shared by the training and inference tests."""
    from monose3.data.scenes.writer import generate_dataset

    return generate_dataset(
        tmp_path_factory.mktemp("tiny_dream"), 6, seed=3, workers=0, size=(160, 120), progress=False
    )


# A network small enough for fast tests; same code path as the presets.
TINY_NET = NetworkConfig(backbone="resnet18", render_size=(64, 48), input_size=(160, 120))


def save_tiny_checkpoint(path, robot: str = "panda", xy_bias: float = 0.0):
    """A randomly initialised tiny model saved as a checkpoint (``xy_bias`` shifts every v_xy)."""
    torch.manual_seed(0)
    config = get_preset("cpu", network=TINY_NET, robot=robot)
    model = build_denoiser(config.network)
    with torch.no_grad():
        model.net.fc.bias[0] = xy_bias
    save_checkpoint(path, {"model": model.state_dict(), "config": config.to_dict(), "step": 0})
    return path


# ---- denoiser inputs ----


def random_poses(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    rot = euler_xyz_to_matrix(torch.randn(n, 3, generator=gen))
    trans = torch.randn(n, 3, generator=gen) * 0.2 + torch.tensor([0.0, 0.0, 1.5])
    return make_pose(rot, trans)


def crop_K(n: int) -> torch.Tensor:
    K = torch.tensor([[400.0, 0, 160], [0, 410, 120], [0, 0, 1]])
    return K.repeat(n, 1, 1)


def slab_surface(size: tuple[int, int], poses: torch.Tensor | None = None, K: torch.Tensor | None = None) -> Surface:
    """The visible surface of a render at ``poses`` (default: two of :func:`random_poses`): a slab
    1.5 m away over the crop's middle."""
    poses = random_poses(2, 3) if poses is None else poses
    w, h = size
    depth = torch.zeros(len(poses), h, w)
    depth[:, h // 4 : 3 * h // 4, w // 4 : 3 * w // 4] = 1.5
    K = crop_K(len(poses)) * torch.tensor([[w / 320], [h / 240], [1.0]]) if K is None else K
    return render_surface(depth, poses, K)


# ---- shared fixtures ----


@pytest.fixture(scope="session")
def panda() -> RobotModel:
    return RobotModel("panda")


@pytest.fixture(scope="session")
def frames(tiny_dream):
    """The frames of :func:`tiny_dream`."""
    from monose3.data.datasets import open_dataset

    return open_dataset(tiny_dream, "panda")


@pytest.fixture(scope="module")
def tiny():
    """A randomly initialised small denoiser (zero head: every update is the identity) with a
    short reverse process, so a frame costs a few small network calls; images of 160x120."""
    from monose3.estimator import PoseEstimator

    config = with_section(
        get_preset("cpu"), "network", backbone="resnet18", render_size=(64, 48), input_size=(160, 120)
    )
    config = with_section(config, "inference", ddim_steps=1, direct_steps=1)
    estimator = PoseEstimator(build_denoiser(config.network), config)
    yield estimator
    estimator.close()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, tiny):
    """:func:`tiny`'s weights as a checkpoint file."""
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, {"model": tiny.model.state_dict(), "config": tiny.config.to_dict(), "robot": "panda"})
    return path
