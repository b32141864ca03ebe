"""Calibration of a static camera: one camera-to-robot extrinsic fused from many frames.

A single image gives an estimate a few centimetres off, and now and then a badly wrong one.
When the camera does not move while the robot goes through many configurations, every
frame estimates the same transform, so fusing them cancels most of the noise -- provided
the wrong ones are thrown out first instead of averaged in:

1. estimate every frame (batched; ``chains`` > 1 runs that many stochastic reverse chains per
   frame, whose disagreement measures the frame's uncertainty);
2. reject frames whose estimate puts the robot outside the image ("out of view") and, with
   several chains, those whose chains disagree by more than ``UNRELIABLE_MM`` ("unreliable chains");
3. fuse the rest robustly (:func:`monose3.geometry.averaging.robust_consensus`: geodesic L1
   median of the rotations, geometric median of the translations, frames beyond
   ``median + k * 1.4826 * MAD`` of the residuals rejected as "far from consensus", the
   inliers fused again).

``monose3 calibrate`` (:mod:`monose3.apps.calibrate`) is the command around it.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from monose3.atomic import json_number
from monose3.data.frames import load_images, skipped_annotations
from monose3.errors import Monose3Error
from monose3.estimator import UNRELIABLE_MM
from monose3.geometry.averaging import (
    CONSENSUS_K,
    CONSENSUS_MIN_DEG,
    CONSENSUS_MIN_MM,
    pose_residuals,
    robust_consensus,
    robust_pose_average,
)
from monose3.geometry.rotations import matrix_to_quat_xyzw
from monose3.report.metrics import add_per_frame
from monose3.report.overlays import image_grid, pose_overlays
from monose3.robot import RobotModel

# Ground-truth poses of a static camera that spread more than this are reported as a moving camera.
STATIC_GT_MM = 5.0
OVERLAY_TILE_WIDTH = 480

REASON_OUT_OF_VIEW = "out of view"
REASON_UNRELIABLE = "unreliable chains"
REASON_POOR_FIT = "unreliable fit"
REASON_CONSENSUS = "far from consensus"


def _has_ground_truth(frames: Sequence) -> bool:
    return len(frames) > 0 and all(
        getattr(f, "pose", None) is not None and getattr(f, "keypoints_3d", None) is not None for f in frames
    )


# ---- calibration ------------------------------------------------------------------------------


@dataclass
class FrameResult:
    """One frame's single-frame estimate and what the fusion made of it."""

    name: str
    camera_from_base: np.ndarray
    in_view: bool
    chain_spread_mm: float
    chain_spread_deg: float
    fit_reliable: bool | None = None  # the "fit" sampler's reliable flag (None for the paper's samplers)
    residual_mm: float = float("nan")  # translation distance to the fused pose
    residual_deg: float = float("nan")  # rotation angle to the fused pose
    used: bool = False
    reason: str | None = None  # why it was rejected
    add_single_mm: float | None = None  # ground truth only: ADD of this frame's own estimate
    add_fused_mm: float | None = None  # ground truth only: ADD of the fused pose on this frame

    def to_dict(self) -> dict:
        return {
            "frame": self.name,
            "used": self.used,
            "rejected_because": self.reason,
            "residual_mm": json_number(self.residual_mm),
            "residual_deg": json_number(self.residual_deg),
            "in_view": self.in_view,
            "fit_reliable": self.fit_reliable,
            "chain_spread_mm": json_number(self.chain_spread_mm),
            "chain_spread_deg": json_number(self.chain_spread_deg),
            "add_single_mm": json_number(self.add_single_mm),
            "add_fused_mm": json_number(self.add_fused_mm),
            "camera_from_base": self.camera_from_base.tolist(),
        }


