"""``monose3 generate``: the command shell over :func:`monose3.data.scenes.writer.generate_dataset`.

The options live in the torch-free :mod:`monose3.apps.arguments` (fast ``--help`` and input errors).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from monose3.apps.arguments import (
    ROBOT_FILE_HELP,
    check_non_negative,
    parse_size,
)
from monose3.data import validation as v
from monose3.data.scenes.profiles import PROFILES
from monose3.errors import Monose3Error
from monose3.robot import get_spec
from monose3.robot.jobs import RENDERERS


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder (DREAM layout)")
    parser.add_argument("--num", required=True, type=int, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed = same data) [0]")
    parser.add_argument("--robot", default="panda", help=f"panda, kuka or {ROBOT_FILE_HELP} [panda]")
    parser.add_argument("--urdf", type=Path, help="custom robot: URDF file (with --keypoints)")
    parser.add_argument("--keypoints", type=Path, help='custom robot: {"keypoints": [{"name", "link", "offset"}]}')
    parser.add_argument("--workers", type=int, default=None, help="processes [one per CPU core]; 0 = no subprocess")
    parser.add_argument("--profile", choices=sorted(PROFILES), default="train", help="scene randomisation [train]")
    parser.add_argument("--backgrounds", type=Path, help="folder of images to use as some of the backgrounds")
    parser.add_argument("--size", type=parse_size, default=(640, 480), help="image size WxH [640x480]")
    parser.add_argument("--resume", action="store_true", help="keep the frames already in --out, make the rest")
    parser.add_argument("--preview", type=Path, help="also save a grid of the first 12 frames with keypoints here")
    parser.add_argument(
        "--sequence",
        choices=("static", "moving"),
        help="one sequence of --num frames instead of independent ones: a static or slowly orbiting camera, "
        "the robot moving smoothly (for tracking)",
    )
    parser.add_argument(
        "--renderer",
        choices=RENDERERS,
        default="torch",
        help="torch: monose3's renderer [default]; tiny/egl: pybullet's (needs pybullet), for cross-renderer test sets",
    )


def check_generate(args: argparse.Namespace) -> None:
    v.check_count(args.num, "--num")
    check_non_negative(args.workers, "--workers")
    v.check_output_dir(args.out, "--out")
    if bool(args.urdf) != bool(args.keypoints):
        raise Monose3Error("a custom robot needs both --urdf and --keypoints")
    if not args.urdf:
        get_spec(args.robot)
    if args.backgrounds is not None:
        v.check_input_dir(args.backgrounds, "--backgrounds")
    if args.preview is not None:
        v.check_output_file(args.preview, "--preview", (".png", ".jpg", ".jpeg"))
    if args.sequence and args.num < 2:
        raise Monose3Error(f"--sequence needs --num 2 or more frames, got {args.num}")
    if args.sequence and args.resume:
        raise Monose3Error("--resume is for independent frames; a --sequence is written whole (run it again)")


def run_generate(args: argparse.Namespace) -> int:
    from monose3.data.scenes.writer import generate_dataset, save_preview_grid
    from monose3.robot import RobotSpec, spec_from_files

    robot: str | RobotSpec = args.robot
    if args.urdf or args.keypoints:
        if not (args.urdf and args.keypoints):
            raise Monose3Error("a custom robot needs both --urdf and --keypoints")
        robot = spec_from_files(args.urdf, args.keypoints)
    start = time.perf_counter()
    if args.sequence:
        out = _write_sequence(args, robot)
    else:
        out = generate_dataset(
            args.out,
            args.num,
            args.seed,
            robot,
            args.workers,
            args.profile,
            args.backgrounds,
            args.size,
            resume=args.resume,
            backend=args.renderer,
        )
    elapsed = time.perf_counter() - start
    print(f"wrote {args.num} frames to {out} in {elapsed:.1f} s ({args.num / max(elapsed, 1e-9):.1f} frames/s)")
    if args.preview:
        print(f"preview: {save_preview_grid(out, args.preview, robot=robot)}")
    return 0


def _write_sequence(args: argparse.Namespace, robot):
    """``--sequence``: one sequence of ``--num`` frames (:mod:`monose3.data.scenes.sequences`)."""
    import torch

    from monose3.data.scenes.appearance import load_photos
    from monose3.data.scenes.sequences import SequenceConfig, write_sequence

    photos = load_photos(args.backgrounds, torch.device("cpu"), bundled=False) if args.backgrounds else None
    config = SequenceConfig(frames=args.num, camera=args.sequence)
    return write_sequence(args.out, config, args.seed, robot, args.profile, args.size, args.renderer, photos)
