"""The ``reliable`` flag of the default pipeline: its thresholds (and the second look's), the
doubts they raise on the fit's own numbers (:func:`fit_reasons`), and what the flag reads besides
them (:func:`fit_doubts`): how much of the robot lies in the image, and how much depth a pixel of
its size in the image stands for."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from monose3.geometry.camera import project
from monose3.geometry.poses import transform_points
from monose3.robot import RobotModel

if TYPE_CHECKING:
    from monose3.perception.fitting import Fit


@dataclass(frozen=True)
class Limits:
    """Where a fit is doubted: its silhouette's IoU with the mask below ``iou``, its outline more
    than ``edge_distance_px`` (RMS, view pixels) off the image's own edges, or less than
    ``edge_support`` of it on them (a fit to a wrong mask: the edges do not come from the parser),
    its restarts in depth ending more than ``spread_mm`` apart (the image does not fix its depth),
    a pixel of the robot's size in the image standing for more than ``depth_per_pixel_mm`` of
    depth (:func:`depth_per_pixel_mm`; too small for its distance). Where the silhouette fits the
    mask at least ``close_iou``, the outline may lie up to ``close_edge_distance_px`` off the
    edges: a wrong mask is rarely a robot's shape, so a fit that matches it that closely is
    mostly a good fit in an image whose edges are soft."""

    iou: float
    edge_distance_px: float
    edge_support: float
    spread_mm: float
    depth_per_pixel_mm: float = math.inf
    close_iou: float = math.inf
    close_edge_distance_px: float = math.inf

    def edge_limit_px(self, iou: float | np.ndarray) -> np.ndarray:
        """How far (view pixels, RMS) the outline may lie off the image's edges at this IoU (or
        these, elementwise: the benchmark reads many fits at once)."""
        return np.where(np.asarray(iou) >= self.close_iou, self.close_edge_distance_px, self.edge_distance_px)


# The ``reliable`` flag. Chosen on 1,180 hard and 440 reallike frames of their own
# (benchmarks/reliable_flag.py: generate --renderer tiny, seeds 3003-12012) for at least 94 % recall
# of estimates off by more than 30 mm (a margin over the goal's 90 %) at the fewest false alarms,
# and checked on 400 frames generated after the choice (seeds 13013, 14014); the thresholds'
# history is in reliable_flag.py's docstring. MIN_INSIDE: less of the robot in the image than
# this is too little to fit to.
FLAG_LIMITS = Limits(0.5, 0.8, 0.2, 25.0, depth_per_pixel_mm=34.0, close_iou=0.9, close_edge_distance_px=1.2)
# When the first fit is doubted, the second look runs (fitting.fit_pose). Its trigger is the flag
# as it stood when the second look was measured (docs/PIPELINE.md, stage 9): more eager than the
# flag, as a second look costs time where a false alarm costs trust.
SECOND_LOOK_LIMITS = Limits(0.5, 0.8, 0.2, 20.0)
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


def fit_reasons(fit: Fit, limits: Limits = FLAG_LIMITS) -> list[str]:
    """Why ``fit`` is not to be trusted by its own numbers, in words (empty: it is, as far as
    the fit can tell), against ``limits``."""
    if not fit.found:
        return ["the robot was not found"]
    reasons = []
    if fit.iou < limits.iou:
        reasons.append(f"silhouette IoU {fit.iou:.2f} < {limits.iou}")
    if math.isinf(fit.edge_distance_px):
        return [*reasons, "no image edge along the outline"]
    edge_limit = float(limits.edge_limit_px(fit.iou))
    if fit.edge_distance_px > edge_limit:
        reasons.append(f"outline {fit.edge_distance_px:.2f} px off the image's edges > {edge_limit}")
    if fit.edge_support < limits.edge_support:
        share = 100 * fit.edge_support
        reasons.append(f"{share:.0f} % of the outline on the image's edges < {100 * limits.edge_support:.0f} %")
    if fit.spread_mm > limits.spread_mm:
        reasons.append(f"restarts in depth ended {fit.spread_mm:.0f} mm apart > {limits.spread_mm:g} mm")
    return reasons


def fit_doubts(fit: Fit, robot: RobotModel, joints: np.ndarray, K: np.ndarray, image_shape) -> list[str]:
    """:func:`fit_reasons`, and whether too little of the robot lies in the image to fit to or
    too little of the image to fix its depth (:func:`depth_per_pixel_mm`)."""
    reasons = fit_reasons(fit)
    if not fit.found:
        return reasons
    share = inside_fraction(robot, fit.pose, joints, K, image_shape)
    if share < MIN_INSIDE:
        reasons.append(f"only {100 * share:.0f} % of the robot in the image")
    depth_mm, limit = depth_per_pixel_mm(robot, fit.pose, joints, K), FLAG_LIMITS.depth_per_pixel_mm
    if depth_mm > limit:
        reasons.append(f"a pixel of the robot's size in the image is {depth_mm:.0f} mm of depth"
                       f" > {limit:g} mm: too small to fix its distance")  # fmt: skip
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
