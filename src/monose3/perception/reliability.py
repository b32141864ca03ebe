"""The ``reliable`` flag of the default pipeline: its thresholds, and what it reads besides the
fit's own numbers (:meth:`~monose3.perception.fitting.Fit.doubts`): how much of the robot lies in
the image, and how much depth a pixel of its size in the image stands for."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from monose3.geometry.camera import project
from monose3.geometry.poses import transform_points
from monose3.robot import RobotModel

if TYPE_CHECKING:
    from monose3.perception.fitting import Fit

# The fit flags an estimate unreliable when its silhouette fits the mask poorly, or its outline
# lies off the image's edges or too little of it on them (a fit to a wrong mask: the edges do
# not come from the parser), or its restarts in depth end far apart (the image does not fix
# its depth), or the robot is so small in the image for its distance that a pixel of its size
# is more depth than the error a good estimate may have (:func:`depth_per_pixel_mm`), or when
# less than MIN_INSIDE of the robot lies in the image (too little to fit to). Chosen on 820
# frames of their own (benchmarks/reliable_flag.py: generate --renderer tiny, seeds 3003-8008)
# for at least 91 % recall of estimates off by more than 30 mm (a margin over the goal's 90 %)
# at the fewest false alarms: 91.1 % and 5.3 % there (the IoU anywhere in 0.3-0.5 alike, the
# edge support at 0 or 0.2 nearly so, 5.2 %: the stricter kept). Chosen again with the zoomed
# view's context masks (views.CONTEXT_SCALES; before them: spread 40 mm, depth per pixel 38 mm,
# 91.3 % and 3.1 %). Kept when chosen again with the second look (fitting.fit_pose): 88.4 % and
# 7.1 % there, where the search's best rule at 91 % flags no more bad estimates on the check's
# frames, with more false alarms. Kept when the robot's inner edges came into the fit: the rules
# chosen again at 91 % and 94 % recall caught fewer bad estimates on new frames (reliable_flag.py's
# docstring). reliable_flag.py --check measures it on 2 x 400 frames generated after the choice,
# benchmarks/accuracy.py on the held-out sets.
RELIABLE_IOU = 0.5
RELIABLE_EDGE_DISTANCE_PX = 0.8
RELIABLE_EDGE_SUPPORT = 0.2
RELIABLE_SPREAD_MM = 20.0
RELIABLE_DEPTH_PER_PIXEL_MM = 32.0
MIN_INSIDE = 0.5


def inside_fraction(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray, image_shape) -> float:
    """The share of the robot's surface points that ``pose`` puts in front of the camera and inside the image."""
    if not np.isfinite(pose).all():
        return 0.0
    cam = transform_points(pose, robot.surface_points(joints[None])[0])
    u, v = project(cam, K).T
    h, w = image_shape[:2]
    return float(np.mean((cam[:, 2] > 0) & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)))


def depth_per_pixel_mm(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray) -> float:
    """How far (mm) the robot at ``pose`` moves in depth for its image to grow or shrink by one
    pixel: its centroid's depth ``z`` over its extent in the image (pixels, the larger of width
    and height), as the extent ``f L / z`` changes by ``-extent / z`` per meter. A fit fixes the
    robot's size in the image to a pixel or so, so this is the depth error to expect."""
    if not np.isfinite(pose).all():
        return math.inf
    surface = robot.surface_points(joints[None])[0]
    z = transform_points(pose, robot.centroid(surface)[None])[0, 2]
    extent = np.ptp(project(transform_points(pose, surface), K), axis=0).max()
    return float(1000 * z / extent) if z > 0 and extent > 0 else math.inf


def fit_doubts(fit: Fit, robot: RobotModel, joints: np.ndarray, K: np.ndarray, image_shape) -> list[str]:
    """:meth:`Fit.doubts`, and whether too little of the robot lies in the image to fit to or
    too little of the image to fix its depth (:func:`depth_per_pixel_mm`)."""
    reasons = fit.doubts()
    if not fit.found:
        return reasons
    share = inside_fraction(robot, fit.pose, joints, K, image_shape)
    if share < MIN_INSIDE:
        reasons.append(f"only {100 * share:.0f} % of the robot in the image")
    depth_mm = depth_per_pixel_mm(robot, fit.pose, joints, K)
    if depth_mm > RELIABLE_DEPTH_PER_PIXEL_MM:
        reasons.append(f"a pixel of the robot's size in the image is {depth_mm:.0f} mm of depth"
                       f" > {RELIABLE_DEPTH_PER_PIXEL_MM:g} mm: too small to fix its distance")  # fmt: skip
    return reasons


def pose_in_view(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray, image_shape) -> bool:
    """Whether ``pose`` puts the robot's centroid in front of the camera and inside the image."""
    if not np.isfinite(pose).all():
        return False
    cam = transform_points(pose, robot.centroid(robot.surface_points(joints[None])))[0]
    if cam[2] <= 0:
        return False
    u, v = project(cam[None], K)[0]
    h, w = image_shape[:2]
    return bool(-0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5)
