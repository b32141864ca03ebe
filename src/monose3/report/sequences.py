"""A tracked sequence (``monose3 track``): each frame's record (:class:`TrackFrame`), the loop
over a sequence's frames with the shared tracking policy (:func:`track_sequence`), the summary
printed at the end and the output files (``poses.jsonl``, ``poses.csv``, ``camera_pose.json``)."""

from __future__ import annotations

import csv
import json
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from monose3.atomic import atomic_path, json_number, write_text
from monose3.errors import Monose3Error
from monose3.report.metrics import FAILURE_MM, add_per_frame
from monose3.report.overlays import pose_overlays
from monose3.robot import RobotModel
from monose3.tracking import MODE_FULL, MODE_FUSED, MODE_TRACK, StaticFusion, Tracker, TrackingPolicy, TrackStep

PRINT_ALL_FRAMES = 40
GIF_TILE_WIDTH = 320


@dataclass
class TrackFrame:
    """The estimate of one frame of a sequence."""

    index: int
    name: str
    camera_from_base: np.ndarray
    mode: str  # where the pose comes from: "full" (a full estimate), "track" (refined from the previous frame), "fused"
    reason: str | None  # why a full estimate ran: first, lost, out of view, jump, doubted, periodic
    in_view: bool
    step_mm: float | None = None  # mean keypoint motion of the tracked pose from the previous one (also when not kept)
    step_deg: float | None = None  # its rotation
    seconds: float = 0.0
    add_mm: float | None = None  # ground truth only; inf when the estimate is out of view
    confidence: float | None = None  # the fit's silhouette IoU (None: nothing to judge by)
    reliable: bool | None = None
    doubts: list[str] = field(default_factory=list)
    decision: str | None = None  # a full estimate ran and the track was kept: why
    fused_frames: int = 0  # --static-camera: frames in the fused pose after this one
    converged: bool = False  # --static-camera: the fused pose had converged
    alternative: np.ndarray | None = None  # the candidate not chosen (not written)
    joints: np.ndarray | None = None  # kept for the ADD of --refine-at-end (not written)
    gt_keypoints: np.ndarray | None = None

    @classmethod
    def of_step(cls, index: int, name: str, step: TrackStep) -> TrackFrame:
        return cls(index, name, step.camera_from_base, step.mode, step.reason, step.in_view, step.step_mm,
                   step.step_deg, confidence=step.confidence, reliable=step.reliable, doubts=step.doubts,
                   decision=step.decision, fused_frames=step.fused_frames, converged=step.converged,
                   alternative=step.alternative)  # fmt: skip

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "frame": self.name,
            "mode": self.mode,
            "reason": self.reason,
            "decision": self.decision,
            "in_view": self.in_view,
            "confidence": json_number(self.confidence),
            "reliable": self.reliable,
            "doubts": self.doubts,
            "camera_from_base": [float(v) for v in self.camera_from_base.reshape(-1)],
            "step_mm": json_number(self.step_mm),
            "step_deg": json_number(self.step_deg),
            "fused_frames": self.fused_frames,
            "seconds": float(self.seconds),
            "add_mm": json_number(self.add_mm),
        }

    def set_add(self, robot: RobotModel) -> None:
        """The ADD against the frame's ground-truth keypoints (when it has them)."""
        if self.gt_keypoints is None:
            return
        if not self.in_view:
            self.add_mm = math.inf
            return
        pred = robot.keypoints(self.joints[None], self.camera_from_base[None])
        self.add_mm = 1000.0 * float(add_per_frame(pred, self.gt_keypoints[None])[0])


def track_sequence(
    estimator,
    frames_iter: Iterable,
    policy: TrackingPolicy | None = None,
    on_frame: Callable[[object, np.ndarray, TrackFrame], None] | None = None,
    skipped: list[dict] | None = None,
    sampler: str | None = None,
    tracker: Tracker | None = None,
) -> list[TrackFrame]:
    """Track the camera-from-base pose over ``frames_iter`` (objects with ``name``, ``K``,
    ``joints``, ``load_image()``; with ``keypoints_3d`` the ADD is filled in) with the shared
    :class:`~monose3.tracking.Tracker` (``tracker``, or one made with ``policy``).

    ``on_frame(frame, image, result)`` is called after each frame (for overlays without keeping
    the images). Returns one :class:`TrackFrame` per usable frame; a frame whose image cannot be
    read is skipped (tracking goes on from the last estimate) and appended to ``skipped`` as
    ``{"frame", "reason"}``.
    """
    skipped = [] if skipped is None else skipped
    tracker = tracker or Tracker(estimator, policy, **({"sampler": sampler} if sampler else {}))
    out: list[TrackFrame] = []
    progress = tqdm(frames_iter, desc="track", unit="frame", leave=False, disable=None)
    for index, frame in enumerate(progress):
        try:
            image = frame.load_image()
        except Monose3Error as err:
            skipped.append({"frame": str(frame.name), "reason": str(err)})
            continue
        tick = time.perf_counter()
        result = TrackFrame.of_step(index, str(frame.name), tracker.update(image, frame.K, frame.joints))
        result.seconds = time.perf_counter() - tick
        gt = getattr(frame, "keypoints_3d", None)
        if gt is not None:
            result.joints, result.gt_keypoints = np.asarray(frame.joints, np.float64), np.asarray(gt, np.float64)
            result.set_add(estimator.robot)
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


