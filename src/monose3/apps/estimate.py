"""``monose3 estimate``: camera-from-base from one image, its joints and intrinsics; writes
pose.json, pose.yaml and overlay.png."""

from __future__ import annotations

import argparse

from monose3.api import estimate_pose, format_pose, load_estimator, overlay_image, write_pose_files
from monose3.data import validation
from monose3.report.overlays import save_image


def run_estimate(args: argparse.Namespace) -> int:
    from monose3.apps.arguments import check_estimate

    inputs = getattr(args, "checked_inputs", None) or check_estimate(args)  # all of it before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, parser=args.parser)
    try:
        joints = inputs.joints if inputs.joints is not None else validation.check_joints(args.joints, estimator.robot)
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
            text=result.confidence_text,
        )
    finally:
        estimator.close()
    json_path, yaml_path = write_pose_files(result, inputs.out)
    png = save_image(inputs.out / "overlay.png", overlay)
    print(format_pose(result))
    print(f"wrote {json_path}, {yaml_path}, {png}")
    return 0