@dataclass
class CalibrationResult:
    """The fused extrinsic (camera-from-base, meters, OpenCV camera axes) and how it was made."""

    camera_from_base: np.ndarray
    frames: list[FrameResult]
    chains: int
    threshold_mm: float
    threshold_deg: float
    ground_truth: dict | None = None
    seconds: float = 0.0
    meta: dict = field(default_factory=dict)
    skipped: list[dict] = field(default_factory=list)  # {"frame", "reason"}: unreadable image or annotation

    @property
    def base_from_camera(self) -> np.ndarray:
        return np.linalg.inv(self.camera_from_base)

    @property
    def used(self) -> list[FrameResult]:
        return [f for f in self.frames if f.used]

    @property
    def rejected(self) -> dict[str, int]:
        """How many frames were rejected for each reason."""
        return dict(Counter(f.reason for f in self.frames if not f.used))

    @property
    def spread(self) -> dict[str, float]:
        """Residuals of the inliers to the fused pose: how much the single frames still disagree."""
        mm = np.array([f.residual_mm for f in self.used])
        deg = np.array([f.residual_deg for f in self.used])
        n = len(mm)
        return {
            "median_mm": float(np.median(mm)),
            "rms_mm": float(np.sqrt(np.mean(mm**2))),
            "max_mm": float(mm.max()),
            "median_deg": float(np.median(deg)),
            "rms_deg": float(np.sqrt(np.mean(deg**2))),
            "max_deg": float(deg.max()),
            # Standard error of a mean of n independent frames; a rough size of the fused pose's
            # own noise (frames of one scene are not fully independent, so it is optimistic).
            "standard_error_mm": float(np.sqrt(np.mean(mm**2)) / np.sqrt(n)),
            "standard_error_deg": float(np.sqrt(np.mean(deg**2)) / np.sqrt(n)),
        }

    def summary_dict(self) -> dict:
        return {
            "units": "meters",
            "convention": "camera_from_base maps base-frame points to OpenCV camera axes (x right, y down, z forward)",
            "camera_from_base": self.camera_from_base.tolist(),
            "base_from_camera": self.base_from_camera.tolist(),
            "camera_from_base_xyz_quat_xyzw": _xyz_quat(self.camera_from_base),
            "base_from_camera_xyz_quat_xyzw": _xyz_quat(self.base_from_camera),
            "frames_total": len(self.frames),
            "frames_used": len(self.used),
            "frames_skipped": len(self.skipped),
            "rejected": self.rejected,
            "chains": self.chains,
            "consensus_threshold_mm": json_number(self.threshold_mm),
            "consensus_threshold_deg": json_number(self.threshold_deg),
            "spread": self.spread,
            "ground_truth": self.ground_truth,
            "seconds": self.seconds,
            **self.meta,
        }

    def to_dict(self) -> dict:
        return {**self.summary_dict(), "frames": [f.to_dict() for f in self.frames], "skipped": self.skipped}


def _xyz_quat(pose: np.ndarray) -> list[float]:
    return [*map(float, pose[:3, 3]), *map(float, matrix_to_quat_xyzw(pose[:3, :3]))]


def _add_mm(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, gt_keypoints: np.ndarray) -> float:
    kp = robot.keypoints(np.asarray(joints, np.float64)[None], pose[None])
    return float(1000.0 * add_per_frame(kp, np.asarray(gt_keypoints, np.float64)[None])[0])


