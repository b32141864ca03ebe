"""The Python API, mirroring the CLI: load the shipped model in one call, estimate from an
image array, joints and K, draw the overlay. ``monose3 estimate`` lives here too."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from monose3.checkpoint import load_model
from monose3.errors import Monose3Error
from monose3.estimator import Estimate, PoseEstimator
from monose3.inputs import CameraIntrinsics, check_image_camera, load_camera, load_image, load_joints, load_pose
from monose3.robot import get_spec
from monose3.robot.renderer import RenderJob, RobotRenderer
from monose3.viz import draw_overlay, save_image

ASSETS = Path(__file__).parent / "assets"
DEFAULT_CHECKPOINT = ASSETS / "panda_cpu.pt"
# Chains that disagree by more than this (mean keypoint distance to the chosen chain) are
# flagged unreliable; see benchmarks/uncertainty.py for what the threshold catches.
UNRELIABLE_MM = 30.0


def default_checkpoint() -> Path:
    if not DEFAULT_CHECKPOINT.is_file():
        raise Monose3Error(
            f"the bundled model {DEFAULT_CHECKPOINT.name} is missing; reinstall monose3 or pass --checkpoint"
        )
    return DEFAULT_CHECKPOINT


def load_estimator(
    checkpoint: str | Path | None = None, robot: str | None = None, device: str = "auto"
) -> PoseEstimator:
    """The estimator for a checkpoint (default: the Panda model shipped in the package)."""
    import torch

    if robot is not None:
        get_spec(robot)  # an unknown robot name fails here, before any loading
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    model, config = load_model(checkpoint or default_checkpoint(), robot=robot, device=device)
    return PoseEstimator(model, config, device=device)


@dataclass
class PoseResult:
    """One estimate. ``camera_from_base`` maps base-frame points (metres) into the camera frame."""

    camera_from_base: np.ndarray
    spread_mm: float
    spread_deg: float
    chains: int
    estimate: Estimate

    @property
    def base_from_camera(self) -> np.ndarray:
        return np.linalg.inv(self.camera_from_base)

    @property
    def reliable(self) -> bool:
        return self.chains < 2 or self.spread_mm <= UNRELIABLE_MM

    @property
    def confidence(self) -> float:
        """exp(-spread / 30 mm): 1 when the chains agree, 0.37 at the unreliable threshold."""
        return float(np.exp(-self.spread_mm / UNRELIABLE_MM)) if self.chains > 1 else float("nan")

    def to_dict(self) -> dict:
        return {
            "units": "meters",
            "camera_from_base": self.camera_from_base.tolist(),
            "base_from_camera": self.base_from_camera.tolist(),
            "confidence": self.confidence,
            "reliable": self.reliable,
            "chain_spread_mm": float(self.spread_mm),
            "chain_spread_deg": float(self.spread_deg),
            "chains": self.chains,
        }


def estimate_pose(
    estimator: PoseEstimator,
    image: np.ndarray,
    joints: np.ndarray,
    K: np.ndarray,
    chains: int = 4,
    sampler: str = "revdiff",
    seed: int = 0,
    prior: np.ndarray | None = None,
) -> PoseResult:
    """Camera-from-base for one RGB image. With ``chains`` > 1, that many stochastic reverse
    chains from perturbed initialisations run in one batch; their spread is the uncertainty.
    ``prior``: an approximate camera-from-base (e.g. a previous calibration) to refine, from
    ``InferenceConfig.prior_t``, instead of RoboPose's initialisation.
    Raises Monose3Error when the estimate puts the robot outside the image."""
    if prior is not None:
        check_prior(estimator, prior, joints, K, np.asarray(image).shape[:2])
    est = estimator.estimate(
        [image],
        np.asarray(K)[None],
        np.asarray(joints)[None],
        sampler=sampler,
        hypotheses=chains,
        stochastic=chains > 1,
        seed=seed,
        **prior_arguments(estimator, None if prior is None else np.asarray(prior)[None]),
    )
    if not est.in_view[0]:
        raise Monose3Error(
            "the estimate puts the robot outside the image (failure); check that the robot is visible "
            "and that the joints and intrinsics belong to this image"
        )
    return PoseResult(est.poses[0], float(est.spread_mm[0]), float(est.spread_deg[0]), chains, est)


def check_prior(estimator: PoseEstimator, prior: np.ndarray, joints: np.ndarray, K: np.ndarray, hw: tuple) -> None:
    """Refuse a prior that does not show the robot: usually the inverse pose or millimetres."""
    points = estimator.robot.keypoints(np.asarray(joints)[None], np.asarray(prior)[None])[0]
    centre = points.mean(0)
    u, v = (np.asarray(K) @ centre)[:2] / centre[2] if centre[2] > 0 else (-1.0, -1.0)
    if not (0 <= u < hw[1] and 0 <= v < hw[0]):
        raise Monose3Error(
            "the prior pose puts the robot outside the image; give camera_from_base (not its inverse), in metres"
        )


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
    """The robot rendered at ``pose`` drawn on the image as an outline with its keypoints."""
    h, w = image.shape[:2]
    renderer = renderer or RobotRenderer(robot)
    job = RenderJob(np.asarray(joints, np.float64), pose, np.asarray(K, np.float64), (w, h))
    _, mask = renderer.render_jobs([job])[0]
    kp = renderer.model.keypoints(np.asarray(joints)[None], pose[None])[0]
    uv = kp[:, :2] / kp[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    gt_uv = None
    if gt_keypoints is not None:
        gt_uv = gt_keypoints[:, :2] / gt_keypoints[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    return draw_overlay(image, mask, uv, gt_keypoints_uv=gt_uv, text=text)


def write_pose_files(result: PoseResult, out: Path) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    data = result.to_dict()
    json_path, yaml_path = out / "pose.json", out / "pose.yaml"
    json_path.write_text(json.dumps(data, indent=2))
    yaml_path.write_text(yaml.safe_dump(data, sort_keys=False))
    return json_path, yaml_path


def format_pose(result: PoseResult) -> str:
    fmt = lambda m: "\n".join("  [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in m)  # noqa: E731
    rel = "reliable" if result.reliable else "UNRELIABLE (chains disagree)"
    spread = f"chains spread {result.spread_mm:.1f} mm / {result.spread_deg:.1f} deg"
    return (
        f"camera_from_base (m):\n{fmt(result.camera_from_base)}\n"
        f"base_from_camera (m):\n{fmt(result.base_from_camera)}\n"
        f"confidence {result.confidence:.2f}: {spread}, {rel}"
    )


def add_estimate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image", required=True, help="RGB image (PNG/JPEG)")
    p.add_argument("--joints", required=True, help="JSON/YAML: {name: radians} or a list in URDF order")
    p.add_argument(
        "--camera",
        required=True,
        help="JSON {fx, fy, cx, cy, width, height}, DREAM camera settings or ROS CameraInfo YAML",
    )
    p.add_argument("--checkpoint", help="model checkpoint (default: the bundled Panda model)")
    p.add_argument("--robot", help="robot the checkpoint must be for (checked)")
    p.add_argument("--out", default="monose3_out", help="folder for pose.json, pose.yaml and overlay.png")
    p.add_argument("--chains", type=int, default=4, help="stochastic reverse chains for the uncertainty (1 = off)")
    p.add_argument("--sampler", choices=["revdiff", "directreg"], default="revdiff")
    p.add_argument(
        "--prior",
        help="approximate camera-from-base to refine (pose.json/calibration.json written by monose3, or a 4x4 list)",
    )


def run_estimate(args: argparse.Namespace) -> int:
    image = load_image(args.image)
    camera: CameraIntrinsics = load_camera(args.camera)
    check_image_camera(image, camera)
    prior = load_pose(args.prior) if args.prior else None
    estimator = load_estimator(args.checkpoint, robot=args.robot)
    try:
        joints = load_joints(args.joints, estimator.robot)
        result = estimate_pose(
            estimator, image, joints, camera.K, chains=max(1, args.chains), sampler=args.sampler, prior=prior
        )
    finally:
        estimator.close()
    out = Path(args.out)
    json_path, yaml_path = write_pose_files(result, out)
    overlay = overlay_image(
        image, camera.K, joints, result.camera_from_base, estimator.robot, text=f"confidence {result.confidence:.2f}"
    )
    png = save_image(out / "overlay.png", overlay)
    print(format_pose(result))
    print(f"wrote {json_path}, {yaml_path}, {png}")
    return 0
