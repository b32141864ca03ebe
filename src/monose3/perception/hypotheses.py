"""Pose hypotheses from the parser's evidence: PnP from the keypoints, and orientations over
the sphere placed where the mask is and as large as it is (the fallback when PnP fails).
``perception/fitting.py`` scores and refines them."""

from __future__ import annotations

import math

import cv2
import numpy as np

from monose3.geometry.poses import make_pose
from monose3.perception.views import MASK_THRESHOLD, ViewEvidence

MIN_KEYPOINT_CONFIDENCE = 0.2
PNP_ERROR_FRACTION = 0.02  # RANSAC inlier threshold, as a fraction of the view's width
SPHERE_AZIMUTHS, SPHERE_ELEVATIONS = 8, (10.0, 45.0)  # a fallback: PnP from the keypoints wins when it works
# The second look's sphere (fitting.fit_pose, step 8): denser, over the elevations a camera sees a
# robot from (-10 to 60 degrees in the hard scenes), each pose facing the robot along its ray.
DENSE_AZIMUTHS, DENSE_ELEVATIONS = 16, (-5.0, 15.0, 35.0, 55.0)


def pnp_hypotheses(view: ViewEvidence, keypoints_base: np.ndarray) -> list[np.ndarray]:
    """Camera-from-base poses from the confident keypoints: RANSAC + SQPnP, refined by LM on
    its inliers, and SQPnP on all confident keypoints."""
    good = view.confidence >= MIN_KEYPOINT_CONFIDENCE
    if good.sum() < 4:
        return []
    obj, img = keypoints_base[good].astype(np.float64), view.keypoints[good].astype(np.float64)
    subsets = [np.ones(len(obj), bool)]
    if len(obj) > 4:  # each keypoint left out in turn: one wrong keypoint then spoils one subset only
        subsets += [np.arange(len(obj)) != i for i in range(len(obj))]
    poses = [_ransac(obj, img, view.K, PNP_ERROR_FRACTION * view.size[0])]
    poses += [_sqpnp(obj[keep], img[keep], view.K) for keep in subsets]
    return [p for p in poses if p is not None and np.isfinite(p).all() and p[2, 3] > 0.05]


# OpenCV's SQPnP asserts (raises) instead of failing when the image points all but coincide
# (keypoints the parser put within a few pixels of each other, as on a small false detection):
# such keypoints carry no pose, so both solvers below give None there.


def _ransac(obj: np.ndarray, img: np.ndarray, K: np.ndarray, error_px: float) -> np.ndarray | None:
    """SQPnP in RANSAC (inliers within ``error_px``), refined by LM on its inliers; None where it fails."""
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, K, None, reprojectionError=error_px, flags=cv2.SOLVEPNP_SQPNP
        )
        if not ok or inliers is None or len(inliers) < 4:
            return None
        idx = inliers[:, 0]
        return _pose(*cv2.solvePnPRefineLM(obj[idx], img[idx], K, None, rvec, tvec))
    except cv2.error:
        return None


def _sqpnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """SQPnP's pose on all of the points, or None where it has none."""
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    return _pose(rvec, tvec) if ok else None


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))


def sphere_hypotheses(view: ViewEvidence, surface_base: np.ndarray, azimuths: int = SPHERE_AZIMUTHS,
                      elevations: tuple[float, ...] = SPHERE_ELEVATIONS,
                      facing: bool = False) -> list[np.ndarray]:  # fmt: skip
    """Orientations over the sphere (the camera looking at the robot from ``azimuths`` x
    ``elevations``), each placed so the robot's centroid projects to the mask's centroid at the
    depth where its projected extent matches the mask's. With ``facing``, each is turned about
    the camera so that it sees the robot from that direction along the ray to it (without, it
    looks along the optical axis, which an off-centre robot is not seen along)."""
    ys, xs = np.nonzero((view.mask > MASK_THRESHOLD).numpy())
    if not len(xs):
        return []
    centre = np.array([xs.mean(), ys.mean()])
    extent = max(xs.max() - xs.min(), ys.max() - ys.min()) + 1
    centroid = surface_base.mean(0)
    f = (view.K[0, 0] + view.K[1, 1]) / 2
    ray = np.array([(centre[0] - view.K[0, 2]) / view.K[0, 0], (centre[1] - view.K[1, 2]) / view.K[1, 1], 1.0])
    turn = _turn_onto(ray) if facing else np.eye(3)
    poses = []
    for elevation in elevations:
        for i in range(azimuths):
            az, el = 2 * math.pi * i / azimuths, math.radians(elevation)
            eye = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            rot = _look_at(eye)
            pts = (surface_base - centroid) @ rot.T
            size = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]))
            depth = f * size / extent
            poses.append(make_pose(turn @ rot, ray * depth - turn @ rot @ centroid))
    return poses


def _turn_onto(ray: np.ndarray) -> np.ndarray:
    """The rotation that turns the optical axis (0, 0, 1) onto ``ray`` about their common normal."""
    direction = ray / np.linalg.norm(ray)
    axis = np.cross([0.0, 0.0, 1.0], direction)
    sin = np.linalg.norm(axis)
    if sin < 1e-9:
        return np.eye(3)
    return cv2.Rodrigues(axis / sin * math.atan2(sin, direction[2]))[0]


def _look_at(eye: np.ndarray) -> np.ndarray:
    """Camera-from-world rotation (OpenCV axes) of a camera at ``eye`` looking at the origin, z up."""
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    return np.stack([x, np.cross(z, x), z])
