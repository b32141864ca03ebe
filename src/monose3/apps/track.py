"""``monose3 track``: the pose over a sequence, one cheap step per frame (the paper's tracking).

The policy (full estimate first, then one step per frame, re-initialised on loss, jumps and
periodically) is :mod:`monose3.tracking`'s, shared with ``monose3 evaluate --sampler tracking``.

Inputs: ``--frames DIR`` (a DREAM folder, whose ground truth gives the ADD of every frame, or
the plain folder of ``monose3 calibrate``: ``NNNN.png`` + ``NNNN.joints.json`` + ``camera.json``),
or ``--video FILE --camera FILE`` with the joints of every frame either in

* ``--joints-csv FILE``: a header row of joint names (URDF names, any order), then one row
  per video frame, radians. An optional column named ``frame`` (or ``name``) names the
  frames; columns ``time``, ``timestamp`` and ``stamp`` are ignored. Example::

      frame,panda_joint1,panda_joint2,panda_joint3,panda_joint4,panda_joint5,panda_joint6,panda_joint7
      0,0.0,-0.3,0.0,-2.2,0.0,2.0,0.8
      1,0.01,-0.3,0.0,-2.2,0.0,2.0,0.8

* ``--joints DIR``: one joints file per video frame (``{name: radians}`` JSON/YAML), taken in
  natural name order.

The number of rows (files) must equal the number of video frames. Outputs (``--out``):
``poses.jsonl`` and ``poses.csv`` (per frame: name, mode full|track|fused, why a full estimate
was run and what was kept, the confidence, the ``reliable`` flag and the doubts behind it,
camera_from_base flattened row-major, meters) and ``track.gif`` (the overlays); with
``--static-camera`` also ``camera_pose.json`` (the fused camera pose and how well it converged).
Every output is written when the run ends, atomically.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from monose3.apps.arguments import (
    ADAPTED_PARSER_FILE,
    CHECKPOINT_HELP,
    DEVICE_HELP,
    PARSER_HELP,
    ROBOT_HELP,
    adapt_and_save,
    add_adapt_option,
    check_adapt_budget,
    check_parser_file,
    robot_model,
)
from monose3.atomic import write_text
from monose3.data import validation as v
from monose3.data.frames import (
    format_skipped,
    load_frames,
    load_joints_csv,
    load_joints_dir,
    skipped_annotations,
)
from monose3.data.inputs import load_camera
from monose3.data.video import video_frames
from monose3.errors import Monose3Error
from monose3.report.overlays import save_animation
from monose3.robot import RobotModel
from monose3.tracking import (
    MAX_STEP_DEG,
    MAX_STEP_MM,
    RECHECK_EVERY,
    Tracker,
    TrackingPolicy,
)
from monose3.training.formats import check_checkpoint


def add_track_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", help="DREAM folder or folder of NNNN.png + NNNN.joints.json + camera.json")
    src.add_argument("--video", help="video file (MP4, AVI, GIF...); needs --camera and --joints-csv or --joints")
    jsrc = p.add_mutually_exclusive_group()
    jsrc.add_argument("--joints-csv", help="with --video: CSV, header = joint names, one row per frame (radians)")
    jsrc.add_argument("--joints", help="with --video: folder with one joints JSON per frame (name order)")
    p.add_argument("--camera", help="with --video: intrinsics file (JSON {fx, fy, cx, cy, width, height}, ...)")
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--parser", help=PARSER_HELP)
    p.add_argument("--robot", help=ROBOT_HELP)
    p.add_argument(
        "--sampler",
        choices=["fit", "revdiff"],
        help="fit: refinement on the robot parser's mask and keypoints each frame (default where there is a parser); "
        "revdiff: the paper's one step at a small t",
    )
    p.add_argument(
        "--out",
        default="monose3_track",
        help="folder for poses.jsonl, poses.csv and track.gif (default: monose3_track)",
    )
    p.add_argument("--limit", type=int, help="track only the first N frames of --frames")
    p.add_argument("--reinit-every", type=int, help="run the full process every N frames as well")
    more = "re-initialise when one step"
    p.add_argument("--max-step-mm", type=float, default=MAX_STEP_MM, help=f"{more} moves more [{MAX_STEP_MM:g}]")
    p.add_argument("--max-step-deg", type=float, default=MAX_STEP_DEG, help=f"{more} rotates more [{MAX_STEP_DEG:g}]")
    p.add_argument(
        "--recheck-every",
        type=int,
        default=RECHECK_EVERY,
        help=f"re-estimate a doubted track at most once every N frames [{RECHECK_EVERY}]",
    )
    p.add_argument(
        "--static-camera",
        action="store_true",
        help="the camera does not move: fuse every reliable frame into one camera pose, each frame's start and answer",
    )
    p.add_argument(
        "--refine-at-end",
        action="store_true",
        help="with --static-camera: give the frames before the fused pose converged the final fused pose",
    )
    p.add_argument("--gif-every", type=int, default=1, help="put every N-th frame in track.gif (default 1; 0: no GIF)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of track.gif (default 10)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    add_adapt_option(p, "track")


def check_track_args(args: argparse.Namespace) -> None:
    """Argument combinations, checked before the model is loaded."""
    if args.limit is not None and args.limit < 1:
        raise Monose3Error(f"--limit must be at least 1, got {args.limit}")
    if args.gif_every < 0:
        raise Monose3Error(f"--gif-every must be >= 0, got {args.gif_every}")
    if args.reinit_every is not None:
        v.check_count(args.reinit_every, "--reinit-every")
    if not args.fps > 0:
        raise Monose3Error(f"--fps must be positive, got {args.fps}")
    v.check_count(args.recheck_every, "--recheck-every")
    check_adapt_budget(args)
    if args.adapt and args.frames is None:
        raise Monose3Error("--adapt needs --frames (a folder of frames); for a video, adapt with `monose3 adapt` first")
    if args.refine_at_end and not args.static_camera:
        raise Monose3Error("--refine-at-end goes with --static-camera (it gives earlier frames the fused camera pose)")
    if args.frames is not None:
        if args.joints_csv or args.joints or args.camera:
            raise Monose3Error(
                "--joints-csv/--joints/--camera go with --video; a --frames folder holds its own joints and camera"
            )
        return
    if not Path(args.video).is_file():
        raise Monose3Error(f"video not found: {args.video}; check the path")
    if not args.camera:
        raise Monose3Error("--video needs --camera FILE with the intrinsics {fx, fy, cx, cy, width, height}")
    if not (args.joints_csv or args.joints):
        raise Monose3Error("--video needs the joints of every frame: --joints-csv FILE or --joints DIR")


def check_track(args: argparse.Namespace) -> SimpleNamespace:
    check_track_args(args)
    check_parser_file(args.parser)
    out = v.check_output_dir(args.out, "--out")
    robot = check_checkpoint(args.checkpoint, args.robot)
    frames = video_joints = None
    if args.frames is not None:
        v.check_input_dir(args.frames, "--frames")
        if robot is not None:
            frames = load_frames(args.frames, robot_model(robot))
            frames = frames[: args.limit] if args.limit is not None else frames
            if args.static_camera:
                check_one_camera(frames)
            if args.adapt:
                from monose3.adaptation import check_frame_count

                check_frame_count(len(frames))
    else:
        camera = load_camera(args.camera)
        v.check_K(camera.K, camera.size, args.camera)
        if robot is not None:
            model = robot_model(robot)
            if args.joints_csv:
                video_joints = load_joints_csv(args.joints_csv, model)
            else:
                video_joints = load_joints_dir(args.joints, model)
    return SimpleNamespace(out=out, frames=frames, video_joints=video_joints)


def check_one_camera(frames: Sequence) -> None:
    """``--static-camera``: every frame of the folder has the same image size and intrinsics."""
    if not frames:
        return
    first = frames[0]
    for frame in frames[1:]:
        other_size = tuple(frame.image_size) != tuple(first.image_size)
        if other_size or not np.allclose(frame.K, first.K, rtol=1e-6, atol=1e-6):
            what = "image size" if other_size else "intrinsics"
            raise Monose3Error(
                f"--static-camera: frame {frame.name} has another {what} than frame {first.name}; a static "
                "camera's frames share one camera: track them without --static-camera, or split the folder"
            )


# ---- command line ------------------------------------------------------------------------------


def _frames_for(args: argparse.Namespace, robot: RobotModel) -> Iterable:
    if args.frames is not None:
        frames = load_frames(args.frames, robot)
        return frames[: args.limit] if args.limit is not None else frames
    checked = getattr(args, "checked_inputs", None)
    if checked is not None and checked.video_joints is not None:
        names, joints = checked.video_joints
    elif args.joints_csv:
        names, joints = load_joints_csv(args.joints_csv, robot)
    else:
        names, joints = load_joints_dir(args.joints, robot)
    return video_frames(args.video, args.camera, joints, names)


def run_track(args: argparse.Namespace) -> int:

    from monose3.api import load_estimator
    from monose3.report.sequences import (
        TrackFrame,
        format_summary,
        overlay_tile,
        refine_at_end,
        track_sequence,
        write_outputs,
    )

    checked = getattr(args, "checked_inputs", None) or check_track(args)  # inputs checked before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, device=args.device, parser=args.parser)
    out = checked.out
    tiles: list[np.ndarray] = []
    skipped: list[dict] = []
    policy = TrackingPolicy(args.max_step_mm, args.max_step_deg, args.reinit_every, args.recheck_every,
                            args.static_camera)  # fmt: skip
    tracker = Tracker(estimator, policy, **({"sampler": args.sampler} if args.sampler else {}))
    try:
        frames = checked.frames
        if frames is None:
            frames = _frames_for(args, estimator.robot)  # inputs checked before any output is written
        skipped.extend(skipped_annotations(frames))
        adapted = []
        if args.adapt:
            adapted = adapt_and_save(estimator, list(frames), args.static_camera, args, out / ADAPTED_PARSER_FILE)

        def on_frame(frame, image: np.ndarray, result: TrackFrame) -> None:
            if args.gif_every and result.index % args.gif_every == 0:
                tiles.append(overlay_tile(estimator, frame, image, result))

        results = track_sequence(estimator, frames, on_frame=on_frame, skipped=skipped, tracker=tracker)
        if args.refine_at_end:
            changed = refine_at_end(results, tracker.fusion, estimator.robot)
            print(f"--refine-at-end: {changed} earlier frame(s) given the final fused pose")
    finally:
        estimator.close()
    written = write_outputs(out, results, tracker.fusion) + adapted
    if tiles:
        written.append(_save_gif(tiles, out / "track.gif", args.fps))
    if skipped:
        written.append(write_text(out / "skipped.json", json.dumps({"skipped": skipped}, indent=1)))
    print(format_summary(results, tracker.fusion))
    line = format_skipped("frames", skipped, where=str(out / "skipped.json"))
    if line:
        print(line)
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _save_gif(tiles: list[np.ndarray], path: Path, fps: float) -> Path:
    """The overlays as one animation; frames of a folder may differ in size, the animation cannot."""
    h, w = tiles[0].shape[:2]
    tiles = [t if t.shape[:2] == (h, w) else cv2.resize(t, (w, h), interpolation=cv2.INTER_AREA) for t in tiles]
    return save_animation(tiles, path, fps=fps)
