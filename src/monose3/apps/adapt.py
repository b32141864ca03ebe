"""``monose3 adapt``: the robot parser fine-tuned on the user's own frames (no labels needed).

:mod:`monose3.adaptation` does the work: it fits every frame, labels the frames with the
reliable fits (``--static-camera``: every frame with the pose fused from them), fine-tunes the
parser on those labels mixed with synthetic scenes for a few minutes, and keeps the result
only when the fits of frames held out from the labels improve. ``--out`` is written only then
(atomically); pass it to ``estimate``, ``calibrate`` or ``track`` with ``--parser``.
``calibrate --adapt`` and ``track --adapt`` do the same before their own work.

Input folder (``--frames DIR``): the plain folder of ``monose3 calibrate``
(``NNNN.png`` + ``NNNN.joints.json`` + ``camera.json``) or a DREAM folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from monose3.apps.arguments import (
    CHECKPOINT_HELP,
    DEVICE_HELP,
    PARSER_HELP,
    ROBOT_HELP,
    adapt_and_save,
    add_adapt_budget,
    check_adapt_budget,
    check_parser_file,
    robot_model,
)
from monose3.data import validation as v
from monose3.data.frames import load_frames
from monose3.training.formats import check_checkpoint


def add_adapt_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", required=True, help="folder of NNNN.png|jpg + NNNN.joints.json + camera.json, or DREAM")
    p.add_argument("--out", required=True, help="the adapted parser's file (.pt), written only when it fits better")
    p.add_argument(
        "--static-camera",
        action="store_true",
        help="the camera did not move: label every frame with the pose fused from the reliable fits",
    )
    add_adapt_budget(p)
    p.add_argument("--parser", help=PARSER_HELP + "; the parser to adapt")
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument("--limit", type=int, help="use only the first N frames")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)


def check_adapt(args: argparse.Namespace) -> list | None:
    check_parser_file(args.parser)
    check_adapt_budget(args)
    if args.limit is not None:
        v.check_count(args.limit, "--limit")
    v.check_input_dir(args.frames, "--frames")
    v.check_output_file(args.out, "--out", (".pt",))
    robot = robot_model(check_checkpoint(args.checkpoint, args.robot))
    if robot is None:
        return None
    return checked_frames(args, robot)


def checked_frames(args: argparse.Namespace, robot) -> list:
    from monose3.adaptation import check_frame_count

    frames = load_frames(args.frames, robot)
    frames = list(frames[: args.limit] if args.limit is not None else frames)
    check_frame_count(len(frames))
    return frames


def run_adapt(args: argparse.Namespace) -> int:
    from monose3.api import load_estimator

    frames = getattr(args, "checked_inputs", None) or check_adapt(args)  # inputs read before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, device=args.device, parser=args.parser)
    try:
        frames = frames or checked_frames(args, estimator.robot)
        written = adapt_and_save(estimator, frames, args.static_camera, args, Path(args.out))
    finally:
        estimator.close()
    if not written:
        print(f"nothing written: estimate with the parser you started from (not {args.out})")
    else:
        print(f"wrote {', '.join(map(str, written))}; use the parser with --parser {written[0]}")
    return 0
