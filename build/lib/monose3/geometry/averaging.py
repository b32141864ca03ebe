"""Robust averaging of rigid poses: one extrinsic from many noisy single-frame estimates.

A static camera seeing the robot in many configurations gives one camera-from-base estimate
per frame. Most are a few millimetres off; a few are badly wrong (a symmetric pose, a
confused arm). The arithmetic mean lets each of those drag the result by ``error / N``,
so the fusion here uses medians instead, which ignore a minority of gross errors entirely:

* rotation: the geodesic L1 median on SO(3) (Weiszfeld iterations in the tangent space,
  Hartley et al., "L1 rotation averaging using the Weiszfeld algorithm", CVPR 2011), started
  from the sample with the smallest summed angle to the others;
* translation: the geometric median (Weiszfeld in R^3), started from the coordinate-wise median.

The plain mean (:func:`mean_pose`: quaternion mean with sign alignment, arithmetic mean of
translations) is kept as the baseline the robust one is measured against.
All functions are numpy, batched over ``[N, 4, 4]`` poses, angles in radians unless named ``_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monose3.errors import Monose3Error
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import (
    matrix_to_quat_xyzw,
    matrix_to_rotvec,
    procrustes,
    quat_xyzw_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
)

# Weiszfeld stops when the update is below these (radians / meters) or after MAX_ITERS.
ROT_TOL = 1e-10
TRANS_TOL = 1e-9
MAX_ITERS = 200
# MAD -> standard deviation for Gaussian data.
MAD_TO_STD = 1.4826
# Consensus rejection: median + CONSENSUS_K * sigma_MAD of the residuals, never tighter than the floors.
CONSENSUS_K = 3.0
CONSENSUS_MIN_MM = 10.0
CONSENSUS_MIN_DEG = 2.0


# ---- averages --------------------------------------------------------------------------------


def _weights(n: int, weights: np.ndarray | None) -> np.ndarray:
    if weights is None:
        return np.ones(n)
    w = np.asarray(weights, np.float64).reshape(-1)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise Monose3Error(f"weights must be {n} finite non-negative numbers with a positive sum")
    return w


def _check_rotations(rots: np.ndarray) -> np.ndarray:
    r = np.asarray(rots, np.float64)
    if r.ndim != 3 or r.shape[1:] != (3, 3) or len(r) == 0:
        raise Monose3Error(f"need a non-empty [N, 3, 3] array of rotations, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise Monose3Error("rotations contain NaN or infinite values; drop the failed estimates first")
    return r


def rotation_medoid(rots: np.ndarray, weights: np.ndarray | None = None) -> int:
    """Index of the rotation with the smallest weighted sum of geodesic angles to all others."""
    r = _check_rotations(rots)
    w = _weights(len(r), weights)
    ang = rotation_angle(r[:, None], r[None])  # [N, N]
    return int(np.argmin(ang @ w))


def quaternion_mean(rots: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The plain (L2, chordal) average rotation: quaternions sign-aligned to the first one,
    averaged and normalised. Accurate for clustered rotations; one gross outlier pulls it by
    its angle / N."""
    r = _check_rotations(rots)
    w = _weights(len(r), weights)
    q = matrix_to_quat_xyzw(r)
    # q and -q are the same rotation: flip each to the hemisphere of the first before averaging.
    q = q * np.where(q @ q[0] < 0, -1.0, 1.0)[:, None]
    mean = (w[:, None] * q).sum(0)
    if np.linalg.norm(mean) < 1e-12:  # antipodal cancellation: fall back to the eigenvector method
        mean = np.linalg.eigh((w[:, None, None] * q[:, :, None] * q[:, None, :]).sum(0))[1][:, -1]
    return quat_xyzw_to_matrix(mean)


def rotation_l1_median(
    rots: np.ndarray, weights: np.ndarray | None = None, iters: int = MAX_ITERS, tol: float = ROT_TOL
) -> np.ndarray:
    """Geodesic L1 median on SO(3) by Weiszfeld iterations in the tangent space.

    Minimises sum_i w_i * angle(R, R_i). Each step averages the unit tangent directions
    towards the samples, weighted by 1/angle, so a far outlier pulls with the same force as
    a near inlier instead of a force proportional to its distance. Started from the medoid
    (already robust), so it only refines inside the inlier cluster.
    """
    r = _check_rotations(rots)
    w = _weights(len(r), weights)
    est = r[rotation_medoid(r, w)]
    for _ in range(iters):
        v = matrix_to_rotvec(est.T @ r)  # [N, 3] tangent vectors at est
        d = np.linalg.norm(v, axis=1)
        near = d < 1e-12
        if np.all(near | (w == 0)):
            break
        inv = np.where(near, 0.0, w / np.where(near, 1.0, d))
        step = (inv[:, None] * v).sum(0) / inv.sum()
        # A sample sitting exactly on the estimate: Weiszfeld's modified step (Vardi-Zhang) keeps
        # the estimate there unless the pull of the others exceeds its weight.
        if np.any(near):
            pull = np.linalg.norm((inv[:, None] * v).sum(0))
            held = w[near].sum()
            if pull <= held:
                break
            step *= 1.0 - held / pull
        est = est @ rotvec_to_matrix(step)
        if np.linalg.norm(step) < tol:
            break
    return procrustes(est)


