"""Fits that start from a pose known roughly: tracking from the previous frame's pose, and the
default refinement from one pose (a rough prior, an earlier calibration; what
``benchmarks/accuracy.py`` measures the refinement by). Both parse one view of the image around
where that pose puts the robot; ``fitting.py`` holds the stages they share with a fit from scratch."""

from __future__ import annotations

import numpy as np

from monose3.geometry.camera import project
from monose3.geometry.poses import transform_points
from monose3.perception.fit_result import Fit
from monose3.perception.fitting import (
    MIN_MASK_FRACTION,
    best_fit,
    best_hypotheses,
    not_found,
    refine_coarse_to_fine,
    restarted_fit,
)
from monose3.perception.hypotheses import pnp_hypotheses
from monose3.perception.local_search import DEFAULT_SEARCH
from monose3.perception.parser import RobotParser
from monose3.perception.views import ViewEvidence, box_around, full_box, image_tensor, parse_view
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer

# Coarse, fine: between frames the robot moves little. Chosen on 100 frames each of seeds 5005
# (hard) and 6006 (reallike), from the true pose moved 2 cm / 3 deg as benchmarks/accuracy.py
# moves it, the variants interleaved frame by frame for their times: 4 + 4 ends at a median
# 18.4 / 3.1 mm, 4 + 5 at 16.3 / 2.8 mm in 8 % more time, 4 + 6 at 14.8 / 2.4 mm in 18 % more.
# 4 + 5 kept tracking at 5.1 images/s on the held-out reallike frames until the compiled
# rasteriser (robot/rasterize_cpu.py) brought it to 8.7; then, on 80 frames each of seeds 9009
# (hard) and 16016 (reallike), interleaved: 4 + 5 ends at a median 22.8 / 3.0 mm with 41 / 1 %
# of frames more than 30 mm off, 4 + 8 at 16.0 / 2.5 mm and 38 / 0 % in 18 % more time, 6 + 8
# at 15.8 / 2.5 mm and 34 / 0 % in 23 % more, 6 + 12 at 13.4 / 2.1 mm and 32 / 1 % in 48 % more.
# With the robot's inner edges pulled in the fine pass (below), 4 + 8 tracked 8 sequences of their
# own (benchmarks/sequences.py's kinds, seeds 41000-41007) to a median 1.12x the single-frame
# fit's (geometric mean over the sequences; at most 1.37x), 6 + 8 to 1.17x (at most 1.43x),
# against 1.47x (at most 2.96x) for 6 + 8 without them; 4 + 8 in 5 % less time than 6 + 8.
TRACK_ITERATIONS = (4, 8)


def view_around(parser: RobotParser, robot: RobotModel, image: np.ndarray, K: np.ndarray, joints: np.ndarray,
                pose: np.ndarray, mirror: bool = True) -> ViewEvidence:  # fmt: skip
    """The parser's view of the image around where ``pose`` (``[4, 4]``, or ``[N, 4, 4]``: around
    all of those that put the robot in front of the camera with its centroid in the image) puts
    the robot's surface: the whole image where that is larger, or where no pose puts it in view;
    ``mirror`` as :func:`~monose3.perception.views.parse_view` takes it."""
    size = parser.config.input_size
    aspect = size[0] / size[1]
    h, w = image.shape[:2]
    whole = full_box((w, h), aspect)
    surface = robot.surface_points(joints[None])[0]
    corners = []
    for p in np.asarray(pose, np.float64).reshape(-1, 4, 4):
        cam = surface @ p[:3, :3].T + p[:3, 3]
        uv = project(cam, K)
        centre = uv.mean(0)
        if np.isfinite(uv).all() and (cam[:, 2] > 0).all() and 0 <= centre[0] < w and 0 <= centre[1] < h:
            corners += [uv.min(0), uv.max(0)]
    box = box_around(np.min(corners, 0), np.max(corners, 0), aspect) if corners else whole
    if box[2] - box[0] > whole[2] - whole[0]:
        box = whole
    return parse_view(parser, image_tensor(image), K, box, mirror)


