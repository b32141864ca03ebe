"""The tracking policy (monose3.tracking): a re-estimate replaces the track only when it fits
better, jumps are judged on the image, a doubted track is re-checked at a bounded rate, and a
static camera's reliable frames fuse into one converging pose (scripted estimators)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import look_at

from monose3.errors import Monose3Error
from monose3.estimator import Estimate
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import euler_xyz_to_matrix
from monose3.tracking import (
    AGREE_MM,
    HELD,
    KEPT_TRACK,
    MODE_FULL,
    MODE_FUSED,
    MODE_TRACK,
    RESET_AFTER,
    StaticFusion,
    Tracker,
    TrackingPolicy,
    estimate_quality,
    keypoint_motion_mm,
)

K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
POSE = look_at(np.array([1.7, -0.5, 0.9]), np.array([0.0, 0.0, 0.45]))
IMAGE = np.zeros((120, 160, 3), np.uint8)
JOINTS = np.zeros(9)


def moved(pose: np.ndarray, mm: float) -> np.ndarray:
    out = pose.copy()
    out[0, 3] += mm / 1000
    return out


def fit_estimate(poses, reliable, scores=None, in_view=None) -> Estimate:
    """An Estimate as the fit sampler makes it (IoU, flag, doubts, score per pose)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    n = len(poses)
    reliable = np.broadcast_to(np.asarray(reliable, bool), (n,))
    in_view = np.ones(n, bool) if in_view is None else np.asarray(in_view, bool)
    scores = np.zeros(n) if scores is None else np.asarray(scores, float)
    return Estimate(poses, poses[:, None], in_view, np.zeros(n), np.zeros(n), fit_iou=np.full(n, 0.9),
                    reliable=reliable.copy(), doubts=[[] if r else ["doubted"] for r in reliable],
                    fit_score=scores)  # fmt: skip


class Scripted:
    """A fit-like estimator: ``track`` returns ``tracks[frame]`` (pose offset in mm or None:
    no robot found, reliable),
    ``estimate`` returns ``fulls[frame]`` (same, or None: at the truth, reliable), ``judge``
    returns the reliable flags and scores of ``judged[frame]``; every call is recorded."""

    def __init__(self, robot, tracks=None, fulls=None, judged=None):
        self.robot, self.frame, self.calls = robot, -1, []
        self.tracks, self.fulls, self.judged = tracks or {}, fulls or {}, judged or {}
        self.starts = []

    def estimate(self, images, Ks, joints, **kw):
        self.calls.append((self.frame, "full"))
        mm, ok, in_view = self.fulls.get(self.frame, (0.0, True, True))
        return fit_estimate([moved(POSE, mm)], ok, in_view=[in_view])

    def track(self, images, Ks, joints, previous, **kw):
        self.calls.append((self.frame, "track"))
        self.starts.append(previous[0])
        mm, ok = self.tracks.get(self.frame, (0.0, True))
        if mm is None:  # the parser found no robot around the previous pose
            return fit_estimate([np.full((4, 4), np.nan)], False, in_view=[False])
        return fit_estimate([moved(previous[0], mm)], ok)

    def judge(self, image, K, joints, poses):
        self.calls.append((self.frame, "judge"))
        (t_ok, t_score), (f_ok, f_score) = self.judged[self.frame]
        return fit_estimate(poses, [t_ok, f_ok], [t_score, f_score])


def run(estimator: Scripted, frames: int, policy: TrackingPolicy | None = None) -> list:
    tracker, steps = Tracker(estimator, policy), []
    for i in range(frames):
        estimator.frame = i
        steps.append(tracker.update(IMAGE, K, JOINTS))
    return steps


def test_a_big_step_the_image_confirms_is_kept_without_a_reestimate(panda):
    est = Scripted(panda, tracks={1: (200.0, True)})
    steps = run(est, 2)
    assert [(s.mode, s.reason) for s in steps] == [(MODE_FULL, "first"), (MODE_TRACK, None)]
    assert steps[1].step_mm == pytest.approx(200.0) and (1, "full") not in est.calls
    assert steps[1].reliable is True and steps[1].confidence == pytest.approx(0.9)


