"""pybullet as an independent reference renderer (optional: ``pip install pybullet``).

monose3 renders with its own batched PyTorch renderer (:mod:`monose3.robot.renderer`);
pybullet serves the tests that check that renderer's silhouettes and ``monose3 generate
--renderer tiny|egl``, which makes evaluation sets with another renderer than the one the
model was trained on (our stand-in for the synthetic-to-real gap). Same interface:
:class:`~monose3.robot.jobs.RenderJob` in, ``(rgb, mask)`` out. Poses are camera-from-base
in OpenCV axes; intrinsics are pixel-centre OpenCV intrinsics.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from monose3.errors import Monose3Error
from monose3.robot import RobotModel, RobotSpec
from monose3.robot.jobs import RenderJob

try:
    import pybullet as pb
except ImportError:  # pragma: no cover - exercised where pybullet is not installed
    pb = None

NEAR, FAR = 0.01, 30.0
# OpenCV camera axes -> OpenGL camera axes (y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def projection_matrix(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenGL projection whose NDC maps exactly onto OpenCV pixel centres of ``K``.

    Pixel u (centre at integer u) covers NDC x in [2u/W - 1, 2(u+1)/W - 1], hence the +0.5.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array(
        [
            [2 * fx / width, 0.0, 1.0 - 2.0 * (cx + 0.5) / width, 0.0],
            [0.0, 2 * fy / height, 2.0 * (cy + 0.5) / height - 1.0, 0.0],
            [0.0, 0.0, -(FAR + NEAR) / (FAR - NEAR), -2.0 * FAR * NEAR / (FAR - NEAR)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


def _egl_available() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except ImportError:  # pragma: no cover - torch is a dependency
        return False


def resolve_backend(backend: str) -> str:
    """'auto' -> 'egl' with a GPU, else 'tiny' (pybullet's CPU TinyRenderer). Pools resolve it
    in the parent so that worker processes need not import torch to find out."""
    if backend not in ("auto", "egl", "tiny"):
        raise Monose3Error(f"unknown render backend {backend!r}; use auto, egl or tiny")
    if pb is None:
        raise Monose3Error("the pybullet renderer needs pybullet: pip install pybullet (Python 3.11)")
    if backend == "auto":
        return "egl" if _egl_available() else "tiny"
    return backend


# The built-in robots ship simplified meshes; pybullet renders its own full-resolution originals.
PYBULLET_URDFS = {"panda": "franka_panda/panda.urdf", "kuka": "kuka_iiwa/model.urdf"}


def pybullet_urdf(spec: RobotSpec) -> str:
    """The URDF pybullet loads for ``spec``: pybullet_data's original for a built-in robot."""
    if spec.mesh_asset and spec.name in PYBULLET_URDFS:
        import pybullet_data

        return str(Path(pybullet_data.getDataPath()) / PYBULLET_URDFS[spec.name])
    return spec.urdf


class Renderer:
    """A pybullet client holding one robot. Not thread-safe; one per process."""

    def __init__(self, robot: str | RobotSpec | RobotModel = "panda", backend: str = "auto"):
        backend = resolve_backend(backend)  # a missing pybullet fails here, in one line
        self.model = robot if isinstance(robot, RobotModel) else RobotModel(robot)
        self.client = pb.connect(pb.DIRECT)
        self.hardware = backend == "egl"
        if self.hardware:
            self._load_egl()
        try:
            self.body = pb.loadURDF(pybullet_urdf(self.model.spec), useFixedBase=True, physicsClientId=self.client)
        except pb.error as err:
            raise Monose3Error(
                f"pybullet cannot load {pybullet_urdf(self.model.spec)}: {err}; check the URDF and its meshes"
            ) from None
        self._joint_ids = {}
        for i in range(pb.getNumJoints(self.body, physicsClientId=self.client)):
            info = pb.getJointInfo(self.body, i, physicsClientId=self.client)
            self._joint_ids[info[1].decode()] = i
        self._base_offset = self._root_link_offset()

    def _load_egl(self) -> None:
        import pkgutil

        egl = pkgutil.get_loader("eglRenderer")
        if egl is None or pb.loadPlugin(egl.get_filename(), "_eglRendererPlugin", physicsClientId=self.client) < 0:
            self.hardware = False

    def _root_link_offset(self) -> np.ndarray:
        """World pose of the URDF root link: pybullet's base pose is the base's inertial frame."""
        pos, orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        inertial = pb.getDynamicsInfo(self.body, -1, physicsClientId=self.client)
        inv_pos, inv_orn = pb.invertTransform(inertial[3], inertial[4])
        pos, orn = pb.multiplyTransforms(pos, orn, inv_pos, inv_orn)
        pose = np.eye(4)
        pose[:3, :3] = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        pose[:3, 3] = pos
        return pose

    def set_joints(self, joints: np.ndarray) -> None:
        for name, value in self.model.all_joint_values(joints).items():
            pb.resetJointState(self.body, self._joint_ids[name], float(value[0]), physicsClientId=self.client)

    def link_world_poses(self) -> dict[str, np.ndarray]:
        """pybullet's own link frames, expressed relative to the root link (used by tests)."""
        base_inv = np.linalg.inv(self._base_offset)
        out = {self.model.root: np.eye(4)}
        for i in range(pb.getNumJoints(self.body, physicsClientId=self.client)):
            st = pb.getLinkState(self.body, i, computeForwardKinematics=True, physicsClientId=self.client)
            pose = np.eye(4)
            pose[:3, :3] = np.array(pb.getMatrixFromQuaternion(st[5])).reshape(3, 3)
            pose[:3, 3] = st[4]
            name = pb.getJointInfo(self.body, i, physicsClientId=self.client)[12].decode()
            out[name] = base_inv @ pose
        return out

    def render(self, job: RenderJob) -> tuple[np.ndarray, np.ndarray]:
        """RGB ``[H, W, 3]`` uint8 on black and the robot mask ``[H, W]`` bool."""
        width, height = job.size
        self.set_joints(job.joints)
        cam_from_world = job.pose @ np.linalg.inv(self._base_offset)
        view = (_CV_TO_GL @ cam_from_world).T.reshape(-1)
        K = np.array(job.K, np.float64)
        if not self.hardware:
            # TinyRenderer covers pixel (u, row) when the screen point (u, H-1-row) is inside a
            # triangle, not the pixel centre (u+0.5, H-row-0.5) as OpenGL does: shift the principal
            # point by half a pixel so both back-ends follow the OpenCV pixel-centre convention.
            K[0, 2] -= 0.5
            K[1, 2] += 0.5
        proj = projection_matrix(K, width, height).T.reshape(-1)
        light = job.lighting
        # Lighting is given in the camera frame; pybullet wants it in its world frame.
        light_world = np.linalg.inv(cam_from_world)[:3, :3] @ np.asarray(light.direction, float)
        _, _, rgba, _, seg = pb.getCameraImage(
            width,
            height,
            viewMatrix=view.tolist(),
            projectionMatrix=proj.tolist(),
            lightDirection=light_world.tolist(),
            lightColor=list(light.color),
            lightAmbientCoeff=light.ambient,
            lightDiffuseCoeff=light.diffuse,
            lightSpecularCoeff=light.specular,
            shadow=0,
            renderer=pb.ER_BULLET_HARDWARE_OPENGL if self.hardware else pb.ER_TINY_RENDERER,
            physicsClientId=self.client,
        )
        rgba = np.asarray(rgba, np.uint8).reshape(height, width, 4)
        mask = np.asarray(seg).reshape(height, width) >= 0
        rgb = np.where(mask[..., None], rgba[..., :3], 0).astype(np.uint8)
        return rgb, mask

    def close(self) -> None:
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1


_WORKER: Renderer | None = None


def _init_worker(robot: RobotSpec, backend: str) -> None:
    global _WORKER
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER = Renderer(robot, backend)


def _render_in_worker(job: RenderJob) -> tuple[np.ndarray, np.ndarray]:
    assert _WORKER is not None
    return _WORKER.render(job)


class RendererPool:
    """Renders batches over worker processes, each with its own pybullet client.

    ``workers=0`` renders in the calling process (no start-up cost, one core).
    """

    def __init__(self, robot: str | RobotSpec = "panda", workers: int | None = None, backend: str = "auto"):
        spec = robot.spec if isinstance(robot, RobotModel) else robot
        self.model = RobotModel(spec)
        self.workers = os.cpu_count() or 1 if workers is None else workers
        backend = resolve_backend(backend)
        if self.workers == 0:
            self._local: Renderer | None = Renderer(self.model, backend)
            self._pool = None
        else:
            self._local = None
            ctx = mp.get_context("spawn")
            self._pool = ctx.Pool(self.workers, initializer=_init_worker, initargs=(self.model.spec, backend))

    def render(self, jobs: Sequence[RenderJob]) -> list[tuple[np.ndarray, np.ndarray]]:
        if self._pool is None:
            return [self._local.render(j) for j in jobs]
        chunk = max(1, len(jobs) // (4 * self.workers))
        return self._pool.map(_render_in_worker, jobs, chunksize=chunk)

    def imap(self, jobs: Iterable[RenderJob]) -> Iterable[tuple[np.ndarray, np.ndarray]]:
        if self._pool is None:
            return (self._local.render(j) for j in jobs)
        return self._pool.imap(_render_in_worker, jobs, chunksize=4)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None
        if self._local is not None:
            self._local.close()

    def __enter__(self) -> RendererPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