def geometric_median(
    points: np.ndarray, weights: np.ndarray | None = None, iters: int = MAX_ITERS, tol: float = TRANS_TOL
) -> np.ndarray:
    """The point minimising the weighted sum of Euclidean distances to ``points`` ``[N, D]``
    (Weiszfeld, with the Vardi-Zhang fix when the iterate lands on a sample)."""
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or len(p) == 0:
        raise Monose3Error(f"need a non-empty [N, D] array of points, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise Monose3Error("points contain NaN or infinite values; drop the failed estimates first")
    w = _weights(len(p), weights)
    est = np.median(p, axis=0)
    for _ in range(iters):
        diff = p - est
        d = np.linalg.norm(diff, axis=1)
        near = d < 1e-12
        inv = np.where(near, 0.0, w / np.where(near, 1.0, d))
        if inv.sum() == 0:
            break
        target = (inv[:, None] * p).sum(0) / inv.sum()
        if np.any(near):
            pull = np.linalg.norm((inv[:, None] * diff).sum(0))
            held = w[near].sum()
            if pull <= held:
                break
            target = est + (target - est) * (1.0 - held / pull)
        moved = np.linalg.norm(target - est)
        est = target
        if moved < tol:
            break
    return est


def _check_poses(poses: np.ndarray) -> np.ndarray:
    p = np.asarray(poses, np.float64)
    if p.ndim != 3 or p.shape[1:] != (4, 4) or len(p) == 0:
        raise Monose3Error(f"need a non-empty [N, 4, 4] array of poses, got shape {p.shape}")
    return p


def mean_pose(poses: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The non-robust baseline: quaternion mean of the rotations, arithmetic mean of the translations."""
    p = _check_poses(poses)
    w = _weights(len(p), weights)
    return make_pose(quaternion_mean(p[:, :3, :3], w), (w[:, None] * p[:, :3, 3]).sum(0) / w.sum())


def robust_pose_average(poses: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The robust fusion of ``[N, 4, 4]`` poses: L1 rotation median and geometric median of
    translations. Rotation and translation are fused separately; for camera-from-base
    poses the translation is the base origin in the camera frame."""
    p = _check_poses(poses)
    w = _weights(len(p), weights)
    return make_pose(rotation_l1_median(p[:, :3, :3], w), geometric_median(p[:, :3, 3], w))


def pose_residuals(poses: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation distance (mm) and rotation angle (deg) of each pose ``[N, 4, 4]`` to ``reference``."""
    p = _check_poses(poses)
    ref = np.asarray(reference, np.float64)
    trans_mm = 1000.0 * np.linalg.norm(p[:, :3, 3] - ref[:3, 3], axis=1)
    rot_deg = np.degrees(rotation_angle(ref[:3, :3], p[:, :3, :3]))
    return trans_mm, rot_deg


def mad_threshold(values: np.ndarray, k: float, floor: float) -> float:
    """``median + k * sigma`` with sigma from the median absolute deviation, never below ``floor``.

    The floor keeps a tight cluster (MAD near 0) from rejecting inliers for differences far
    below what the estimator can resolve."""
    v = np.asarray(values, np.float64)
    med = float(np.median(v))
    sigma = MAD_TO_STD * float(np.median(np.abs(v - med)))
    return max(floor, med + k * sigma)


@dataclass
class ConsensusResult:
    """The robust average of a set of poses after rejecting those far from a first robust estimate."""

    pose: np.ndarray  # [4, 4] fused over the inliers
    inliers: np.ndarray  # [N] bool
    residual_mm: np.ndarray  # [N] translation distance of each pose to ``pose``
    residual_deg: np.ndarray  # [N] rotation angle of each pose to ``pose``
    threshold_mm: float
    threshold_deg: float


def robust_consensus(
    poses: np.ndarray,
    k: float = CONSENSUS_K,
    min_threshold_mm: float = CONSENSUS_MIN_MM,
    min_threshold_deg: float = CONSENSUS_MIN_DEG,
    weights: np.ndarray | None = None,
) -> ConsensusResult:
    """Fuse, reject poses beyond MAD thresholds of the first robust estimate, fuse the rest.

    Thresholds: ``median + k * 1.4826 * MAD`` of the residuals (translation and rotation
    separately), at least ``min_threshold_mm`` / ``min_threshold_deg``. With fewer than three
    poses nothing is rejected (a MAD of two values says nothing).
    """
    p = _check_poses(poses)
    w = _weights(len(p), weights)
    first = robust_pose_average(p, w)
    trans_mm, rot_deg = pose_residuals(p, first)
    if len(p) < 3:
        thr_mm, thr_deg = float("inf"), float("inf")
    else:
        thr_mm = mad_threshold(trans_mm, k, min_threshold_mm)
        thr_deg = mad_threshold(rot_deg, k, min_threshold_deg)
    inliers = (trans_mm <= thr_mm) & (rot_deg <= thr_deg)
    fused = robust_pose_average(p[inliers], w[inliers]) if inliers.any() else first
    res_mm, res_deg = pose_residuals(p, fused)
    return ConsensusResult(fused, inliers, res_mm, res_deg, thr_mm, thr_deg)