def test_an_unreliable_reestimate_never_replaces_a_reliable_track(panda):
    # Frame 1: a doubted 200 mm step; the full estimate runs, and judged on one view it is the unreliable one.
    est = Scripted(panda, tracks={1: (200.0, False)}, fulls={1: (900.0, False, True)},
                   judged={1: ((True, 0.5), (False, 0.9))})  # fmt: skip
    steps = run(est, 2, TrackingPolicy(recheck_every=1))
    assert est.calls == [(0, "full"), (1, "track"), (1, "full"), (1, "judge")]
    step = steps[1]
    assert (step.mode, step.reason) == (MODE_TRACK, "jump") and "unreliable" in step.decision
    assert np.allclose(step.camera_from_base, moved(POSE, 200.0)) and np.allclose(step.alternative, moved(POSE, 900.0))


def test_a_reestimate_replaces_the_track_only_when_it_fits_better(panda):
    better = Scripted(panda, tracks={1: (200.0, False)}, fulls={1: (5.0, True, True)},
                      judged={1: ((True, 0.5), (True, 0.7))})  # fmt: skip
    step = run(better, 2, TrackingPolicy(recheck_every=1))[1]
    assert (step.mode, step.reason, step.decision) == (MODE_FULL, "jump", None)
    assert np.allclose(step.camera_from_base, moved(POSE, 5.0)) and np.allclose(step.alternative, moved(POSE, 200.0))
    # A reliable track re-checked (periodically) stays where it fits better than the re-estimate.
    worse = Scripted(
        panda, tracks={1: (2.0, True)}, fulls={1: (5.0, True, True)}, judged={1: ((True, 0.8), (True, 0.7))}
    )
    step = run(worse, 2, TrackingPolicy(reinit_every=1))[1]
    assert (step.mode, step.reason, step.decision) == (MODE_TRACK, "periodic", KEPT_TRACK)
    # So does a doubted track: a reliable re-estimate that fits the view worse would make the frame worse.
    doubted = Scripted(
        panda, tracks={1: (200.0, False)}, fulls={1: (5.0, True, True)}, judged={1: ((False, 0.8), (True, 0.7))}
    )
    step = run(doubted, 2, TrackingPolicy(recheck_every=1))[1]
    assert (step.mode, step.reason, step.decision) == (MODE_TRACK, "jump", KEPT_TRACK)
    # A re-estimate that loses the robot keeps the track, without judging.
    lost = Scripted(panda, tracks={1: (200.0, False)}, fulls={1: (0.0, False, False)})
    step = run(lost, 2, TrackingPolicy(recheck_every=1))[1]
    assert step.mode == MODE_TRACK and step.in_view and (1, "judge") not in lost.calls


def test_a_track_that_found_no_robot_takes_the_reestimate_without_judging_a_missing_pose(panda):
    est = Scripted(panda, tracks={1: (None, False)}, fulls={1: (5.0, False, True)})
    step = run(est, 2)[1]
    assert (step.mode, step.reason) == (MODE_FULL, "out of view") and (1, "judge") not in est.calls
    assert np.allclose(step.camera_from_base, moved(POSE, 5.0)) and step.in_view


def test_a_doubted_big_step_soon_after_a_full_estimate_is_judged_against_the_previous_pose(panda):
    # recheck_every 10: the first frame's full estimate was one frame ago, so no full estimate runs.
    est = Scripted(panda, tracks={1: (200.0, False)}, judged={1: ((False, 0.2), (True, 0.8))})
    step = run(est, 2)[1]
    assert (1, "full") not in est.calls and (1, "judge") in est.calls
    assert step.mode == MODE_TRACK and np.allclose(step.camera_from_base, POSE) and step.decision == HELD
    assert step.reliable is False and step.doubts[0] == HELD and np.allclose(step.alternative, moved(POSE, 200.0))
    # Where the step fits better (a lost track found again), it is kept, doubted.
    found = Scripted(panda, tracks={1: (200.0, False)}, judged={1: ((True, 0.9), (False, 0.1))})
    step = run(found, 2)[1]
    assert np.allclose(step.camera_from_base, moved(POSE, 200.0)) and step.decision is None and step.reliable is False


