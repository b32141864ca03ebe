"""The paper's pipeline (Alg. 2): RoboPose's initialisation, K timestep-aware DDIM steps
(RevDiff, Eq. 8 through :class:`~monose3.method.scheduler.DDIMScheduler`), M direct-regression
steps, the DirectReg baseline and 1-step tracking. Batched over images and hypotheses: one render
batch and one network call per step. ``monose3.estimator.PoseEstimator`` offers it beside the fit."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from monose3.errors import Monose3Error
from monose3.geometry.camera import project, standardize_image
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix, rotation_angle
from monose3.method.config import Config
from monose3.method.denoiser import Denoiser
from monose3.method.evidence import Evidence, evidence_crops, keypoints_ref, render_maps
from monose3.method.flow_pose import render_surface
from monose3.method.pose_space import base_frame, centroid_frame
from monose3.method.render_compare import crop_batch, crop_geometry, image_to_tensor
from monose3.method.scheduler import DDIMScheduler
from monose3.method.update import apply_update, raw_to_update
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer

# RoboPose's fixed initial orientation (camera-from-reference-point): the robot seen from the front.
INIT_ROTATION = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
INIT_BOX_FRACTION = 3 / 5
# Chains that disagree by more than this (mean keypoint distance to the chosen chain) are
# flagged unreliable; see benchmarks/uncertainty.py for what the threshold catches.
UNRELIABLE_MM = 30.0


@dataclass
class Chains:
    """The reverse process's result for B images with H chains each (camera-from-base, metres)."""

    poses: np.ndarray  # [B, 4, 4] each image's medoid chain
    hypotheses: np.ndarray  # [B, H, 4, 4] every chain's end
    in_view: np.ndarray  # [B] bool: the estimate keeps the robot's centroid in the image, in front
    spread_mm: np.ndarray  # [B] mean keypoint distance of the chains to the chosen one
    spread_deg: np.ndarray  # [B] mean rotation angle of the chains to the chosen one
    history: list[np.ndarray] = field(default_factory=list)  # per step [B, H, 4, 4]
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class PreparedBatch:
    """The inputs of :meth:`PoseEstimator.estimate` brought to the network's image size, one row per hypothesis."""

    images: torch.Tensor  # [N, 3, H, W] standardized, one row per hypothesis
    K: torch.Tensor  # [N, 3, 3] of the standardized image
    size: torch.Tensor  # [N, 2]
    joints: np.ndarray  # [N, n]
    points_ref: torch.Tensor  # [N, P, 3]
    centroid: torch.Tensor  # [N, 3]
    evidence: Evidence | None = None  # the parser's, for a denoiser that reads it (one row per hypothesis)
    keypoints_ref: torch.Tensor | None = None  # [N, K, 3] the robot's keypoints in the centroid frame


def check_steps(sampler: str, ddim_steps: int, direct_steps: int) -> None:
    """One line for step counts the reverse process cannot run (before any work)."""
    if sampler not in ("revdiff", "directreg"):
        raise Monose3Error(f"unknown sampler {sampler!r}; choose fit, revdiff or directreg")
    if min(ddim_steps, direct_steps) < 0:
        raise Monose3Error(f"step counts cannot be negative (ddim_steps={ddim_steps}, direct_steps={direct_steps})")
    if sampler == "revdiff" and ddim_steps < 1:
        raise Monose3Error("revdiff needs ddim_steps >= 1; for direct steps only use sampler='directreg'")
    if ddim_steps + direct_steps < 1:
        raise Monose3Error("directreg needs at least one step (ddim_steps + direct_steps >= 1)")