def calibrate(
    estimator,
    frames: Sequence,
    chains: int = 1,
    batch_size: int = 4,
    seed: int = 0,
    consensus_k: float = CONSENSUS_K,
    min_threshold_mm: float = CONSENSUS_MIN_MM,
    min_threshold_deg: float = CONSENSUS_MIN_DEG,
    unreliable_mm: float = UNRELIABLE_MM,
    progress: bool = False,
    sampler: str | None = None,
) -> CalibrationResult:
    """Fuse the estimates of ``frames`` (all seen by one static camera) into one extrinsic.

    ``frames``: objects with ``name``, ``K``, ``joints`` and ``load_image()`` (DREAM frames or
    :class:`monose3.data.frame.Frame`); with ``pose`` and ``keypoints_3d`` on every frame the error of the
    fused pose against ground truth is filled in. Frames whose image cannot be read are
    skipped and listed in ``result.skipped``. Raises Monose3Error if no frame survives.
    """
    if len(frames) == 0:
        raise Monose3Error("no frames to calibrate from; give a folder with at least one frame")
    if chains < 1 or batch_size < 1:
        raise Monose3Error(f"chains and batch size must be at least 1, got {chains} and {batch_size}")
    start = time.perf_counter()
    skipped = skipped_annotations(frames)
    usable, results = estimate_frames(estimator, frames, chains, batch_size, seed, skipped, progress, sampler)
    if not results:
        first = skipped[0] if skipped else {"frame": "-", "reason": "-"}
        raise Monose3Error(
            f"no usable frame: all {len(skipped)} were skipped (first: {first['frame']}: {first['reason']})"
        )
    candidates = reject_unusable(results, chains, unreliable_mm)
    consensus = robust_consensus(
        np.stack([results[i].camera_from_base for i in candidates]), consensus_k, min_threshold_mm, min_threshold_deg
    )
    fused = consensus.pose
    for i, inlier in zip(candidates, consensus.inliers, strict=True):
        results[i].used = bool(inlier)
        if not inlier:
            results[i].reason = REASON_CONSENSUS
    set_residuals(results, fused)
    gt = ground_truth_report(estimator.robot, usable, results, fused) if _has_ground_truth(usable) else None
    return CalibrationResult(
        camera_from_base=fused,
        frames=results,
        chains=chains,
        threshold_mm=consensus.threshold_mm,
        threshold_deg=consensus.threshold_deg,
        ground_truth=gt,
        seconds=time.perf_counter() - start,
        skipped=skipped,
    )


def estimate_frames(
    estimator,
    frames: Sequence,
    chains: int,
    batch_size: int,
    seed: int,
    skipped: list[dict],
    progress: bool,
    sampler: str | None = None,
    desc: str = "calibrate",
) -> tuple[list, list[FrameResult]]:
    """Single-frame estimates of every readable frame, ``batch_size`` at a time; unreadable
    frames are appended to ``skipped``. Returns the frames used and their results."""
    results: list[FrameResult] = []
    usable: list = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(frames), desc=desc, unit="frame")
    for b, first in enumerate(range(0, len(frames), batch_size)):
        chunk = [frames[i] for i in range(first, min(first + batch_size, len(frames)))]
        batch, images = load_images(chunk, skipped)
        usable.extend(batch)
        if batch:
            est = estimator.estimate(
                images,
                np.stack([np.asarray(f.K, np.float64) for f in batch]),
                np.stack([np.asarray(f.joints, np.float64) for f in batch]),
                sampler=sampler,
                hypotheses=chains,
                stochastic=chains > 1,
                seed=seed + b,
            )
            results.extend(_frame_result(f, est, j, chains) for j, f in enumerate(batch))
        if bar is not None:
            bar.update(len(chunk))
    if bar is not None:
        bar.close()
    return usable, results


def _frame_result(frame, est, j: int, chains: int) -> FrameResult:
    return FrameResult(
        name=str(frame.name),
        camera_from_base=np.asarray(est.poses[j], np.float64),
        in_view=bool(est.in_view[j]),
        chain_spread_mm=float(est.spread_mm[j]) if chains > 1 and est.fit_iou is None else float("nan"),
        chain_spread_deg=float(est.spread_deg[j]) if chains > 1 and est.fit_iou is None else float("nan"),
        fit_reliable=None if est.reliable is None else bool(est.reliable[j]),
    )


def reject_unusable(results: list[FrameResult], chains: int, unreliable_mm: float) -> list[int]:
    """Mark estimates out of view, or (with several chains) whose chains disagree; the indices
    of the rest. Raises Monose3Error when none is left."""
    for r in results:
        if not r.in_view or not np.all(np.isfinite(r.camera_from_base)):
            r.reason = REASON_OUT_OF_VIEW
        elif r.fit_reliable is False:
            r.reason = REASON_POOR_FIT
        elif chains > 1 and r.chain_spread_mm > unreliable_mm:
            r.reason = REASON_UNRELIABLE
    candidates = [i for i, r in enumerate(results) if r.reason is None]
    if not candidates:
        counts = ", ".join(f"{n} {why}" for why, n in Counter(r.reason for r in results).items())
        raise Monose3Error(
            f"all {len(results)} frames were rejected ({counts}); check that the robot is visible, that the joints "
            "and intrinsics belong to these images and that the checkpoint is for this robot"
        )
    return candidates


