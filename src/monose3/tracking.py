"""The tracking policy, one for every command that tracks a sequence (``monose3 track`` and
``monose3 evaluate --sampler tracking``).

The first frame gets the full estimate; every next frame starts from the previous estimate and
is refined there (:meth:`PoseEstimator.track`: the paper's one step at a small t, or the fit's
short refinement). A full estimate runs again when

* the previous estimate was out of view ("lost": there is no track to keep),
* the tracked pose puts the robot's centre outside the image ("out of view"; where it stays
  out, at most once every ``recheck_every`` frames, the track going on meanwhile),
* the tracked pose moved the robot's keypoints by more than ``max_step_mm`` on average or
  rotated it by more than ``max_step_deg`` and its fit gives reason to doubt it ("jump": a big
  step that the image confirms is the robot moving, not the track slipping; where the
  estimator has no flag, the step size alone decides); within ``recheck_every`` frames of the
  last full estimate the doubted step is judged against the previous pose instead, which is kept
  where it fits the image better,
* its fit is doubted, at most once every ``recheck_every`` frames ("doubted"), or
* ``reinit_every`` frames passed since the last full estimate ("periodic", off by default).

**A re-estimate never makes a frame worse**: where there was a track, the estimator judges the
tracked pose and the full estimate on the same view of the image (:meth:`PoseEstimator.judge`),
and the full estimate replaces the track only when it is reliable (by its own fit and by that
judgement) and fits that view better than the track; an unreliable one never replaces it.
Every frame carries a confidence, a ``reliable`` flag and the doubts behind it.

With ``static_camera`` the camera does not move, the robot does: every reliable frame adds its
pose to one fused camera pose (:class:`StaticFusion`, a robust average as ``calibrate`` fuses),
which each frame starts from; once it has converged it is every frame's answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.averaging import robust_pose_average
from monose3.geometry.rotations import rotation_angle
from monose3.robot import RobotModel

if TYPE_CHECKING:  # the estimator imports torch; the policy's constants are read by the torch-free options
    from monose3.estimator import Estimate

# A tracked pose that moves the robot more than this between two frames is checked against a full estimate.
MAX_STEP_MM = 50.0
MAX_STEP_DEG = 10.0
# A doubted track is checked against a full estimate at most once in this many frames: a full
# estimate costs 10-20 tracked frames, and where the image is poor (low contrast) it rarely wins.
RECHECK_EVERY = 10

MODE_FULL, MODE_TRACK, MODE_FUSED = "full", "track", "fused"
REASON_FIRST, REASON_LOST, REASON_PERIODIC = "first", "lost", "periodic"
REASON_OUT_OF_VIEW, REASON_JUMP, REASON_DOUBTED = "out of view", "jump", "doubted"
KEPT_TRACK = "the track fits better than the full estimate"
HOLD = "hold"  # a doubted big step too soon after the last full estimate: checked against the previous pose
HELD = "a doubted big step: the previous pose fits better and was kept"
UNRELIABLE_FULL = "the full estimate is unreliable"

# Static camera: the fused pose needs this many reliable frames, and its standard error (from the
# frames' spread about it) below this, to be called converged; a reliable frame further than
# AGREE_MM from a converged fused pose does not join it, and RESET_AFTER such frames in a row
# mean the camera moved (the fusion starts again).
FUSE_MIN_FRAMES = 5
FUSE_CONVERGED_MM = 2.0
AGREE_MM = 30.0
RESET_AFTER = 5


@dataclass(frozen=True)
class TrackingPolicy:
    """When tracking re-estimates (see the module docstring)."""

    max_step_mm: float = MAX_STEP_MM
    max_step_deg: float = MAX_STEP_DEG
    reinit_every: int | None = None  # also run the full estimate every N frames
    recheck_every: int = RECHECK_EVERY
    static_camera: bool = False

    def __post_init__(self) -> None:
        if self.reinit_every is not None and self.reinit_every < 1:
            raise Monose3Error(f"reinit_every must be at least 1 (or None), got {self.reinit_every}")
        if self.recheck_every < 1:
            raise Monose3Error(f"recheck_every must be at least 1, got {self.recheck_every}")


@dataclass
class Quality:
    """How far one estimate can be trusted: ``confidence`` (the fit's silhouette IoU; the paper's
    chains: exp(-spread / 30 mm)), ``reliable`` and the ``doubts`` behind it; None where nothing
    can be judged (one chain of the paper's sampler)."""

    confidence: float | None
    reliable: bool | None
    doubts: list[str] = field(default_factory=list)


def estimate_quality(est: Estimate, j: int = 0) -> Quality:
    """The :class:`Quality` of estimate ``j`` of ``est``."""
    if est.fit_iou is not None and est.reliable is not None:
        return Quality(float(est.fit_iou[j]), bool(est.reliable[j]), list(est.doubts[j]) if est.doubts else [])
    if est.hypotheses.shape[1] > 1 and np.isfinite(est.spread_mm[j]):
        from monose3.method.reverse import UNRELIABLE_MM

        spread = float(est.spread_mm[j])
        ok = spread <= UNRELIABLE_MM
        return Quality(math.exp(-spread / UNRELIABLE_MM), ok, [] if ok else ["chains disagree"])
    return Quality(None, None)


@dataclass
class TrackStep:
    """What the policy did with one frame."""

    camera_from_base: np.ndarray  # [4, 4] the frame's answer
    mode: str  # where it comes from: MODE_FULL (a full estimate), MODE_TRACK (the track), MODE_FUSED (static camera)
    reason: str | None  # why a full estimate ran: first, lost, out of view, jump, doubted, periodic
    in_view: bool
    step_mm: float | None  # mean keypoint motion of the tracked pose from the previous one (also when not kept)
    step_deg: float | None  # its rotation
    estimate: Estimate  # the estimator's result of the frame's own pose (its history, spread, fit)
    quality: Quality = field(default_factory=lambda: Quality(None, None))
    decision: str | None = None  # a full estimate ran but the track was kept: why
    alternative: np.ndarray | None = None  # the candidate not chosen (the full estimate or the track)
    fused: np.ndarray | None = None  # static camera: the fused pose after this frame
    fused_frames: int = 0  # static camera: the frames in it
    converged: bool = False  # static camera: the fused pose has converged

    @property
    def confidence(self) -> float | None:
        return self.quality.confidence

    @property
    def reliable(self) -> bool | None:
        return self.quality.reliable

    @property
    def doubts(self) -> list[str]:
        return self.quality.doubts


def keypoint_motion_mm(robot: RobotModel, joints: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance (mm) the robot's keypoints at ``joints`` ``[n]`` move between camera-from-base
    poses ``a`` and ``b`` ``[4, 4]``."""
    kp = robot.keypoints(np.asarray(joints, np.float64)[None])[0]
    pa = kp @ a[:3, :3].T + a[:3, 3]
    pb = kp @ b[:3, :3].T + b[:3, 3]
    return float(1000.0 * np.linalg.norm(pa - pb, axis=1).mean())


class StaticFusion:
    """One camera pose from many frames of a static camera: the robust average (geodesic L1
    median of the rotations, geometric median of the translations) of the reliable frames' poses,
    with how well it has converged (the standard error of a median from the frames' spread about it)."""

    def __init__(self, robot: RobotModel):
        self.robot = robot
        self.poses: list[np.ndarray] = []
        self.joints: list[np.ndarray] = []
        self.pose: np.ndarray | None = None
        self.spread_mm = math.inf  # median keypoint distance of the frames' poses to the fused one
        self.disagreeing = 0  # reliable frames in a row that disagree with a converged fused pose
        self.resets = 0

    @property
    def standard_error_mm(self) -> float:
        """About how far the fused pose is from the truth, if the frames' errors are independent:
        1.25 x the spread / sqrt(n), the standard error of a median."""
        return 1.2533 * self.spread_mm / math.sqrt(len(self.poses)) if self.poses else math.inf

    @property
    def converged(self) -> bool:
        return len(self.poses) >= FUSE_MIN_FRAMES and self.standard_error_mm <= FUSE_CONVERGED_MM

    def offer(self, pose: np.ndarray, joints: np.ndarray) -> bool:
        """Add a reliable frame's pose unless a converged fused pose disagrees with it (then,
        after :data:`RESET_AFTER` such frames in a row, the camera moved: start again)."""
        if self.converged and keypoint_motion_mm(self.robot, joints, self.pose, pose) > AGREE_MM:
            self.disagreeing += 1
            if self.disagreeing < RESET_AFTER:
                return False
            self.poses, self.joints, self.resets = [], [], self.resets + 1
        self.disagreeing = 0
        self.poses.append(np.asarray(pose, np.float64))
        self.joints.append(np.asarray(joints, np.float64))
        self.pose = robust_pose_average(np.stack(self.poses))
        distances = [
            keypoint_motion_mm(self.robot, q, self.pose, p) for p, q in zip(self.poses, self.joints, strict=True)
        ]
        self.spread_mm = float(np.median(distances))
        return True

    def summary(self) -> dict:
        return {"camera_from_base": None if self.pose is None else self.pose.tolist(), "frames": len(self.poses),
                "spread_mm": self.spread_mm, "standard_error_mm": self.standard_error_mm,
                "converged": self.converged, "resets": self.resets}  # fmt: skip


class Tracker:
    """Applies a :class:`TrackingPolicy` frame by frame with an estimator (anything with
    ``robot``, ``estimate(images, Ks, joints, **kw)`` and ``track(images, Ks, joints, previous)``;
    with ``judge(image, K, joints, poses)`` it compares a track with a re-estimate, else the
    re-estimate replaces the track).

    ``full_kwargs`` go to every full ``estimate`` call (``sampler``, ``ddim_steps``, ...).
    """

    def __init__(self, estimator, policy: TrackingPolicy | None = None, **full_kwargs):
        self.estimator = estimator
        self.policy = TrackingPolicy() if policy is None else policy
        self.full_kwargs = full_kwargs
        self.previous: np.ndarray | None = None  # the last estimate to go on from, None when lost
        self.previous_in_view = True
        self.previous_reliable: bool | None = None
        self.frames = 0  # frames seen
        self.since_full = 0  # frames since the last full estimate
        self.fusion = StaticFusion(estimator.robot) if self.policy.static_camera else None

    def update(self, image: np.ndarray, K: np.ndarray, joints: np.ndarray) -> TrackStep:
        """The estimate of the next frame of the sequence (``K`` ``[3, 3]``, ``joints`` ``[n]``)."""
        K = np.asarray(K, np.float64)[None]
        q = np.asarray(joints, np.float64)[None]
        start = self.previous
        if self.fusion is not None and self.fusion.pose is not None:
            start = self.fusion.pose  # the camera did not move: the best start is every frame's fused pose
        if start is None:
            result = self._full(image, K, q, REASON_FIRST if self.frames == 0 else REASON_LOST)
        else:
            result = self._track(image, K, q, start)
        self.since_full += 1
        self.frames += 1
        if self.fusion is not None:
            result = self._fuse(result, q[0])
        # A kept track goes on even where the robot's centre left the image (it is still the best pose there is).
        kept = result.mode == MODE_TRACK and np.isfinite(result.camera_from_base).all()
        self.previous = result.camera_from_base if result.in_view or kept else None
        self.previous_in_view, self.previous_reliable = result.in_view, result.reliable
        return result

    # ---- the steps ----------------------------------------------------------------------------

    def _full(self, image, K, q, reason: str) -> TrackStep:
        est = self.estimator.estimate([image], K, q, **self.full_kwargs)
        self.since_full = 0
        return TrackStep(est.poses[0], MODE_FULL, reason, bool(est.in_view[0]), None, None, est, estimate_quality(est))

    def _track(self, image, K, q, start: np.ndarray) -> TrackStep:
        sampler = self.full_kwargs.get("sampler")
        est = self.estimator.track([image], K, q, start[None], **({"sampler": sampler} if sampler else {}))
        pose, quality = est.poses[0], estimate_quality(est)
        step_mm = keypoint_motion_mm(self.estimator.robot, q[0], start, pose)
        step_deg = float(np.degrees(rotation_angle(start[:3, :3], pose[:3, :3])))
        tracked = TrackStep(pose, MODE_TRACK, None, bool(est.in_view[0]), step_mm, step_deg, est, quality)
        reason = self._reason(tracked)
        if reason is None or not hasattr(self.estimator, "judge") and reason == HOLD:
            return tracked
        if reason == HOLD:  # a doubted big step, and a full estimate ran lately: the previous pose, if it fits better
            held = TrackStep(start.copy(), MODE_TRACK, None, True, step_mm, step_deg, est,
                             Quality(None, self.previous_reliable))  # fmt: skip
            if not self._better(image, K[0], q[0], tracked, held)[0]:
                return tracked
            held.quality = Quality(tracked.confidence, False, [HELD, *tracked.doubts])
            held.decision, held.alternative = HELD, tracked.camera_from_base
            return held
        full = self._full(image, K, q, reason)
        full.step_mm, full.step_deg = step_mm, step_deg
        if not hasattr(self.estimator, "judge") or not np.isfinite(pose).all():
            return full  # (no pose tracked: the parser found no robot around the previous one)
        replace, full_ok = self._better(image, K[0], q[0], tracked, full) if full.in_view else (False, False)
        if replace:
            full.alternative = tracked.camera_from_base
            return full
        tracked.reason, tracked.alternative = reason, full.camera_from_base
        lost = not full.in_view
        tracked.decision = "the full estimate lost the robot" if lost else KEPT_TRACK if full_ok else UNRELIABLE_FULL
        return tracked

    def _reason(self, tracked: TrackStep) -> str | None:
        """Why the tracked pose is checked against a full estimate (None: it is kept; HOLD: a
        doubted big step too soon after the last full estimate: checked against the previous pose)."""
        policy, doubted = self.policy, tracked.reliable is False
        due = self.since_full >= policy.recheck_every
        if not tracked.in_view:  # a track that just left the view is checked; one that stays out, at the recheck rate
            return REASON_OUT_OF_VIEW if due or self.previous_in_view else None
        if policy.reinit_every is not None and self.since_full >= policy.reinit_every:
            return REASON_PERIODIC
        big = tracked.step_mm > policy.max_step_mm or tracked.step_deg > policy.max_step_deg
        if big and tracked.reliable is not True:  # a big step the image confirms is the robot moving
            return REASON_JUMP if due or tracked.reliable is None else HOLD
        if doubted and due:
            return REASON_DOUBTED
        return None

    def _better(self, image, K, q, tracked: TrackStep, other: TrackStep) -> tuple[bool, bool]:
        """Whether ``other`` (a full estimate, or the previous pose) should replace the tracked
        pose, and whether it is reliable: it replaces the track only when it is reliable (by its
        own flag and judged beside the track on one view, :meth:`PoseEstimator.judge`) and fits
        that view better, whether the track is reliable or not (on the tuning sequences, seeds
        41000-41007, replacing a doubted track by any reliable re-estimate had made 1 of 8
        replaced frames worse)."""
        judged = self.estimator.judge(image, K, q, np.stack([tracked.camera_from_base, other.camera_from_base]))
        o_ok = bool(other.reliable) and bool(judged.reliable[1])
        t_score, o_score = (float(s) for s in judged.fit_score)
        return bool(o_ok and o_score > t_score), o_ok

    def _fuse(self, result: TrackStep, joints: np.ndarray) -> TrackStep:
        """Static camera: a reliable frame joins the fused pose; a converged fused pose is the answer."""
        fusion = self.fusion
        if result.in_view and result.reliable:
            fusion.offer(result.camera_from_base, joints)
        result.fused, result.fused_frames, result.converged = fusion.pose, len(fusion.poses), fusion.converged
        if fusion.converged and fusion.disagreeing == 0:
            result.alternative, result.camera_from_base = result.camera_from_base, fusion.pose.copy()
            result.mode, result.in_view = MODE_FUSED, True
            # The fused pose stands on many frames: this frame's doubts are its own fit's, not the answer's.
            result.quality = Quality(result.quality.confidence, True, [])
        return result
