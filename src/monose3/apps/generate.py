"""``monose3 generate``: the command shell over :func:`monose3.data.scenes.writer.generate_dataset`.

The options live in the torch-free :mod:`monose3.apps.arguments` (fast ``--help`` and input errors).
"""

from __future__ import annotations

import argparse
import time

from monose3.data.scenes.writer import generate_dataset, save_preview_grid
from monose3.errors import Monose3Error
from monose3.robot import RobotSpec, spec_from_files


def run_generate(args: argparse.Namespace) -> int:
    robot: str | RobotSpec = args.robot
    if args.urdf or args.keypoints:
        if not (args.urdf and args.keypoints):
            raise Monose3Error("a custom robot needs both --urdf and --keypoints")
        robot = spec_from_files(args.urdf, args.keypoints)
    start = time.perf_counter()
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
