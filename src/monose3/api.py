"""The Python API, mirroring the CLI: load the shipped model in one call, estimate from an
image array, joints and K, draw the overlay (``monose3 estimate`` is the same, in
:mod:`monose3.apps.estimate`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from monose3 import atomic
from monose3.data import validation
from monose3.errors import Monose3Error
from monose3.estimator import UNRELIABLE_MM, Estimate, PoseEstimator  # noqa: F401 - UNRELIABLE_MM: the shipped chains threshold, read from here
from monose3.report.overlays import pose_overlays
from monose3.robot.renderer import RobotRenderer
from monose3.tracking import estimate_quality
from monose3.training.checkpoints import load_model, load_parser
from monose3.training.formats import BUNDLED_CHECKPOINT, BUNDLED_PARSER, BUNDLED_PARSER_ROBOT, check_checkpoint

ASSETS = Path(__file__).parent / "assets"


def load_estimator(
    checkpoint: str | Path | None = None,
    robot: str | None = None,
    device: str = "auto",
    parser: str | Path | None = None,
) -> PoseEstimator:
    """The estimator for a checkpoint (default: the Panda model shipped in the package) with a
    robot parser (``parser``: its weights; default the bundled Panda parser for the Panda, none
    for other robots, which then have the paper's samplers only)."""
    import torch

    # An unknown robot, a missing bundled model, a folder, another robot's checkpoint: refused
    # here, before torch.load.
    check_checkpoint(checkpoint, robot)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    model, config = load_model(checkpoint or BUNDLED_CHECKPOINT, robot=robot, device=device)
    if parser is None and config.robot == BUNDLED_PARSER_ROBOT:
        parser = BUNDLED_PARSER
    robot_parser = None if parser is None else load_parser(parser, device)
    if robot_parser is not None and robot_parser.config.robot != config.robot:
        raise Monose3Error(
            f"parser {Path(parser).name} is for robot {robot_parser.config.robot!r}, the model for {config.robot!r}"
        )
    return PoseEstimator(model, config, device=device, parser=robot_parser)


@dataclass
class PoseResult:
    """One estimate. ``camera_from_base`` maps base-frame points (metres) into the camera frame."""

    camera_from_base: np.ndarray
    spread_mm: float
    spread_deg: float
    chains: int
    estimate: Estimate
    sampler: str = "revdiff"

    @property
    def base_from_camera(self) -> np.ndarray:
        return np.linalg.inv(self.camera_from_base)

    @property
    def fit_iou(self) -> float | None:
        """The "fit" sampler's silhouette IoU with the parser's mask; None for the paper's samplers."""
        return None if self.estimate.fit_iou is None else float(self.estimate.fit_iou[0])

    @property
    def edge_support(self) -> float | None:
        """The "fit" sampler's share of the estimate's outline that lies on the image's own edges; None otherwise."""
        return None if self.estimate.edge_support is None else float(self.estimate.edge_support[0])

    @property
    def edge_distance_px(self) -> float | None:
        """The "fit" sampler's RMS distance (parser-view pixels) of the estimate's outline to the
        image's edges (inf: none along it); None otherwise."""
        return None if self.estimate.edge_distance_px is None else float(self.estimate.edge_distance_px[0])

    @property
    def doubts(self) -> list[str]:
        """Why the estimate is unreliable, in words (empty when it is reliable or there is nothing to judge by)."""
        return estimate_quality(self.estimate).doubts

    @property
    def reliable(self) -> bool | None:
        """ "fit": whether the fit can be trusted: the odds that it is off by more than 30 mm, by
        a model of the fit's numbers (how the silhouette fits the mask, how its outline and inner
        edges lie on the image's edges, how its restarts in depth agree, how large the robot is
        in the image for its distance), are low, and most of the robot is in the image
        (``perception.reliability.FLAG_MODEL``; :attr:`doubts` says why not). The paper's
        samplers: whether the chains agree within ``UNRELIABLE_MM``; None with one chain
        (nothing to compare)."""
        return estimate_quality(self.estimate).reliable

    @property
    def confidence(self) -> float | None:
        """ "fit": the silhouette IoU. The paper's samplers: exp(-spread / 30 mm), 1 when the
        chains agree, 0.37 at the unreliable threshold; None with one chain (no spread to measure)."""
        return estimate_quality(self.estimate).confidence

    @property
    def confidence_text(self) -> str:
        return "confidence n/a (1 chain)" if self.confidence is None else f"confidence {self.confidence:.2f}"

    @property
    def overlay_label(self) -> str:
        """The overlay's caption: the confidence and, for an unreliable estimate, the first reason why."""
        if self.reliable is False:
            return f"{self.confidence_text}, UNRELIABLE: {self.doubts[0]}"
        return self.confidence_text

    def to_dict(self) -> dict:
        return {
            "units": "meters",
            "camera_from_base": self.camera_from_base.tolist(),
            "base_from_camera": self.base_from_camera.tolist(),
            "confidence": self.confidence,
            "reliable": self.reliable,
            "sampler": self.sampler,
            "silhouette_iou": self.fit_iou,
            "edge_support": self.edge_support,
            "edge_distance_px": atomic.json_number(self.edge_distance_px),
            "doubts": self.doubts,
            "chain_spread_mm": atomic.json_number(self.spread_mm) if self.chains > 1 else None,
            "chain_spread_deg": atomic.json_number(self.spread_deg) if self.chains > 1 else None,
            "chains": self.chains,
        }


def estimate_pose(
    estimator: PoseEstimator,
    image: np.ndarray,
    joints: np.ndarray,
    K: np.ndarray,
    chains: int = 4,
    sampler: str | None = None,
    seed: int = 0,
    prior: np.ndarray | None = None,
) -> PoseResult:
    """Camera-from-base for one RGB image.

    ``image``: ``H x W x 3`` uint8 RGB (``monose3.data.inputs.load_image`` reads a file); ``joints``:
    ``{name: radians}``, or the arm's values in URDF order (7 for the Panda; 8 with the
    gripper), as a list or an array of shape ``[n]`` or ``[1, n]`` (``load_joints`` reads a
    file); ``K``: the 3x3 intrinsics of this image in pixels (``load_camera(path).K``). With
    ``chains`` > 1, that many stochastic reverse chains from perturbed initialisations run in
    one batch; their spread is the uncertainty (``chains=1``: confidence and reliable are None).
    ``prior``: an approximate camera-from-base in metres (e.g. a previous calibration) to
    refine, from ``InferenceConfig.prior_t``, instead of RoboPose's initialisation.
    ``sampler``: "fit" (the default with a robot parser: parser, PnP, silhouette search and
    refinement; ``chains`` is then unused and ``prior`` joins the hypotheses), or the paper's
    "revdiff" / "directreg".

    Every input goes through :mod:`monose3.data.validation` first (the same checks as ``monose3
    estimate``); a bad one raises Monose3Error, as does an estimate that puts the robot outside
    the image."""
    sampler = sampler or estimator.default_sampler
    image, joints, K, prior, chains = validation.check_estimate_inputs(
        image, joints, K, estimator.robot, prior=prior, chains=chains, sampler=sampler
    )
    if sampler == "fit":
        est = estimator.estimate([image], K[None], joints[None], sampler=sampler, init_poses=_batch_of(prior))
        chains = 1
    else:
        est = estimator.estimate(
            [image],
            K[None],
            joints[None],
            sampler=sampler,
            hypotheses=chains,
            stochastic=chains > 1,
            seed=seed,
            **prior_arguments(estimator, _batch_of(prior)),
        )
    if est.found is not None and not est.found[0]:
        raise Monose3Error(
            "the robot was not found in the image (the parser's mask is empty); check that the robot is visible"
        )
    if not est.in_view[0]:
        raise Monose3Error(
            "the estimate puts the robot outside the image (failure); check that the robot is visible "
            "and that the joints and intrinsics belong to this image"
        )
    return PoseResult(est.poses[0], float(est.spread_mm[0]), float(est.spread_deg[0]), chains, est, sampler)


def _batch_of(prior: np.ndarray | None) -> np.ndarray | None:
    return None if prior is None else prior[None]


def prior_arguments(estimator: PoseEstimator, priors: np.ndarray | None) -> dict:
    """``PoseEstimator.estimate`` arguments that refine approximate poses ``[B, 4, 4]`` (none: RoboPose's start)."""
    if priors is None:
        return {}
    return {"init_poses": priors, "start_t": estimator.config.inference.prior_t}


def overlay_image(
    image: np.ndarray,
    K: np.ndarray,
    joints: np.ndarray,
    pose: np.ndarray,
    robot,
    renderer: RobotRenderer | None = None,
    text: str | None = None,
    gt_keypoints: np.ndarray | None = None,
) -> np.ndarray:
    """The robot rendered at ``pose`` drawn on the image as an outline with its keypoints
    (camera-frame ``gt_keypoints`` ``[K, 3]`` as crosses)."""
    renderer = renderer or RobotRenderer(robot)
    return pose_overlays(renderer, [image], [K], [joints], [pose], [text], [gt_keypoints])[0]


def write_pose_files(result: PoseResult, out: Path) -> tuple[Path, Path]:
    """``pose.json`` (strict JSON: no NaN) and ``pose.yaml`` in ``out``, each written atomically."""
    data = result.to_dict()
    json_path, yaml_path = out / "pose.json", out / "pose.yaml"
    atomic.write_text(json_path, json.dumps(data, indent=2, allow_nan=False))
    atomic.write_text(yaml_path, yaml.safe_dump(data, sort_keys=False))
    return json_path, yaml_path


def format_pose(result: PoseResult) -> str:
    fmt = lambda m: "\n".join("  [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in m)  # noqa: E731
    if result.fit_iou is not None:
        rel = "reliable" if result.reliable else f"UNRELIABLE ({'; '.join(result.doubts)})"
        edges = f"outline {result.edge_distance_px:.2f} px from the image's edges ({result.edge_support:.2f} on them)"
        how = f"silhouette IoU {result.fit_iou:.3f}, {edges}, {rel}"
    elif result.reliable is None:
        how = "a single chain has no spread, so no confidence (use --chains 2 or more for one)"
    else:
        rel = "reliable" if result.reliable else f"UNRELIABLE ({'; '.join(result.doubts)})"
        how = f"chains spread {result.spread_mm:.1f} mm / {result.spread_deg:.1f} deg, {rel}"
    return (
        f"camera_from_base (m):\n{fmt(result.camera_from_base)}\n"
        f"base_from_camera (m):\n{fmt(result.base_from_camera)}\n"
        f"{result.confidence_text}: {how}"
    )