def set_residuals(results: list[FrameResult], fused: np.ndarray) -> None:
    """Each frame's translation (mm) and rotation (deg) residual to the fused pose (NaN if it has none)."""
    poses = np.stack([r.camera_from_base for r in results])
    finite = np.all(np.isfinite(poses), axis=(1, 2))
    res_mm, res_deg = np.full(len(results), np.nan), np.full(len(results), np.nan)
    if finite.any():
        res_mm[finite], res_deg[finite] = pose_residuals(poses[finite], fused)
    for r, mm, deg in zip(results, res_mm, res_deg, strict=True):
        r.residual_mm, r.residual_deg = float(mm), float(deg)


def ground_truth_report(robot: RobotModel, frames: Sequence, results: list[FrameResult], fused: np.ndarray) -> dict:
    """Error of the fused pose against ground truth, next to the single-frame errors it replaces."""
    gt_poses = np.stack([np.asarray(f.pose, np.float64) for f in frames])
    gt_ref = robust_pose_average(gt_poses)
    gt_spread_mm, gt_spread_deg = pose_residuals(gt_poses, gt_ref)
    fused_mm, fused_deg = pose_residuals(fused[None], gt_ref)
    single_mm, single_deg = pose_residuals(np.stack([r.camera_from_base for r in results]), gt_ref)
    for f, r in zip(frames, results, strict=True):
        r.add_fused_mm = _add_mm(robot, fused, f.joints, f.keypoints_3d)
        ok = r.in_view and np.all(np.isfinite(r.camera_from_base))
        r.add_single_mm = _add_mm(robot, r.camera_from_base, f.joints, f.keypoints_3d) if ok else float("inf")
    single_add = np.array([r.add_single_mm for r in results])
    return {
        "fused_error_mm": float(fused_mm[0]),
        "fused_error_deg": float(fused_deg[0]),
        "fused_add_mean_mm": float(np.mean([r.add_fused_mm for r in results])),
        "single_frame_error_median_mm": float(np.median(single_mm)),
        "single_frame_error_median_deg": float(np.median(single_deg)),
        "single_frame_add_median_mm": json_number(float(np.median(single_add))),
        "ground_truth_spread_max_mm": float(gt_spread_mm.max()),
        "ground_truth_spread_max_deg": float(gt_spread_deg.max()),
        "static_camera": bool(gt_spread_mm.max() <= STATIC_GT_MM),
    }


def overlay_grid(estimator, frames: Sequence, result: CalibrationResult, count: int = 6, cols: int = 3) -> np.ndarray:
    """The robot at the fused pose on ``count`` frames spread over the set, with each frame's
    residual (skipped frames left out)."""
    by_name = {r.name: r for r in result.frames}
    frames = [f for f in frames if str(f.name) in by_name]
    n = len(frames)
    picks = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(count, n))})
    images, Ks, joints, texts, gts = [], [], [], [], []
    for i in picks:
        f, r = frames[i], by_name[str(frames[i].name)]
        images.append(f.load_image())
        Ks.append(f.K)
        joints.append(f.joints)
        status = f"{r.residual_mm:.0f} mm / {r.residual_deg:.1f} deg" if r.used else f"rejected ({r.reason})"
        texts.append(f"{f.name}: {status}")
        gts.append(getattr(f, "keypoints_3d", None))
    poses = [result.camera_from_base] * len(picks)
    tiles = pose_overlays(estimator.renderer, images, Ks, joints, poses, texts, gts, OVERLAY_TILE_WIDTH)
    return image_grid(tiles, cols=min(cols, len(tiles)), pad=4, background=255)
