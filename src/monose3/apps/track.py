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
``poses.jsonl`` and ``poses.csv`` (per frame: name, mode full|track, why a full estimate was
run, camera_from_base flattened row-major, meters) and ``track.gif`` (the overlays).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from monose3.apps.arguments import (
    CHECKPOINT_HELP,
    DEVICE_HELP,
    PARSER_HELP,
    ROBOT_HELP,
    check_parser_file,
    robot_model,
)
from monose3.atomic import atomic_path, json_number, write_text
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
from monose3.report.metrics import FAILURE_MM
from monose3.report.overlays import pose_overlays, save_animation
from monose3.robot import RobotModel
from monose3.tracking import MAX_STEP_DEG, MAX_STEP_MM, MODE_FULL, MODE_TRACK, Tracker, TrackingPolicy
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
    p.add_argument("--gif-every", type=int, default=1, help="put every N-th frame in track.gif (default 1; 0: no GIF)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of track.gif (default 10)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)


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


GIF_TILE_WIDTH = 320
PRINT_ALL_FRAMES = 40


@dataclass
class TrackFrame:
    """The estimate of one frame of a sequence."""

    index: int
    name: str
    camera_from_base: np.ndarray
    mode: str  # "full" (reverse process from the initialisation) or "track" (1 step from the previous frame)
    reason: str | None  # why the full process ran: first, lost, out of view, jump, periodic
    in_view: bool
    step_mm: float | None = None  # mean keypoint motion of the 1-step update (also when it was rejected)
    step_deg: float | None = None  # rotation of the 1-step update
    seconds: float = 0.0
    add_mm: float | None = None  # ground truth only; inf when the estimate is out of view

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "frame": self.name,
            "mode": self.mode,
            "reason": self.reason,
            "in_view": self.in_view,
            "camera_from_base": [float(v) for v in self.camera_from_base.reshape(-1)],
            "step_mm": json_number(self.step_mm),
            "step_deg": json_number(self.step_deg),
            "seconds": float(self.seconds),
            "add_mm": json_number(self.add_mm),
        }


def track_sequence(
    estimator,
    frames_iter: Iterable,
    policy: TrackingPolicy | None = None,
    on_frame: Callable[[object, np.ndarray, TrackFrame], None] | None = None,
    skipped: list[dict] | None = None,
    sampler: str | None = None,
) -> list[TrackFrame]:
    """Track the camera-from-base pose over ``frames_iter`` (objects with ``name``, ``K``,
    ``joints``, ``load_image()``; with ``keypoints_3d`` the ADD is filled in) with the shared
    :class:`~monose3.tracking.Tracker` and ``policy``.

    ``on_frame(frame, image, result)`` is called after each frame (for streaming output and
    overlays without keeping the images). Returns one :class:`TrackFrame` per usable frame; a
    frame whose image cannot be read is skipped (tracking goes on from the last estimate) and
    appended to ``skipped`` as ``{"frame", "reason"}``.
    """
    skipped = [] if skipped is None else skipped
    tracker = Tracker(estimator, policy, **({"sampler": sampler} if sampler else {}))
    robot: RobotModel = estimator.robot
    out: list[TrackFrame] = []
    for index, frame in enumerate(frames_iter):
        try:
            image = frame.load_image()
        except Monose3Error as err:
            skipped.append({"frame": str(frame.name), "reason": str(err)})
            continue
        tick = time.perf_counter()
        step = tracker.update(image, frame.K, frame.joints)
        result = TrackFrame(
            index,
            str(frame.name),
            step.camera_from_base,
            step.mode,
            step.reason,
            step.in_view,
            step.step_mm,
            step.step_deg,
        )
        result.seconds = time.perf_counter() - tick
        gt = getattr(frame, "keypoints_3d", None)
        if gt is not None:
            if result.in_view:
                kp = robot.keypoints(np.asarray(frame.joints, np.float64)[None], result.camera_from_base[None])[0]
                result.add_mm = float(1000.0 * np.linalg.norm(kp - np.asarray(gt), axis=1).mean())
            else:
                result.add_mm = float("inf")
        out.append(result)
        if on_frame is not None:
            on_frame(frame, image, result)
    if not out and skipped:
        raise Monose3Error(
            f"no usable frame: all {len(skipped)} were skipped (first: {skipped[0]['frame']}: {skipped[0]['reason']})"
        )
    if not out:
        raise Monose3Error("no frames to track; give a folder or video with at least one frame")
    return out


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


