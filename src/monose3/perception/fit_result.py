"""The record of one image's fit (:class:`Fit`): what ``fitting`` and ``from_pose`` produce and
``reliability`` judges, in a module of its own so that neither imports the other for it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monose3.perception.views import ViewEvidence


@dataclass
class Fit:
    """One image's result: the pose (camera-from-base), its fit and the view it was fitted in."""

    pose: np.ndarray
    iou: float
    keypoint_error: float  # mean reprojection error of confident keypoints, view pixels
    score: float
    view: ViewEvidence
    candidates: np.ndarray  # [H, 4, 4] the refined hypotheses (with the restarts: the two), best first
    edge_support: float = 0.0  # share of the pose's outline on the image's own edges, [0, 1]
    edge_distance_px: float = math.inf  # RMS distance of the outline to the image's edges, view pixels
    # Mean keypoint distance of the other candidates (the other restart) to the pose; for a tracked
    # fit (``tracked``), of the previous frame's pose to it (from_pose.track_pose).
    spread_mm: float = 0.0
    inner_support: float = math.nan  # how well the render's inner edges lie on the image's, [0, 1]; NaN: not measured
    found: bool = True
    tracked: bool = False  # refined from the previous frame's pose (tracking), not fitted from scratch
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
