"""``monose3 demo``: the bundled sample scene (a generated Panda image with its joints, camera
and ground truth) through the bundled model, with the error against the ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from monose3.apps.arguments import (
    CHAINS_HELP,
    CHECKPOINT_HELP,
)
from monose3.data import validation as v
from monose3.data.inputs import load_camera, load_image, load_joints
from monose3.geometry.rotations import rotation_angle
from monose3.report.metrics import add_per_frame
from monose3.training.formats import check_checkpoint


def add_demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out",
        default="monose3_demo",
        help="folder for pose.json, pose.yaml and overlay.png (default: monose3_demo; created if missing)",
    )
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP + "; it must be a Panda model")
    p.add_argument("--chains", type=int, default=4, help=f"{CHAINS_HELP} (default 4)")


def check_demo(args: argparse.Namespace) -> SimpleNamespace:
    chains = v.check_chains(args.chains, "--chains")
    out = v.check_output_dir(args.out, "--out")
    check_checkpoint(args.checkpoint, "panda")
    return SimpleNamespace(chains=chains, out=out)


def pose_errors(robot, joints: np.ndarray, pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """ADD over the keypoints (mm), translation error (mm) and rotation error (deg)."""
    to_cam = lambda pose: robot.keypoints(joints[None], pose[None])[0]  # noqa: E731
    return {
        "add_mm": 1000 * float(add_per_frame(to_cam(pred)[None], to_cam(truth)[None])[0]),
        "translation_mm": 1000 * float(np.linalg.norm(pred[:3, 3] - truth[:3, 3])),
        "rotation_deg": float(np.degrees(rotation_angle(pred[:3, :3], truth[:3, :3]))),
    }


def run_demo(args: argparse.Namespace) -> int:
    from monose3.api import ASSETS, estimate_pose, format_pose, load_estimator, overlay_image, write_pose_files
    from monose3.report.overlays import save_image

    sample = ASSETS / "sample"

    checked = getattr(args, "checked_inputs", None) or check_demo(args)
    image = load_image(sample / "image.jpg")
    camera = load_camera(sample / "camera.json")
    truth = np.asarray(json.loads((sample / "ground_truth.json").read_text())["camera_from_base"])
    estimator = load_estimator(args.checkpoint, robot="panda")
    try:
        joints = load_joints(sample / "joints.json", estimator.robot)
        result = estimate_pose(estimator, image, joints, camera.K, chains=checked.chains)
    finally:
        estimator.close()
    out = Path(checked.out)
    err = pose_errors(estimator.robot, joints, result.camera_from_base, truth)
    text = f"ADD {err['add_mm']:.0f} mm, {result.overlay_label}"
    overlay = overlay_image(
        image, camera.K, joints, result.camera_from_base, estimator.robot, estimator.renderer, text=text
    )
    write_pose_files(result, out)
    png = save_image(out / "overlay.png", overlay)
    print(f"sample scene: {sample.name} ({camera.width}x{camera.height}), robot {estimator.robot.name}")
    print(format_pose(result))
    print(
        f"error vs ground truth: ADD {err['add_mm']:.1f} mm, translation {err['translation_mm']:.1f} mm, "
        f"rotation {err['rotation_deg']:.2f} deg"
    )
    print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in result.estimate.timings.items()))
    print(f"wrote {out / 'pose.json'}, {out / 'pose.yaml'}, {png}")
    return 0
