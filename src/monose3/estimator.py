"""The estimator above both pipelines: :class:`PoseEstimator` loads nothing itself, checks every
input once, and sends each batch to the geometric fit on the robot parser's evidence
(:mod:`monose3.perception`, the "fit" sampler, the default when there is a parser) or to the
paper's reverse diffusion (:mod:`monose3.method.reverse`, "revdiff" and "directreg"). Both
answer with one :class:`Estimate`."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from monose3.data.validation import check_batch, check_pose_batch
from monose3.errors import Monose3Error
from monose3.geometry.camera import padded_size
from monose3.method.config import Config
from monose3.method.denoiser import Denoiser
from monose3.method.evidence import Evidence
from monose3.method.reverse import UNRELIABLE_MM, Chains, ReverseDiffusion
from monose3.perception.fit_result import Fit
from monose3.perception.fitting import fit_pose
from monose3.perception.from_pose import judge_poses, track_pose
from monose3.perception.parser import RobotParser
from monose3.perception.reliability import fit_doubts, pose_in_view
from monose3.perception.views import MIN_MASK_FRACTION, ViewEvidence, parse_image
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer

__all__ = ["UNRELIABLE_MM", "Estimate", "PoseEstimator"]


@dataclass
class Estimate:
    """Results for a batch of B images with H hypotheses each (poses are camera-from-base,
    in the caller's original camera, metres)."""

    poses: np.ndarray  # [B, 4, 4] the chosen estimate (medoid of the hypotheses)
    hypotheses: np.ndarray  # [B, H, 4, 4]
    in_view: np.ndarray  # [B] bool: the estimate keeps the robot's centroid in the image, in front
    spread_mm: np.ndarray  # [B] mean keypoint distance of the hypotheses to the chosen one
    spread_deg: np.ndarray  # [B] mean rotation angle of the hypotheses to the chosen one
    history: list[np.ndarray] = field(default_factory=list)  # per step [B, H, 4, 4]
    timings: dict[str, float] = field(default_factory=dict)
    # The "fit" sampler's (perception.fitting) fit per image; None for the paper's samplers.
    fit_iou: np.ndarray | None = None  # [B] silhouette IoU of the estimate with the parser's mask
    keypoint_px: np.ndarray | None = None  # [B] keypoint reprojection error, parser-view pixels
    found: np.ndarray | None = None  # [B] bool: the parser found the robot (else the pose is NaN)
    reliable: np.ndarray | None = None  # [B] bool: the fit is good and the robot mostly in the image
    edge_support: np.ndarray | None = None  # [B] share of the estimate's outline on the image's edges
    edge_distance_px: np.ndarray | None = None  # [B] RMS distance of that outline to the edges, parser-view pixels
    doubts: list[list[str]] | None = None  # [B] why each estimate is unreliable, in words (empty: reliable)
    fit_score: np.ndarray | None = None  # [B] the fit's score (fitting.best_fit): higher fits better

    @classmethod
    def of_chains(cls, chains: Chains) -> Estimate:
        """The paper's samplers' result (no fit numbers: the chains' spread is their confidence)."""
        return cls(**vars(chains))


def evidence_of(views: list[ViewEvidence], image_sizes: list[tuple[int, int]], input_size: tuple[int, int]) -> Evidence:
    """The parser's views of B images (``image_sizes`` (w, h) each) as the evidence denoiser reads
    them: in the standardised image of ``input_size`` (padded right/bottom to its aspect, then
    resized: :func:`~monose3.geometry.camera.standardize_image`), edge coordinates scaled alike."""
    boxes, keypoints = [], []
    for view, (w, h) in zip(views, image_sizes, strict=True):
        scale = input_size[0] / padded_size((w, h), input_size)[0]
        per_pixel = (view.box[2:] - view.box[:2]) / np.array(view.size)
        boxes.append(view.box * scale)
        keypoints.append((view.box[:2] + (view.keypoints + 0.5) * per_pixel) * scale - 0.5)
    return Evidence(
        mask=torch.stack([view.mask.float() for view in views])[:, None],
        box=torch.from_numpy(np.stack(boxes)),
        keypoints=torch.from_numpy(np.stack(keypoints)),
        confidence=torch.from_numpy(np.stack([view.confidence for view in views]).astype(np.float32)),
    )


class PoseEstimator:
    """A trained denoiser plus the batched renderer on the model's device, and optionally a
    robot parser (the "fit" sampler, the default when there is one); call :meth:`estimate` or :meth:`track`."""

    def __init__(self, model: Denoiser, config: Config, device: str = "cpu", parser: RobotParser | None = None):
        self.parser = None if parser is None else parser.to(device).eval()
        self.config = config
        self.robot = RobotModel(config.robot)
        self.renderer = RobotRenderer(self.robot, device)
        self.reverse = ReverseDiffusion(model.to(device).eval(), config, self.robot, self.renderer)

    @property
    def model(self) -> Denoiser:
        return self.reverse.model

    @property
    def device(self):
        return self.renderer.device

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per stage of the last reverse-process call (render, crop, network, update)."""
        return self.reverse.timings

    @property
    def default_sampler(self) -> str:
        """ "fit" (parser + geometry) when the estimator has a parser, else the paper's "revdiff"."""
        return "fit" if self.parser is not None else "revdiff"

    def close(self) -> None:
        """Free the renderer's cached mesh tensors (GPU memory when on CUDA)."""
        self.renderer.release()

    def estimate(
        self,
        images: list[np.ndarray],
        Ks: np.ndarray,
        joints: np.ndarray,
        sampler: str | None = None,
        ddim_steps: int | None = None,
        direct_steps: int | None = None,
        hypotheses: int = 1,
        stochastic: bool = False,
        seed: int = 0,
        init_poses: np.ndarray | None = None,
        start_t: int | None = None,
    ) -> Estimate:
        """Estimate camera-from-base for each image. ``sampler``: 'fit' (the robot parser, PnP,
        silhouette scoring and refinement: :mod:`monose3.perception.fitting`; ``init_poses``
        join its hypotheses), 'revdiff' (K DDIM + M direct steps, the paper) or 'directreg'
        (K + M direct steps, the baseline); default :attr:`default_sampler`. ``stochastic``
        adds DDIM's noise term and perturbs the initial poses (several chains -> uncertainty).
        ``init_poses`` ``[B, 4, 4]`` replace RoboPose's initialisation (tracking)."""
        images, Ks, joints = check_batch(images, Ks, joints, self.robot)  # Monose3Error, not a crash in roi_align
        sampler = sampler or self.default_sampler
        if sampler == "fit":
            return self.fit(images, Ks, joints, init_poses)
        views = self.parse(images, Ks) if self.reverse.model.inputs == "parser" else None
        evidence = None if views is None else evidence_of(views, [im.shape[1::-1] for im in images], self.input_size)
        chains = self.reverse.run(images, Ks, joints, sampler, ddim_steps, direct_steps, hypotheses, stochastic, seed,
                                  init_poses, start_t, evidence)  # fmt: skip
        result = Estimate.of_chains(chains)
        if views is not None:
            result.found = np.array([view.robot_fraction >= MIN_MASK_FRACTION for view in views])
            result.in_view &= result.found
        return result

    @property
    def input_size(self) -> tuple[int, int]:
        return self.config.network.input_size

    def parse(self, images: list[np.ndarray], Ks: np.ndarray) -> list[ViewEvidence]:
        """The robot parser's view of each image (whole, then zoomed on the robot: ``views.parse_image``)."""
        if self.parser is None:
            raise Monose3Error(
                f"no robot parser for {self.robot.name}: the evidence denoiser reads its evidence (--parser FILE)"
            )
        return [parse_image(self.parser, image, K) for image, K in zip(images, Ks, strict=True)]

    def fit(
        self, images: list[np.ndarray], Ks: np.ndarray, joints: np.ndarray, priors: np.ndarray | None = None,
        track: bool = False,
    ) -> Estimate:  # fmt: skip
        """The "fit" sampler, image by image (``priors`` ``[B, 4, 4]`` join the hypotheses; with
        ``track`` they are only refined, from a view around them: tracking)."""
        if self.parser is None:
            raise Monose3Error(
                f"no robot parser for {self.robot.name}: the 'fit' sampler needs one (--parser FILE); "
                "or use --sampler revdiff"
            )
        start = time.perf_counter()
        fits = []
        for i, (image, K, q) in enumerate(zip(images, Ks, joints, strict=True)):
            prior = None if priors is None else np.asarray(priors[i], np.float64)
            if track:
                fits.append(track_pose(self.parser, self.renderer, self.robot, image, K, q, prior))
            else:
                extra = None if prior is None else prior[None]
                fits.append(fit_pose(self.parser, self.renderer, self.robot, image, K, q, extra))
        return self._fit_estimate(fits, images, Ks, joints, time.perf_counter() - start)

    def _fit_estimate(self, fits: list[Fit], images, Ks, joints, seconds: float) -> Estimate:
        poses = np.stack([f.pose for f in fits])
        hyps = max(1, max(len(f.candidates) for f in fits))
        candidates = np.full((len(fits), hyps, 4, 4), np.nan)
        for i, f in enumerate(fits):
            candidates[i, : len(f.candidates)] = f.candidates
        found = np.array([f.found for f in fits])
        views = list(zip(poses, joints, Ks, [img.shape for img in images], strict=True))
        in_view = found & np.array([pose_in_view(self.robot, *v) for v in views])
        doubts = [fit_doubts(fit, self.robot, *v[1:]) for fit, v in zip(fits, views, strict=True)]
        return Estimate(
            poses=poses,
            hypotheses=candidates,
            in_view=in_view,
            spread_mm=np.array([f.spread_mm for f in fits]),
            spread_deg=np.zeros(len(fits)),
            history=[candidates],
            timings={"total": seconds},
            fit_iou=np.array([f.iou for f in fits]),
            keypoint_px=np.array([f.keypoint_error for f in fits]),
            found=found,
            reliable=in_view & np.array([not reasons for reasons in doubts]),
            edge_support=np.array([f.edge_support for f in fits]),
            edge_distance_px=np.array([f.edge_distance_px for f in fits]),
            doubts=doubts,
            fit_score=np.array([f.score for f in fits]),
        )

    def judge(self, image: np.ndarray, K: np.ndarray, joints: np.ndarray, poses: np.ndarray) -> Estimate:
        """How well each of ``poses`` ``[N, 4, 4]`` fits one image as it stands (nothing is refined):
        all fitted to the same parser view, so their ``fit_score``, ``fit_iou`` and ``reliable``
        compare (:func:`~monose3.perception.from_pose.judge_poses`). Needs the robot parser."""
        images, Ks, q = check_batch([image], np.asarray(K, np.float64)[None], np.asarray(joints)[None], self.robot)
        poses = check_pose_batch(poses, len(poses), "pose to judge")
        if self.parser is None:
            raise Monose3Error(f"no robot parser for {self.robot.name}: judging a pose needs one (--parser FILE)")
        start = time.perf_counter()
        fits = judge_poses(self.parser, self.renderer, self.robot, images[0], Ks[0], q[0], poses)
        n = len(poses)
        return self._fit_estimate(
            fits, images * n, np.repeat(Ks, n, 0), np.repeat(q, n, 0), time.perf_counter() - start
        )

    def track(
        self, images: list[np.ndarray], Ks: np.ndarray, joints: np.ndarray, previous: np.ndarray,
        sampler: str | None = None,
    ) -> Estimate:  # fmt: skip
        """Tracking: from the previous estimates, the paper's one step at a small t
        (``sampler`` 'revdiff'), or a few refinement iterations on a parser view around them ('fit')."""
        images, Ks, joints = check_batch(images, Ks, joints, self.robot)
        previous = check_pose_batch(previous, len(images), "previous pose")
        if (sampler or self.default_sampler) == "fit":
            return self.fit(images, Ks, joints, previous, track=True)
        return self.estimate(
            images,
            Ks,
            joints,
            sampler="revdiff",
            ddim_steps=1,
            direct_steps=0,
            init_poses=previous,
            start_t=self.config.inference.tracking_t,
        )
