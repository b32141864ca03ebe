"""Evaluation on annotated data: ADD of every frame of a dataset (batched, or one frame at a
time through the tracking policy), the per-frame JSON records and denoising-step overlays.

Frames stream through in small batches, so memory stays flat however many frames there are.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from monose3 import atomic
from monose3.data.frames import load_images, skipped_annotations
from monose3.errors import Monose3Error
from monose3.estimator import Estimate, PoseEstimator
from monose3.report.metrics import add_per_frame, summarize
from monose3.report.overlays import denoising_strip
from monose3.robot.jobs import RenderJob
from monose3.tracking import Tracker, TrackStep


@dataclass
class DatasetResult:
    name: str
    adds: list[float] = field(default_factory=list)
    frames: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    skipped: list[dict] = field(default_factory=list)  # {"frame", "reason"}: unreadable image or annotation

    def summary(self) -> dict:
        fps = len(self.adds) / self.seconds if self.seconds > 0 else None
        out = summarize(np.asarray(self.adds), fps=fps)
        out["skipped"] = len(self.skipped)
        return out


def _batches(n: int, size: int, limit: int | None) -> list[range]:
    n = n if limit is None else min(n, limit)
    return [range(i, min(i + size, n)) for i in range(0, n, size)]


def evaluate_dataset(
    estimator: PoseEstimator,
    frames: Sequence,
    name: str,
    sampler: str | None = None,
    ddim_steps: int | None = None,
    direct_steps: int | None = None,
    batch_size: int = 4,
    limit: int | None = None,
    overlay_frames: Sequence[int] = (),
    overlay_dir: Path | None = None,
    tracking: bool = False,
    progress: bool = True,
) -> DatasetResult:
    """ADD of every frame; an estimate out of view counts as infinite ADD. Frames whose image
    cannot be read are skipped and listed in ``result.skipped`` (with those the reader left
    out for bad annotations); Monose3Error when no frame is usable.

    ``tracking``: frames are a sequence, estimated one at a time by the tracking policy that
    ``monose3 track`` uses (:class:`~monose3.tracking.Tracker`: the full reverse process
    with ``sampler``/``ddim_steps``/``direct_steps`` first and on re-initialisation, one step
    from the previous estimate otherwise); each frame's record then has its ``mode`` and ``reason``.
    """
    result = DatasetResult(name, skipped=skipped_annotations(frames))
    full = {"sampler": sampler, "ddim_steps": ddim_steps, "direct_steps": direct_steps}
    tracker = Tracker(estimator, **full) if tracking else None
    batches = _batches(len(frames), 1 if tracking else batch_size, limit)
    for idx in tqdm(batches, desc=f"evaluate {name}", unit="batch", disable=not progress):
        pairs = [(i, frames[i]) for i in idx]
        batch, images = load_images([f for _, f in pairs], result.skipped)
        if not batch:
            continue
        idx = [i for i, f in pairs if any(f is b for b in batch)]
        Ks = np.stack([f.K for f in batch])
        joints = np.stack([f.joints for f in batch])
        tick = time.perf_counter()
        step = tracker.update(images[0], Ks[0], joints[0]) if tracker is not None else None
        est = step.estimate if step is not None else estimator.estimate(images, Ks, joints, **full)
        result.seconds += time.perf_counter() - tick
        poses = est.poses if step is None else step.camera_from_base[None]
        in_view = est.in_view if step is None else np.array([step.in_view])
        pred = estimator.robot.keypoints(joints, poses)
        gt = np.stack([f.keypoints_3d for f in batch])
        adds = add_per_frame(pred, gt)
        adds[~in_view] = np.inf
        for j, frame in enumerate(batch):
            result.adds.append(float(adds[j]))
            result.frames.append(frame_record(frame, float(adds[j]), est, j, step))
        for j, i in enumerate(idx):
            if i in overlay_frames and overlay_dir is not None:
                _denoising_overlay(
                    estimator,
                    images[j],
                    Ks[j],
                    joints[j],
                    [h[j, 0] for h in est.history],
                    overlay_dir / f"{name}_{frame_label(batch[j])}.png",
                )
    if not result.adds:
        raise no_usable_frame(name, result.skipped)
    return result


def no_usable_frame(name: str, skipped: list[dict]) -> Monose3Error:
    """The error for a dataset of which no frame could be evaluated."""
    if skipped:
        first = skipped[0]
        return Monose3Error(
            f"no usable frame in {name}: all {len(skipped)} were skipped (first: {first['frame']}: {first['reason']})"
        )
    return Monose3Error(f"no frames to evaluate in {name}; give a DREAM or RoboKeyGen folder with frames")


def frame_record(frame, add: float, est: Estimate, j: int, step: TrackStep | None) -> dict:
    """The JSON record of frame ``j`` of ``est`` (with the tracking policy's mode and reason)."""
    record = {
        "frame": frame.name,
        "add_m": atomic.json_number(add),
        "camera_from_base": (est.poses[j] if step is None else step.camera_from_base).tolist(),
        "in_view": bool(est.in_view[j] if step is None else step.in_view),
    }
    if est.fit_iou is not None:
        record.update(silhouette_iou=float(est.fit_iou[j]), keypoint_px=float(est.keypoint_px[j]),
                      edge_support=float(est.edge_support[j]), reliable=bool(est.reliable[j]),
                      edge_distance_px=atomic.json_number(est.edge_distance_px[j]),
                      doubts=est.doubts[j])  # fmt: skip
    if step is not None:
        record.update(mode=step.mode, reason=step.reason, confidence=atomic.json_number(step.confidence),
                      reliable=step.reliable, doubts=step.doubts)  # fmt: skip
    return record


def frame_label(frame) -> str:
    return str(frame.name).replace("/", "_")


def _denoising_overlay(estimator: PoseEstimator, image, K, joints, poses, path: Path) -> None:
    """Overlays of the render on the image at each denoising step (paper's Fig. 3b)."""
    h, w = image.shape[:2]
    masks = [mask for _, mask in estimator.renderer.render_jobs([RenderJob(joints, p, K, (w, h)) for p in poses])]
    labels = ["init"] + [f"step {i}" for i in range(1, len(poses))]
    denoising_strip(image, masks, labels, path)


def _strict(value):
    """``value`` with every non-finite float replaced by None, so the JSON is strict."""
    if isinstance(value, float):
        return atomic.json_number(value)
    if isinstance(value, dict):
        return {k: _strict(x) for k, x in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(x) for x in value]
    return value


def write_json(results: Sequence[DatasetResult], path: Path, meta: dict) -> None:
    """Summary, per-frame results and skipped frames of every dataset, written atomically."""
    data = {
        "meta": meta,
        "datasets": {r.name: {"summary": r.summary(), "frames": r.frames, "skipped": r.skipped} for r in results},
    }
    atomic.write_text(path, json.dumps(_strict(data), indent=1, default=float, allow_nan=False))