def test_a_doubted_track_is_rechecked_at_most_every_n_frames(panda):
    doubted = {i: (1.0, False) for i in range(1, 8)}
    judged = {i: ((False, 0.9), (False, 0.1)) for i in range(8)}  # the track always fits better
    est = Scripted(panda, tracks=doubted, judged=judged)
    steps = run(est, 8, TrackingPolicy(recheck_every=3))
    assert [s.reason for s in steps] == ["first", None, None, "doubted", None, None, "doubted", None]
    assert all(s.mode == MODE_TRACK for s in steps[1:]) and steps[3].decision == "the full estimate is unreliable"
    assert all(s.reliable is False and s.doubts == ["doubted"] for s in steps[1:])
    with pytest.raises(Monose3Error, match="recheck_every must be at least 1"):
        TrackingPolicy(recheck_every=0)


def test_quality_of_the_papers_chains():
    one = Estimate(POSE[None], POSE[None, None], np.ones(1, bool), np.zeros(1), np.zeros(1))
    assert estimate_quality(one).reliable is None and estimate_quality(one).confidence is None
    chains = Estimate(POSE[None], np.stack([POSE, POSE])[None], np.ones(1, bool), np.array([60.0]), np.zeros(1))
    quality = estimate_quality(chains)
    assert quality.reliable is False and quality.confidence == pytest.approx(np.exp(-2)) and quality.doubts


def noisy(pose: np.ndarray, rng: np.random.Generator, mm: float) -> np.ndarray:
    rot = euler_xyz_to_matrix(rng.normal(0, mm / 1000 / 2, 3))
    return make_pose(rot @ pose[:3, :3], pose[:3, 3] + rng.normal(0, mm / 1000, 3))


def test_static_fusion_converges_rejects_outliers_and_restarts_when_the_camera_moves(panda):
    rng = np.random.default_rng(0)
    fusion = StaticFusion(panda)
    q = np.zeros(9)
    for _ in range(12):
        fusion.offer(noisy(POSE, rng, 2.0), q)
    assert fusion.converged and keypoint_motion_mm(panda, q, fusion.pose, POSE) < 2.0
    assert fusion.standard_error_mm < 2.0 and len(fusion.poses) == 12
    assert not fusion.offer(moved(POSE, 3 * AGREE_MM), q) and len(fusion.poses) == 12  # an outlier stays out
    assert fusion.offer(noisy(POSE, rng, 2.0), q) and fusion.disagreeing == 0  # ... and an agreeing frame ends its run
    elsewhere = moved(POSE, 300.0)
    joined = [fusion.offer(noisy(elsewhere, rng, 2.0), q) for _ in range(RESET_AFTER)]
    assert joined == [False] * (RESET_AFTER - 1) + [True] and fusion.resets == 1 and len(fusion.poses) == 1


def test_static_camera_starts_from_and_answers_with_the_fused_pose(panda):
    rng = np.random.default_rng(1)

    class Noisy(Scripted):
        def track(self, images, Ks, joints, previous, **kw):
            self.starts.append(previous[0])
            return fit_estimate([noisy(POSE, rng, 2.0)], True)

    est = Noisy(panda)
    steps = run(est, 12, TrackingPolicy(static_camera=True))
    first = next(i for i, s in enumerate(steps) if s.converged)
    assert 4 <= first <= 10 and all(s.mode == MODE_FUSED for s in steps[first:])
    assert all(s.mode != MODE_FUSED for s in steps[:first])
    assert np.allclose(steps[-1].camera_from_base, steps[-1].fused) and steps[-1].reliable
    assert keypoint_motion_mm(panda, JOINTS, steps[-1].camera_from_base, POSE) < 3.0
    assert np.allclose(est.starts[-1], steps[-2].fused)  # each frame starts from the fused pose
