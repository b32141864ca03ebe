"""``monose3 track``: the pose over a sequence, one cheap step per frame (the paper's tracking).

The policy (full estimate first, then one step per frame, re-initialised on loss, jumps and
periodically) is :mod:`monose3.method.tracking`'s, shared with ``monose3 evaluate --sampler tracking``.

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
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from monose3.atomic import atomic_path, write_text
from monose3.data.frame import Frame
from monose3.data.frames import (
    format_skipped,
    load_frames,
    load_joints_csv,
    load_joints_dir,
    skipped_annotations,
)
from monose3.data.inputs import load_camera
from monose3.errors import Monose3Error
from monose3.method.tracking import MODE_FULL, MODE_TRACK, Tracker, TrackingPolicy
from monose3.report.metrics import FAILURE_MM
from monose3.report.overlays import pose_overlays, save_animation
from monose3.robot import RobotModel

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
        num = lambda v: None if v is None or not math.isfinite(v) else float(v)  # noqa: E731
        return {
            "index": self.index,
            "frame": self.name,
            "mode": self.mode,
            "reason": self.reason,
            "in_view": self.in_view,
            "camera_from_base": [float(v) for v in self.camera_from_base.reshape(-1)],
            "step_mm": num(self.step_mm),
            "step_deg": num(self.step_deg),
            "seconds": float(self.seconds),
            "add_mm": num(self.add_mm),
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
    :class:`~monose3.method.tracking.Tracker` and ``policy``.

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


# ---- video input -----------------------------------------------------------------------------


def read_video(path: str | Path) -> Iterator[np.ndarray]:
    """The frames of a video file as RGB uint8 arrays (OpenCV's FFmpeg; imageio/Pillow for what
    OpenCV cannot open, such as GIFs on some builds)."""
    p = Path(path)
    if not p.is_file():
        raise Monose3Error(f"video not found: {p}; check the path")
    cap = cv2.VideoCapture(str(p))
    count = 0
    try:
        while cap.isOpened():
            ok, bgr = cap.read()
            if not ok:
                break
            count += 1
            yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    finally:
        cap.release()
    if count:
        return
    import imageio.v3 as iio

    try:
        frames = iio.imiter(p)
        for frame in frames:
            img = np.asarray(frame)
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            yield np.ascontiguousarray(img[:, :, :3]).astype(np.uint8, copy=False)
            count += 1
    except Exception as err:  # noqa: BLE001 - any decoder failure means the same to the user
        if count:
            raise Monose3Error(f"video {p} is corrupt after frame {count} ({type(err).__name__})") from None
        raise Monose3Error(
            f"cannot read video {p} ({type(err).__name__}); convert it to MP4 (H.264) or a folder of PNG frames"
        ) from None
    if not count:
        raise Monose3Error(f"video {p} has no frames; check the file")


def count_video_frames(path: str | Path) -> int:
    """Number of decodable frames (counted by grabbing, not from the header, which can be wrong)."""
    cap = cv2.VideoCapture(str(path))
    n = 0
    try:
        while cap.isOpened() and cap.grab():
            n += 1
    finally:
        cap.release()
    return n if n else sum(1 for _ in read_video(path))


def video_frames(
    video: str | Path, camera_file: str | Path, joints: np.ndarray, names: Sequence[str] | None = None
) -> Iterator[Frame]:
    """The frames of a video with their joints. The camera file and the frame count are checked
    here, before anything is estimated; the frames are then decoded one at a time."""
    camera = load_camera(camera_file)
    n = count_video_frames(video)
    if n != len(joints):
        raise Monose3Error(
            f"video {Path(video).name} has {n} frames but {len(joints)} joint rows were given; "
            "give exactly one row (file) of joints per video frame"
        )

    def frames() -> Iterator[Frame]:
        for i, image in enumerate(read_video(video)):
            name = names[i] if names is not None and names[i] else f"{i:06d}"
            yield Frame(name, camera.K, camera.size, joints[i], image=image)

    return frames()


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
    from monose3.apps.arguments import check_track

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