class ReverseDiffusion:
    """A trained denoiser, its scheduler and the batched renderer on the model's device; :meth:`run`
    is Alg. 2 (or DirectReg) over a batch of images whose inputs were checked by the caller."""

    def __init__(self, model: Denoiser, config: Config, robot: RobotModel, renderer: RobotRenderer):
        self.model = model
        self.config = config
        self.robot = robot
        self.renderer = renderer
        self.device = renderer.device
        self.scheduler = DDIMScheduler(config.diffusion)
        self.timings: dict[str, float] = defaultdict(float)

    # ---- inputs ---------------------------------------------------------------------------

    def prepare(self, images: list[np.ndarray], Ks: np.ndarray, joints: np.ndarray, hyps: int,
                evidence: Evidence | None = None) -> PreparedBatch:  # fmt: skip
        """Standardise the images (and their K) to ``network.input_size``; ``hyps`` rows per image
        (and of ``evidence``, the parser's in the standardised images, where the denoiser reads it)."""
        if self.model.inputs == "parser" and evidence is None:
            raise Monose3Error(
                "the evidence denoiser reads the robot parser's evidence: load the estimator with a parser"
            )
        size = self.config.network.input_size
        std_images, std_K = [], []
        for img, K in zip(images, Ks, strict=True):
            im, k = standardize_image(img, np.asarray(K, np.float64), size)
            std_images.append(image_to_tensor(im))
            std_K.append(k)
        joints = np.asarray(joints, np.float64)
        points = self.robot.surface_points(joints)
        centroid = self.robot.centroid(points)
        rep = lambda x: x.repeat_interleave(hyps, 0)  # noqa: E731
        return PreparedBatch(
            images=rep(torch.stack(std_images)).to(self.device),  # crops then run on the model's device
            K=rep(torch.from_numpy(np.stack(std_K))),
            size=torch.tensor([size], dtype=torch.float64).repeat(len(images) * hyps, 1),
            joints=np.repeat(joints, hyps, axis=0),
            points_ref=rep(torch.from_numpy(points - centroid[:, None])),
            centroid=rep(torch.from_numpy(centroid)),
            evidence=None if evidence is None else evidence.map(rep),
            keypoints_ref=rep(keypoints_ref(self.robot, joints, centroid)),
        )

    def initial_poses(self, batch: PreparedBatch) -> torch.Tensor:
        """RoboPose's identity initialisation (camera-from-centroid): fixed rotation, the robot
        fitted to a box over the central 3/5 of the image."""
        n = len(batch.K)
        rot = INIT_ROTATION.expand(n, 3, 3)
        pts = batch.points_ref @ rot.transpose(1, 2)
        extent = pts.amax(1) - pts.amin(1)
        box = batch.size * INIT_BOX_FRACTION
        f = torch.stack([batch.K[:, 0, 0], batch.K[:, 1, 1]], 1)
        z = (f * extent[:, :2] / box).amax(1)
        center = batch.size / 2 - 0.5
        xy = (center - batch.K[:, :2, 2]) * z[:, None] / f
        return make_pose(rot, torch.cat([xy, z[:, None]], 1))

    @contextmanager
    def timed(self, key: str) -> Iterator[None]:
        """Add the seconds the block takes to ``self.timings[key]``."""
        tick = time.perf_counter()
        yield
        self.timings[key] += time.perf_counter() - tick

    @torch.no_grad()
    def predict_x0(self, batch: PreparedBatch, pose_ref: torch.Tensor, t: int) -> torch.Tensor:
        """The denoiser's H_0 prediction (Eq. 9) at ``pose_ref`` = H_t, camera-from-centroid ``[N, 4, 4]``."""
        net = self.config.network
        with self.timed("crop"):
            boxes, K_crop = crop_geometry(pose_ref, batch.points_ref, batch.K, net.render_size)
        render, crops, depth = self.compared(batch, pose_ref, boxes, K_crop.to(self.device))
        with self.timed("network"):
            steps = torch.full((len(pose_ref),), t, dtype=torch.long, device=self.device)
            surface = render_surface(depth, pose_ref.to(self.device).float(), K_crop.to(self.device).float())
            surface.keypoints_ref = batch.keypoints_ref.to(self.device)
            raw = self.model(render, crops.to(self.device), steps, surface).raw.double().cpu()
        with self.timed("update"):
            v_xy, d_rot, v_z = raw_to_update(raw, net.render_size[0])
            return apply_update(pose_ref, v_xy, d_rot, v_z, K_crop)

    def compared(self, batch: PreparedBatch, pose_ref: torch.Tensor, boxes: torch.Tensor,
                 K_crop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
        """What the denoiser compares at H_t = ``pose_ref``: the render and the crop (the image's
        pixels; or, for the evidence denoiser, the silhouette and keypoints against the parser's
        evidence: :mod:`monose3.method.evidence`), and the render's depth."""
        size, evidence = self.config.network.render_size, self.model.inputs == "parser"
        with self.timed("render"):
            pose_base = base_frame(pose_ref, batch.centroid).to(self.device)
            rendered = self.renderer.render(batch.joints, pose_base, K_crop, size, shade=not evidence)
            render = rendered.rgb
            if evidence:
                kp_cam = torch.from_numpy(self.robot.keypoints(batch.joints, pose_base.cpu().numpy()))
                render = render_maps(rendered.mask, kp_cam.to(self.device), K_crop)
        with self.timed("crop"):
            if evidence:
                crops = evidence_crops(batch.evidence, boxes, size)
            else:
                crops = crop_batch(batch.images, boxes.to(self.device), size)
        return render, crops, rendered.depth

    # ---- Alg. 2 -----------------------------------------------------------------------------

    def run(
        self,
        images: list[np.ndarray],
        Ks: np.ndarray,
        joints: np.ndarray,
        sampler: str,
        ddim_steps: int | None = None,
        direct_steps: int | None = None,
        hypotheses: int = 1,
        stochastic: bool = False,
        seed: int = 0,
        init_poses: np.ndarray | None = None,
        start_t: int | None = None,
        evidence: Evidence | None = None,
    ) -> Chains:
        """'revdiff' (K DDIM + M direct steps, the paper) or 'directreg' (K + M direct steps, the
        baseline) from RoboPose's initialisation or ``init_poses`` ``[B, 4, 4]``; ``stochastic``
        adds DDIM's noise term and perturbs the starts (several chains -> uncertainty)."""
        inf = self.config.inference
        ddim_steps = inf.ddim_steps if ddim_steps is None else ddim_steps
        direct_steps = inf.direct_steps if direct_steps is None else direct_steps
        check_steps(sampler, ddim_steps, direct_steps)
        self.timings = defaultdict(float)
        start = time.perf_counter()
        batch = self.prepare(images, Ks, joints, hypotheses, evidence)
        gen = torch.Generator().manual_seed(seed) if stochastic else None
        if init_poses is None:
            pose = self.initial_poses(batch)
        else:
            # Standardising the image changes K only: a 3D pose means the same in both cameras.
            init = np.repeat(np.asarray(init_poses, np.float64), hypotheses, 0)
            pose = centroid_frame(torch.from_numpy(init), batch.centroid)
        if stochastic:
            pose = self.perturb(pose, gen, start_t)
        history = [pose]
        if sampler == "revdiff":  # Alg. 2: K timestep-aware DDIM steps (Eq. 8) over the scheduler
            steps = self.scheduler.timesteps(ddim_steps, start_t)
            for t, t_prev in zip(steps, [*steps[1:], 0], strict=True):
                x0 = self.predict_x0(batch, pose, t)
                with self.timed("update"):
                    pose = self.scheduler.step(x0, t, t_prev, pose, batch.K, batch.size, inf.eta, gen)
                history.append(pose)
        else:  # directreg (check_steps refused anything else)
            direct_steps += ddim_steps
        for _ in range(direct_steps):
            pose = self.predict_x0(batch, pose, 1)
            history.append(pose)
        result = self.finish(batch, history, len(images), hypotheses)
        result.timings["total"] = time.perf_counter() - start
        return result

    def perturb(self, pose: torch.Tensor, gen: torch.Generator, start_t: int | None) -> torch.Tensor:
        """Spread the chains' starts: 0.15 rad per axis and 5 % of the translation from t = T,
        shrunk like the forward process's noise std sqrt(1 - alpha_bar_t) when the chains start
        lower (refining a prior), so a good prior is not thrown further than the noise at t."""
        ab = self.scheduler.alpha_bar
        t = self.scheduler.num_steps if start_t is None else start_t
        scale = float(torch.sqrt((1 - ab[t]) / (1 - ab[-1])))
        n = len(pose)
        rot = euler_xyz_to_matrix(torch.randn(n, 3, generator=gen, dtype=pose.dtype) * 0.15 * scale)
        out = pose.clone()
        out[:, :3, :3] = rot @ pose[:, :3, :3]
        out[:, :3, 3] = pose[:, :3, 3] * (1 + 0.05 * scale * torch.randn(n, 3, generator=gen, dtype=pose.dtype))
        return out

    def finish(self, batch: PreparedBatch, history: list[torch.Tensor], n_images: int, hyps: int) -> Chains:
        """The :class:`Chains` of the poses ``history`` (camera-from-centroid, per step): each
        image's medoid hypothesis, the spread of its hypotheses and whether it is in view."""
        to_base = [base_frame(p, batch.centroid).numpy().reshape(n_images, hyps, 4, 4) for p in history]
        final = to_base[-1]
        kps = self.robot.keypoints(batch.joints[::hyps])  # [B, K, 3]
        chosen, spread_mm, spread_deg = [], [], []
        for b in range(n_images):
            cam = np.einsum("hij,kj->hki", final[b, :, :3, :3], kps[b]) + final[b, :, None, :3, 3]
            dist = np.linalg.norm(cam[:, None] - cam[None], axis=-1).mean(-1)  # [H, H]
            m = int(np.argmin(dist.sum(1)))
            chosen.append(final[b, m])
            spread_mm.append(1000 * dist[m].sum() / max(1, hyps - 1))
            ang = np.degrees(rotation_angle(final[b, :, :3, :3], final[b, m, :3, :3]))
            spread_deg.append(ang.sum() / max(1, hyps - 1))
        poses = np.stack(chosen)
        ref = centroid_frame(torch.from_numpy(poses), batch.centroid[::hyps])
        uv = project(ref[:, None, :3, 3], batch.K[::hyps])[:, 0]
        size = batch.size[::hyps]
        in_view = (ref[:, 2, 3] > 0) & (uv >= -0.5).all(1) & (uv <= size - 0.5).all(1)
        return Chains(
            poses=poses,
            hypotheses=final,
            in_view=in_view.numpy(),
            spread_mm=np.asarray(spread_mm),
            spread_deg=np.asarray(spread_deg),
            history=to_base,
            timings=dict(self.timings),
        )