def track_pose(
    parser: RobotParser,
    renderer: RobotRenderer,
    robot: RobotModel,
    image: np.ndarray,
    K: np.ndarray,
    joints: np.ndarray,
    previous: np.ndarray,
    iterations: tuple[int, int] = TRACK_ITERATIONS,
) -> Fit:
    """Tracking: the refinement's (coarse, fine) ``iterations``, without the local search, in
    the parser's :func:`view_around` the ``previous`` pose, from the better of ``previous`` and
    the view's PnP hypotheses, scored as the search scores them (a few small renders): between
    frames the robot can move further than a few iterations reach, and a lost track is found again.
    The view's mask is not mirror-averaged: on the held-out frames tracking was no more accurate
    with it, and 10 % slower (benchmarks/accuracy.py). The fine pass pulls the robot's inner edges
    (``fitting.INNER_EDGE_WEIGHT``) as the full fit does: from a pose 2 cm / 3 deg off, in 4 + 5
    iterations, they had ended further (held-out median 3.6 -> 3.8 mm reallike, 19.0 -> 21.0 mm
    hard), but on sequences, where each frame starts a few millimetres off, they hold the track
    to the single-frame fit's precision (see :data:`TRACK_ITERATIONS`). Nor does it score them
    (``best_fit``'s ``inner_edges``): its one refined pose needs no choice."""
    view = view_around(parser, robot, image, K, joints, previous, mirror=False)
    if view.robot_fraction < MIN_MASK_FRACTION:
        return not_found(view)
    kp_base = robot.keypoints(joints[None])[0]
    start = best_hypotheses(renderer, joints, np.stack([previous, *pnp_hypotheses(view, kp_base)]), view, kp_base, 1)
    poses = refine_coarse_to_fine(renderer, joints, start, view, kp_base, *iterations)
    fit = best_fit(renderer, joints, poses, view, kp_base, inner_edges=False)
    # A tracked fit has no restarts whose spread tells how firmly the image holds it; how far it
    # moved from the previous frame's pose stands in (a track that slips jumps). On 8 sequences of
    # their own (benchmarks/sequences.py, seeds 41000-41007, 430 tracked frames) the flag then
    # caught 37 of 46 frames off by more than 30 mm with 43 false alarms in 383 (11 %), against
    # 14 of 46 with 10 (3 %) when the spread was left at 0.
    fit.tracked = True
    fit.spread_mm = float(
        1000 * np.linalg.norm(transform_points(fit.pose, kp_base) - transform_points(previous, kp_base), axis=-1).mean()
    )
    return fit


def judge_poses(parser: RobotParser, renderer: RobotRenderer, robot: RobotModel, image: np.ndarray, K: np.ndarray,
                joints: np.ndarray, poses: np.ndarray) -> list[Fit]:  # fmt: skip
    """Each of ``poses`` ``[N, 4, 4]`` as it stands (nothing refined), fitted to one parser view
    around them all (:func:`view_around`), so their fits compare: tracking's choice between a
    tracked pose and a re-estimate. Judged as tracking's fits are (no inner edges, no restarts),
    by the same flag."""
    view = view_around(parser, robot, image, K, joints, poses, mirror=False)
    if view.robot_fraction < MIN_MASK_FRACTION:
        return [not_found(view) for _ in poses]
    kp_base = robot.keypoints(joints[None])[0]
    return [best_fit(renderer, joints, pose[None], view, kp_base, inner_edges=False) for pose in poses]


def refine_from(parser: RobotParser, renderer: RobotRenderer, robot: RobotModel, image: np.ndarray,
                K: np.ndarray, joints: np.ndarray, start: np.ndarray) -> Fit:  # fmt: skip
    """The default pipeline's refinement (``refine_coarse_to_fine`` with the local search, then
    ``restarted_fit``) from the one pose ``start``, in the parser's :func:`view_around` it: what
    ``benchmarks/accuracy.py`` measures the refinement by, and a way to refine a pose known
    roughly (an earlier calibration)."""
    view = view_around(parser, robot, image, K, joints, start)
    if view.robot_fraction < MIN_MASK_FRACTION:
        return not_found(view)
    kp_base = robot.keypoints(joints[None])[0]
    pivot = robot.centroid(robot.surface_points(joints[None])[0])
    poses = refine_coarse_to_fine(renderer, joints, start[None], view, kp_base, search=DEFAULT_SEARCH, pivot=pivot)
    return restarted_fit(renderer, joints, poses, view, kp_base, pivot)
