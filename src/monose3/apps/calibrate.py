"""``monose3 calibrate``: one camera-to-robot extrinsic fused from many frames of a static camera
(:mod:`monose3.calibration` does the work; this module reads, prints and writes). The pipeline:

1. estimate every frame (batched; ``chains`` > 1 runs that many stochastic reverse chains per
   frame, whose disagreement measures the frame's uncertainty);
2. reject frames whose estimate puts the robot outside the image ("out of view") and, with
   several chains, those whose chains disagree by more than ``estimator.UNRELIABLE_MM``
   ("unreliable chains");
3. fuse the rest robustly (:mod:`monose3.geometry.averaging`: geodesic L1 median of the rotations,
   geometric median of the translations), reject frames whose translation or rotation lies
   beyond ``median + k * 1.4826 * MAD`` of the residuals to that first fusion ("far from
   consensus"), and fuse the remaining inliers again.

Input folder (``--frames DIR``), one of:

* a DREAM folder (``NNNNNN.json`` + ``NNNNNN.rgb.jpg`` + ``_camera_settings.json``) or a
  RoboKeyGen sequence: its ground truth is used to report the error of the fused pose;
* a plain folder::

      camera.json          intrinsics {fx, fy, cx, cy, width, height} (or any layout
                           monose3.data.inputs.load_camera reads: DREAM settings, ROS CameraInfo;
                           camera.yaml works too)
      0000.png             an image (PNG or JPEG: .png, .jpg, .jpeg)
      0000.joints.json     its joint angles: {joint name: radians} (or a list in URDF order;
                           .joints.yaml works too)
      0001.jpg
      0001.joints.json
      ...

  Every image needs its joints file; frames are taken in natural name order.

Outputs (``--out``): ``calibration.json`` (the fused camera_from_base and base_from_camera in
meters, the rejections and per-frame residuals), ``calibration.yaml`` (the same without the
per-frame list) and ``calibration_overlay.png`` (the robot at the fused pose drawn on a few frames).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import yaml

from monose3 import atomic
from monose3.apps.arguments import (
    ADAPTED_PARSER_FILE,
    DEVICE_HELP,
    adapt_and_save,
    add_adapt_option,
    add_model_arguments,
    check_adapt_budget,
    check_non_negative,
    check_parser_file,
    robot_model,
)
from monose3.data import validation as v
from monose3.data.frames import format_skipped, load_frames
from monose3.errors import Monose3Error
from monose3.training.formats import check_checkpoint

if TYPE_CHECKING:
    from monose3.calibration import CalibrationResult


def add_calibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--frames",
        required=True,
        help="folder of NNNN.png|jpg + NNNN.joints.json + camera.json, or a DREAM folder (then the error vs ground "
        "truth is reported)",
    )
    add_model_arguments(p, 1, "stochastic chains per frame; >1 also rejects frames whose chains disagree")
    p.add_argument(
        "--out",
        default="monose3_calibration",
        help="folder for calibration.json/.yaml and the overlay (default: monose3_calibration)",
    )
    p.add_argument("--batch-size", type=int, default=4, help="frames estimated together (default 4)")
    p.add_argument("--limit", type=int, help="use only the first N frames")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument(
        "--consensus-k",
        type=float,
        default=3.0,
        help="reject frames beyond median + k * sigma_MAD of the residuals to the first robust fusion (default 3)",
    )
    p.add_argument("--overlay-frames", type=int, default=6, help="frames in the overlay grid (default 6; 0: none)")
    add_adapt_option(p, "calibrate")


def check_calibrate(args: argparse.Namespace) -> SimpleNamespace:
    chains = v.check_chains(args.chains, "--chains")
    check_parser_file(args.parser)
    v.check_count(args.batch_size, "--batch-size")
    if args.limit is not None:
        v.check_count(args.limit, "--limit")
    check_non_negative(args.overlay_frames, "--overlay-frames")
    check_adapt_budget(args)
    if not args.consensus_k > 0:
        raise Monose3Error(f"--consensus-k must be positive, got {args.consensus_k}")
    v.check_input_dir(args.frames, "--frames")
    out = v.check_output_dir(args.out, "--out")
    robot = robot_model(check_checkpoint(args.checkpoint, args.robot))
    frames = None
    if robot is not None:
        frames = load_frames(args.frames, robot)
        if args.limit is not None:
            frames = frames[: args.limit]
        if args.adapt:
            from monose3.adaptation import check_frame_count

            check_frame_count(len(frames))
    return SimpleNamespace(chains=chains, out=out, frames=frames)


log = logging.getLogger("monose3")

PRINT_ALL_FRAMES = 40


# ---- report and files ---------------------------------------------------------------------------


def format_report(result: CalibrationResult, max_frames: int = PRINT_ALL_FRAMES) -> str:
    """The per-frame residual table (all frames if few, else the rejected ones) and the summary."""
    fmt = lambda m: "\n".join(  # noqa: E731
        "  [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in np.where(np.abs(m) < 5e-7, 0.0, m)
    )
    lines = []
    shown = result.frames if len(result.frames) <= max_frames else [f for f in result.frames if not f.used]
    if shown:
        lines.append(
            f"{'frame':>16} {'status':>28} {'resid mm':>9} {'resid deg':>9}"
            + (f" {'chains mm':>9}" if result.chains > 1 else "")
        )
        for f in shown:
            status = "used" if f.used else f"rejected: {f.reason}"
            row = f"{f.name:>16} {status:>28} {f.residual_mm:9.1f} {f.residual_deg:9.2f}"
            if result.chains > 1:
                row += f" {f.chain_spread_mm:9.1f}"
            lines.append(row)
        if len(shown) < len(result.frames):
            lines.append(f"  ({len(result.frames) - len(shown)} used frames not listed; see calibration.json)")
    s = result.spread
    rejected = ", ".join(f"{n} {why}" for why, n in result.rejected.items()) or "none"
    skipped_line = format_skipped("frames", result.skipped)
    lines += [
        *([skipped_line] if skipped_line else []),
        f"frames: {len(result.used)} of {len(result.frames)} used; rejected: {rejected}",
        f"consensus thresholds: {result.threshold_mm:.1f} mm / {result.threshold_deg:.2f} deg",
        f"spread of the used frames to the fused pose: median {s['median_mm']:.1f} mm / {s['median_deg']:.2f} deg, "
        f"RMS {s['rms_mm']:.1f} mm / {s['rms_deg']:.2f} deg (standard error ~{s['standard_error_mm']:.1f} mm / "
        f"{s['standard_error_deg']:.2f} deg)",
        f"camera_from_base (m):\n{fmt(result.camera_from_base)}",
        f"base_from_camera (m):\n{fmt(result.base_from_camera)}",
    ]
    gt = result.ground_truth
    if gt is not None:
        lines.append(
            f"vs ground truth: fused {gt['fused_error_mm']:.1f} mm / {gt['fused_error_deg']:.2f} deg "
            f"(ADD {gt['fused_add_mean_mm']:.1f} mm); single frames median {gt['single_frame_error_median_mm']:.1f} mm "
            f"/ {gt['single_frame_error_median_deg']:.2f} deg (ADD {_mm(gt['single_frame_add_median_mm'])})"
        )
        if not gt["static_camera"]:
            lines.append(
                f"warning: the ground-truth poses differ by up to {gt['ground_truth_spread_max_mm']:.0f} mm: the "
                "camera was not static, so one extrinsic cannot fit every frame (see the per-frame ADDs in the JSON)"
            )
    return "\n".join(lines)


def _mm(v: float | None) -> str:
    return "failed" if v is None else f"{v:.1f} mm"


def write_calibration_files(result: CalibrationResult, out: str | Path) -> tuple[Path, Path]:
    """``calibration.json`` (everything, per-frame residuals included) and ``calibration.yaml`` (the summary)."""
    out = Path(out)
    json_path, yaml_path = out / "calibration.json", out / "calibration.yaml"
    atomic.write_text(json_path, json.dumps(result.to_dict(), indent=2, allow_nan=False))
    atomic.write_text(yaml_path, yaml.safe_dump(result.summary_dict(), sort_keys=False, default_flow_style=None))
    return json_path, yaml_path


# ---- command line ------------------------------------------------------------------------------


def run_calibrate(args: argparse.Namespace) -> int:
    from monose3.api import load_estimator
    from monose3.calibration import calibrate, overlay_grid
    from monose3.report.overlays import save_image

    checked = getattr(args, "checked_inputs", None) or check_calibrate(args)  # inputs read before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, device=args.device, parser=args.parser)
    try:
        frames = checked.frames
        if frames is None:
            frames = load_frames(args.frames, estimator.robot)
            frames = frames[: args.limit] if args.limit is not None else frames
        adapted = []
        if args.adapt:
            adapted = adapt_and_save(estimator, list(frames), True, args, checked.out / ADAPTED_PARSER_FILE)
        print(f"calibrating from {len(frames)} frames of {args.frames}")
        result = calibrate(
            estimator,
            frames,
            chains=checked.chains,
            batch_size=args.batch_size,
            consensus_k=args.consensus_k,
            progress=True,
            sampler=args.sampler,
        )
        grid = overlay_grid(estimator, frames, result, args.overlay_frames) if args.overlay_frames > 0 else None
    finally:
        estimator.close()
    out = checked.out
    json_path, yaml_path = write_calibration_files(result, out)
    written = [json_path, yaml_path, *adapted]
    if grid is not None:
        written.append(save_image(out / "calibration_overlay.png", grid))
    print(format_report(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
