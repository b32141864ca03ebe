"""``monose3 estimate``: camera-from-base from one image, its joints and intrinsics; writes
pose.json, pose.yaml and overlay.png."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

from monose3.apps.arguments import (
    CHAINS_HELP,
    add_model_arguments,
    check_parser_file,
    robot_model,
)
from monose3.data import validation as v
from monose3.data.inputs import load_camera, load_image, load_pose
from monose3.training.formats import check_checkpoint


def add_estimate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image", required=True, help="RGB image (PNG/JPEG) of the robot")
    p.add_argument(
        "--joints",
        required=True,
        help="JSON/YAML: {name: radians}, a list in URDF order (7 for the Panda) or a DREAM frame JSON",
    )
    p.add_argument(
        "--camera",
        required=True,
        help="intrinsics of this image: JSON {fx, fy, cx, cy, width, height}, DREAM camera settings or ROS "
        "CameraInfo YAML",
    )
    add_model_arguments(p, 4, CHAINS_HELP)
    p.add_argument(
        "--out",
        default="monose3_out",
        help="folder for pose.json, pose.yaml and overlay.png (default: monose3_out; created if missing)",
    )
    p.add_argument(
        "--prior",
        help="approximate camera-from-base to refine, in metres (pose.json/calibration.json written by monose3, "
        "or a 4x4 list)",
    )


def check_estimate(args: argparse.Namespace) -> SimpleNamespace:
    chains = v.check_chains(args.chains, "--chains")
    check_parser_file(args.parser)
    out = v.check_output_dir(args.out, "--out")
    robot = robot_model(check_checkpoint(args.checkpoint, args.robot))
    image = v.check_image(load_image(args.image), args.image)
    camera = load_camera(args.camera)
    K = v.check_camera(camera, image, args.camera)
    joints = prior = None
    if robot is not None:
        joints = v.check_joints(args.joints, robot)
    if args.prior:
        prior = load_pose(args.prior)
        if robot is not None:
            prior = v.check_prior(prior, robot, joints, K, camera.size, f"prior {args.prior}")
    return SimpleNamespace(image=image, camera=camera, K=K, joints=joints, prior=prior, chains=chains, out=out)


def run_estimate(args: argparse.Namespace) -> int:
    from monose3.api import estimate_pose, format_pose, load_estimator, overlay_image, write_pose_files
    from monose3.report.overlays import save_image

    inputs = getattr(args, "checked_inputs", None) or check_estimate(args)  # all of it before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, parser=args.parser)
    try:
        joints = inputs.joints if inputs.joints is not None else v.check_joints(args.joints, estimator.robot)
        result = estimate_pose(
            estimator, inputs.image, joints, inputs.K, chains=inputs.chains, sampler=args.sampler, prior=inputs.prior
        )
        overlay = overlay_image(
            inputs.image,
            inputs.K,
            joints,
            result.camera_from_base,
            estimator.robot,
            estimator.renderer,  # the estimator's own: no second mesh set-up
            text=result.overlay_label,
        )
    finally:
        estimator.close()
    json_path, yaml_path = write_pose_files(result, inputs.out)
    png = save_image(inputs.out / "overlay.png", overlay)
    print(format_pose(result))
    print(f"wrote {json_path}, {yaml_path}, {png}")
    return 0
