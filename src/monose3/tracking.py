"""The tracking policy (the paper's 1-step tracking, Sec. IV-D), one for every command that
tracks a sequence (``monose3 track`` and ``monose3 evaluate --sampler tracking``).

The first frame gets the full reverse process (Alg. 2); every next frame starts from the
previous estimate and takes one step at a small timestep (:meth:`PoseEstimator.track`). A frame
is re-initialised with the full process when

* the previous estimate was out of view ("lost"),
* the 1-step update puts the robot outside the image ("out of view"),
* the 1-step update moved the robot's keypoints by more than ``max_step_mm`` on average or
  rotated the pose by more than ``max_step_deg`` ("jump": between consecutive frames the pose
  should barely change, so a big step means the update is not to be trusted), or
* ``reinit_every`` frames passed since the last full estimate ("periodic", off by default).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.rotations import rotation_angle
from monose3.robot import RobotModel

if TYPE_CHECKING:  # the estimator imports torch; the policy's constants are read by the torch-free options
    from monose3.estimator import Estimate

# A 1-step update that moves the robot more than this between two frames is not trusted.
MAX_STEP_MM = 50.0
MAX_STEP_DEG = 10.0

MODE_FULL, MODE_TRACK = "full", "track"
REASON_FIRST, REASON_LOST, REASON_PERIODIC = "first", "lost", "periodic"
REASON_OUT_OF_VIEW, REASON_JUMP = "out of view", "jump"


@dataclass(frozen=True)
class TrackingPolicy:
    """When tracking re-initialises (see the module docstring)."""

    max_step_mm: float = MAX_STEP_MM
    max_step_deg: float = MAX_STEP_DEG
    reinit_every: int | None = None  # also run the full process every N frames

    def __post_init__(self) -> None:
        if self.reinit_every is not None and self.reinit_every < 1:
            raise Monose3Error(f"reinit_every must be at least 1 (or None), got {self.reinit_every}")


@dataclass
class TrackStep:
    """What the policy did with one frame."""

    camera_from_base: np.ndarray  # [4, 4] the frame's estimate
    mode: str  # MODE_FULL (reverse process from the initialisation) or MODE_TRACK (1 step)
    reason: str | None  # why the full process ran: first, lost, out of view, jump, periodic
    in_view: bool
    step_mm: float | None  # mean keypoint motion of the 1-step update (also when it was rejected)
    step_deg: float | None  # rotation of the 1-step update
    estimate: Estimate  # the estimator's result the pose comes from (its history, spread)


def keypoint_motion_mm(robot: RobotModel, joints: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance (mm) the robot's keypoints at ``joints`` ``[n]`` move between camera-from-base
    poses ``a`` and ``b`` ``[4, 4]``."""
    kp = robot.keypoints(np.asarray(joints, np.float64)[None])[0]
    pa = kp @ a[:3, :3].T + a[:3, 3]
    pb = kp @ b[:3, :3].T + b[:3, 3]
    return float(1000.0 * np.linalg.norm(pa - pb, axis=1).mean())


class Tracker:
    """Applies a :class:`TrackingPolicy` frame by frame with an estimator (anything with
    ``robot``, ``estimate(images, Ks, joints, **kw)`` and ``track(images, Ks, joints, previous)``).

    ``full_kwargs`` go to every full ``estimate`` call (``sampler``, ``ddim_steps``, ...).
    """

    def __init__(self, estimator, policy: TrackingPolicy | None = None, **full_kwargs):
        self.estimator = estimator
        self.policy = TrackingPolicy() if policy is None else policy
        self.full_kwargs = full_kwargs
        self.previous: np.ndarray | None = None  # the last in-view estimate, None when lost
        self.frames = 0  # frames seen
        self.since_full = 0  # frames since the last full estimate

    def update(self, image: np.ndarray, K: np.ndarray, joints: np.ndarray) -> TrackStep:
        """The estimate of the next frame of the sequence (``K`` ``[3, 3]``, ``joints`` ``[n]``)."""
        K = np.asarray(K, np.float64)[None]
        q = np.asarray(joints, np.float64)[None]
        policy = self.policy
        step_mm = step_deg = None
        if self.previous is None:
            reason = REASON_FIRST if self.frames == 0 else REASON_LOST
        elif policy.reinit_every is not None and self.since_full >= policy.reinit_every:
            reason = REASON_PERIODIC
        else:
            sampler = self.full_kwargs.get("sampler")
            est = self.estimator.track([image], K, q, self.previous[None], **({"sampler": sampler} if sampler else {}))
            pose = est.poses[0]
            step_mm = keypoint_motion_mm(self.estimator.robot, q[0], self.previous, pose)
            step_deg = float(np.degrees(rotation_angle(self.previous[:3, :3], pose[:3, :3])))
            if not est.in_view[0]:
                reason = REASON_OUT_OF_VIEW
            elif step_mm > policy.max_step_mm or step_deg > policy.max_step_deg:
                reason = REASON_JUMP
            else:
                reason = None
                result = TrackStep(pose, MODE_TRACK, None, True, step_mm, step_deg, est)
        if reason is not None:
            est = self.estimator.estimate([image], K, q, **self.full_kwargs)
            result = TrackStep(est.poses[0], MODE_FULL, reason, bool(est.in_view[0]), step_mm, step_deg, est)
            self.since_full = 0
        self.since_full += 1
        self.frames += 1
        self.previous = result.camera_from_base if result.in_view else None
        return result