def format_summary(results: Sequence[TrackFrame], max_frames: int = PRINT_ALL_FRAMES) -> str:
    lines = []
    has_gt = any(r.add_mm is not None for r in results)
    if len(results) <= max_frames:
        for r in results:
            row = f"{r.name:>16} {r.mode:>5} {r.reason or '':>12}"
            if r.step_mm is not None:
                row += f"  step {r.step_mm:6.1f} mm {r.step_deg:5.2f} deg"
            if r.add_mm is not None:
                row += f"  ADD {r.add_mm:7.1f} mm" if math.isfinite(r.add_mm) else "  ADD failed"
            lines.append(row)
    full = [r for r in results if r.mode == MODE_FULL]
    track = [r for r in results if r.mode == MODE_TRACK]
    why = ", ".join(f"{n} {k}" for k, n in Counter(r.reason for r in full).items())
    lines.append(f"frames: {len(results)}; full: {len(full)} ({why}); track: {len(track)}")
    if track:
        t = float(np.mean([r.seconds for r in track]))
        lines.append(
            f"time per frame: track {t:.3f} s ({1 / t:.1f} FPS), full {np.mean([r.seconds for r in full]):.3f} s"
        )
    if has_gt:
        adds = np.array([r.add_mm for r in results if r.add_mm is not None])
        ok = adds[np.isfinite(adds)]
        if ok.size:
            lines.append(
                f"ADD vs ground truth: mean {ok.mean():.1f} mm, median {np.median(ok):.1f} mm, "
                f"failures (ADD > {FAILURE_MM:g} mm or out of view) {int((~(adds <= FAILURE_MM)).sum())} "
                f"of {len(adds)}, out of view {int((~np.isfinite(adds)).sum())}"
            )
        else:
            lines.append(f"ADD vs ground truth: every frame failed ({len(adds)})")
    return "\n".join(lines)


def overlay_tile(estimator, frame, image: np.ndarray, result: TrackFrame) -> np.ndarray:
    """The GIF tile of one frame: the estimate's overlay, labelled with the mode and the ADD."""
    text = f"{result.name} {result.mode}" + (f" ({result.reason})" if result.reason else "")
    if result.add_mm is not None and math.isfinite(result.add_mm):
        text += f" ADD {result.add_mm:.0f} mm"
    gt = getattr(frame, "keypoints_3d", None)
    pose = result.camera_from_base
    renderer = estimator.renderer
    return pose_overlays(renderer, [image], [frame.K], [frame.joints], [pose], [text], [gt], GIF_TILE_WIDTH)[0]


def run_track(args: argparse.Namespace) -> int:

    from monose3.api import load_estimator

    checked = getattr(args, "checked_inputs", None) or check_track(args)  # inputs checked before the model loads
    estimator = load_estimator(args.checkpoint, robot=args.robot, device=args.device, parser=args.parser)
    out = checked.out
    tiles: list[np.ndarray] = []
    skipped: list[dict] = []
    jsonl_path, csv_path = out / "poses.jsonl", out / "poses.csv"
    try:
        frames = checked.frames
        if frames is None:
            frames = _frames_for(args, estimator.robot)  # inputs checked before any output is written
        skipped.extend(skipped_annotations(frames))
        # Written to temporary files that replace poses.jsonl / poses.csv only when the run ends
        # well: an interrupted or failed run leaves no partial outputs.
        with (
            atomic_path(jsonl_path) as jsonl_tmp,
            atomic_path(csv_path) as csv_tmp,
            jsonl_tmp.open("w") as jf,
            csv_tmp.open("w", newline="") as cf,
        ):
            writer = csv.writer(cf)
            writer.writerow(
                ["index", "frame", "mode", "reason", "in_view", *(f"m{r}{c}" for r in range(4) for c in range(4))]
                + ["add_mm"]
            )

            def on_frame(frame, image: np.ndarray, result: TrackFrame) -> None:
                d = result.to_dict()
                jf.write(json.dumps(d, allow_nan=False) + "\n")
                writer.writerow(
                    [d["index"], d["frame"], d["mode"], d["reason"] or "", int(d["in_view"])]
                    + [f"{v:.9g}" for v in d["camera_from_base"]]
                    + ["" if d["add_mm"] is None else f"{d['add_mm']:.3f}"]
                )
                if args.gif_every and result.index % args.gif_every == 0:
                    tiles.append(overlay_tile(estimator, frame, image, result))

            policy = TrackingPolicy(args.max_step_mm, args.max_step_deg, args.reinit_every)
            results = track_sequence(
                estimator, frames, policy, on_frame=on_frame, skipped=skipped, sampler=args.sampler
            )
    finally:
        estimator.close()
    written = [jsonl_path, csv_path]
    if tiles:
        written.append(_save_gif(tiles, out / "track.gif", args.fps))
    if skipped:
        written.append(write_text(out / "skipped.json", json.dumps({"skipped": skipped}, indent=1)))
    print(format_summary(results))
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