def refine_at_end(results: Sequence[TrackFrame], fusion: StaticFusion, robot: RobotModel) -> int:
    """``--refine-at-end``: the frames before the fused pose converged get the final fused pose
    (when it converged); returns how many."""
    if not fusion.converged:
        return 0
    changed = 0
    for r in results:
        if r.mode != MODE_FUSED:
            r.alternative, r.camera_from_base = r.camera_from_base, fusion.pose.copy()
            r.mode, r.in_view, r.reliable, r.doubts = MODE_FUSED, True, True, []
            r.decision = "given the final fused pose at the end"
            r.set_add(robot)
            changed += 1
    return changed


def format_summary(results: Sequence[TrackFrame], fusion: StaticFusion | None = None,
                   max_frames: int = PRINT_ALL_FRAMES) -> str:  # fmt: skip
    lines = []
    has_gt = any(r.add_mm is not None for r in results)
    if len(results) <= max_frames:
        for r in results:
            row = f"{r.name:>16} {r.mode:>5} {r.reason or '':>12}"
            if r.step_mm is not None:
                row += f"  step {r.step_mm:6.1f} mm {r.step_deg:5.2f} deg"
            if r.confidence is not None:
                row += f"  conf {r.confidence:.2f}" + ("" if r.reliable else " UNRELIABLE")
            if r.add_mm is not None:
                row += f"  ADD {r.add_mm:7.1f} mm" if math.isfinite(r.add_mm) else "  ADD failed"
            lines.append(row)
    counts = Counter(r.mode for r in results)
    why = ", ".join(f"{n} {k}" for k, n in Counter(r.reason for r in results if r.reason).items())
    kept = sum(r.decision is not None and r.mode == MODE_TRACK for r in results)
    lines.append(
        f"frames: {len(results)}; full estimates run: {sum(r.reason is not None for r in results)} ({why or 'none'}), "
        f"{kept} of them kept the track; poses from full {counts[MODE_FULL]}, track {counts[MODE_TRACK]}, "
        f"fused {counts[MODE_FUSED]}"
    )
    reliable = [r for r in results if r.reliable is not None]
    if reliable:
        lines.append(f"reliable: {sum(bool(r.reliable) for r in reliable)} of {len(reliable)}")
    track = [r for r in results if r.reason is None]
    full = [r for r in results if r.reason is not None]
    if track:
        t = float(np.mean([r.seconds for r in track]))
        line = f"time per frame: track {t:.3f} s ({1 / t:.1f} FPS)"
        lines.append(line + (f", with a full estimate {np.mean([r.seconds for r in full]):.3f} s" if full else ""))
    if fusion is not None:
        lines.append(fused_line(results, fusion))
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


def fused_line(results: Sequence[TrackFrame], fusion: StaticFusion) -> str:
    """How the static camera's fused pose converged, in one line."""
    if fusion.pose is None:
        return "static camera: no reliable frame, so no fused pose"
    first = next((r.index for r in results if r.converged), None)
    state = f"converged at frame {first}" if first is not None else "NOT converged"
    return (f"static camera: fused from {len(fusion.poses)} reliable frames, {state}; frames' median distance to it "
            f"{fusion.spread_mm:.1f} mm (standard error about {fusion.standard_error_mm:.1f} mm)"
            + (f"; restarted {fusion.resets} time(s): the camera moved" if fusion.resets else ""))  # fmt: skip


CSV_HEADER = ["index", "frame", "mode", "reason", "in_view", "confidence", "reliable", "doubts",
              *(f"m{r}{c}" for r in range(4) for c in range(4)), "add_mm"]  # fmt: skip


def csv_row(d: dict) -> list:
    reliable = "" if d["reliable"] is None else int(d["reliable"])
    confidence = "" if d["confidence"] is None else f"{d['confidence']:.4f}"
    return (
        [d["index"], d["frame"], d["mode"], d["reason"] or "", int(d["in_view"]), confidence, reliable]
        + ["; ".join(d["doubts"])]
        + [f"{v:.9g}" for v in d["camera_from_base"]]
        + ["" if d["add_mm"] is None else f"{d['add_mm']:.3f}"]
    )


def write_outputs(out: Path, results: Sequence[TrackFrame], fusion: StaticFusion | None) -> list[Path]:
    """``poses.jsonl``, ``poses.csv`` and, for a static camera, ``camera_pose.json``, each atomically."""
    records = [r.to_dict() for r in results]
    lines = "".join(json.dumps(d, allow_nan=False) + "\n" for d in records)
    written = [write_text(out / "poses.jsonl", lines)]
    with atomic_path(out / "poses.csv") as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_HEADER)
        writer.writerows(csv_row(d) for d in records)
    written.append(out / "poses.csv")
    if fusion is not None:
        summary = {k: json_number(v) if isinstance(v, float) else v for k, v in fusion.summary().items()}
        if fusion.pose is not None:
            summary["base_from_camera"] = np.linalg.inv(fusion.pose).tolist()
        written.append(write_text(out / "camera_pose.json", json.dumps({"units": "meters", **summary}, indent=2)))
    return written


def overlay_tile(estimator, frame, image: np.ndarray, result: TrackFrame) -> np.ndarray:
    """The GIF tile of one frame: the estimate's overlay, labelled with the mode, the flag and the ADD."""
    text = f"{result.name} {result.mode}" + (f" ({result.reason})" if result.reason else "")
    if result.confidence is not None:
        text += f" {result.confidence:.2f}" + ("" if result.reliable else " UNRELIABLE")
    if result.add_mm is not None and math.isfinite(result.add_mm):
        text += f" ADD {result.add_mm:.0f} mm"
    gt = getattr(frame, "keypoints_3d", None)
    pose = result.camera_from_base
    renderer = estimator.renderer
    return pose_overlays(renderer, [image], [frame.K], [frame.joints], [pose], [text], [gt], GIF_TILE_WIDTH)[0]
