"""``monose3 demo``: the bundled sample scene (a generated Panda image with its joints, camera
and ground truth) through the bundled model, with the error against the ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from monose3.api import ASSETS, estimate_pose, format_pose, load_estimator, overlay_image, write_pose_files
from monose3.data.inputs import load_camera, load_image, load_joints
from monose3.geometry.rotations import rotation_angle
from monose3.report.metrics import add_per_frame
from monose3.report.overlays import save_image

SAMPLE = ASSETS / "sample"


def pose_errors(robot, joints: np.ndarray, pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """ADD over the keypoints (mm), translation error (mm) and rotation error (deg)."""
    to_cam = lambda pose: robot.keypoints(joints[None], pose[None])[0]  # noqa: E731
    return {
        "add_mm": 1000 * float(add_per_frame(to_cam(pred)[None], to_cam(truth)[None])[0]),
        "translation_mm": 1000 * float(np.linalg.norm(pred[:3, 3] - truth[:3, 3])),
        "rotation_deg": float(np.degrees(rotation_angle(pred[:3, :3], truth[:3, :3]))),
    }


def run_demo(args: argparse.Namespace) -> int:
    from monose3.apps.arguments import check_demo

    checked = getattr(args, "checked_inputs", None) or check_demo(args)
    image = load_image(SAMPLE / "image.jpg")
    camera = load_camera(SAMPLE / "camera.json")
    truth = np.asarray(json.loads((SAMPLE / "ground_truth.json").read_text())["camera_from_base"])
    estimator = load_estimator(args.checkpoint, robot="panda")
    try:
        joints = load_joints(SAMPLE / "joints.json", estimator.robot)
        result = estimate_pose(estimator, image, joints, camera.K, chains=checked.chains)
    finally:
        estimator.close()
    out = Path(checked.out)
    err = pose_errors(estimator.robot, joints, result.camera_from_base, truth)
    text = f"ADD {err['add_mm']:.0f} mm, {result.confidence_text}"
    overlay = overlay_image(
        image, camera.K, joints, result.camera_from_base, estimator.robot, estimator.renderer, text=text
    )
    write_pose_files(result, out)
    png = save_image(out / "overlay.png", overlay)
    print(f"sample scene: {SAMPLE.name} ({camera.width}x{camera.height}), robot {estimator.robot.name}")
    print(format_pose(result))
    print(
        f"error vs ground truth: ADD {err['add_mm']:.1f} mm, translation {err['translation_mm']:.1f} mm, "
        f"rotation {err['rotation_deg']:.2f} deg"
    )
    print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in result.estimate.timings.items()))
    print(f"wrote {out / 'pose.json'}, {out / 'pose.yaml'}, {png}")
    return 0
