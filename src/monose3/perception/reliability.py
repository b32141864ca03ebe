"""The ``reliable`` flag of the default pipeline and the second look's trigger.

The flag (:func:`fit_doubts`) reads a fit's numbers (:func:`fit_numbers`: its silhouette's IoU,
how its outline and its inner edges lie on the image's edges, its restarts' spread, how much of
the robot is in the image and how much depth a pixel of its size stands for) through a logistic
model of the odds that the fit is off by more than 30 mm (:class:`DoubtModel`). The second look's trigger
(:func:`fit_reasons`) is thresholds on the fit's own numbers (:class:`Limits`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from monose3.geometry.camera import inside_image, project
from monose3.geometry.poses import transform_points
from monose3.perception.fit_result import Fit
from monose3.robot import RobotModel


@dataclass(frozen=True)
class Limits:
    """Where a fit is doubted enough for the second look (``fitting.fit_pose``, step 8): its
    silhouette's IoU with the mask below ``iou``, its outline more than ``edge_distance_px`` (RMS,
    view pixels) off the image's own edges, or less than ``edge_support`` of it on them (a fit to
    a wrong mask: the edges do not come from the parser), its restarts in depth ending more than
    ``spread_mm`` apart (the image does not fix its depth)."""

    iou: float
    edge_distance_px: float
    edge_support: float
    spread_mm: float


# When the first fit is doubted, the second look runs (fitting.fit_pose). Its trigger is the flag
# as it stood when the second look was measured (docs/PIPELINE.md, stage 9): more eager than the
# flag, as a second look costs time where a false alarm costs trust.
SECOND_LOOK_LIMITS = Limits(0.5, 0.8, 0.2, 20.0)
MIN_INSIDE = 0.5  # less of the robot in the image than this is too little to fit to
MIN_IOU = 0.5  # a silhouette that misses most of the parser's mask (or the mask most of it) is no fit
# A pixel of the robot's size standing for more depth than this (depth_per_pixel_mm) is too little
# to fix its distance: of the 2,020 frames of seeds 3003-14014 (the fits of this code), all 20
# fits beyond it were off by more than BAD_MM, too few for the model to learn it from.
MAX_DEPTH_PER_PIXEL_MM = 40.0
BAD_MM = 30.0  # what the flag's model calls a bad estimate: ADD above this
NUMBERS = ("iou", "edge_distance", "support", "spread", "inside", "depth_per_pixel", "inner_support")  # fit_numbers's
# the sign of a change that makes a fit worse, number by number
WORSE = {"iou": -1, "edge_distance": 1, "support": -1, "spread": 1, "inside": -1, "depth_per_pixel": 1,
         "inner_support": -1}  # fmt: skip


def model_inputs(numbers: Mapping[str, ArrayLike]) -> dict[str, np.ndarray]:
    """The flag model's inputs from a fit's numbers (:func:`fit_numbers`; scalars, or arrays of
    many fits): those that grow without bound capped (an outline far from any edge, a robot too
    far to fix), the restarts' spread on a log scale (it spans 0.1 mm to metres), a support not
    measured (a robot not found; saved features write it null) as none."""
    x = {k: np.asarray(numbers[k], float) for k in NUMBERS}
    capped = {
        "edge_distance": np.minimum(x["edge_distance"], 5.0),
        "depth_per_pixel": np.minimum(x["depth_per_pixel"], 200.0),
    }
    unmeasured_as_none = {k: np.nan_to_num(x[k], nan=0.0, posinf=0.0) for k in ("support", "inner_support")}
    return {**x, **capped, **unmeasured_as_none, "spread": np.log1p(np.minimum(x["spread"], 500.0))}


@dataclass(frozen=True)
class DoubtModel:
    """The ``reliable`` flag: a logistic model of the odds that a fit is off by more than
    :data:`BAD_MM` (ADD), read from all its numbers at once (:func:`model_inputs`), flagged at
    ``threshold`` or more. Thresholds on each number alone flag many good fits for one number
    just past its limit that the others vouch for; the model weighs them together. ``typical``
    holds a good fit's numbers (the medians of good fits): a doubt names the numbers whose
    departure from them raised the odds most."""

    weights: Mapping[str, float]
    bias: float
    threshold: float
    typical: Mapping[str, float]

    def logits(self, numbers: Mapping[str, ArrayLike]) -> np.ndarray:
        inputs = model_inputs(numbers)
        return self.bias + sum(w * inputs[k] for k, w in self.weights.items())

    def odds(self, numbers: Mapping[str, ArrayLike]) -> np.ndarray:
        """The probability that each fit is off by more than :data:`BAD_MM`."""
        return 1 / (1 + np.exp(-self.logits(numbers)))

    def doubted(self, numbers: Mapping[str, ArrayLike]) -> np.ndarray:
        """Unreliable (elementwise): a :func:`sure_doubts`, or :meth:`odds` at the threshold or more."""
        return surely_doubted(numbers) | (self.odds(numbers) >= self.threshold)

    def causes(self, numbers: Mapping[str, float], most: int = 2) -> list[str]:
        """The numbers (names) worse than a typical good fit's that raise the odds most above its,
        largest first: up to ``most``, each raising the log-odds by a third of the first's or more.
        (A number better than typical can raise the odds too, where the model uses it to tell
        apart fits that others make look alike; it is no reason to give in words.)"""
        inputs, typical = model_inputs(numbers), model_inputs(self.typical)
        raised = {k: float(w * (inputs[k] - typical[k])) for k, w in self.weights.items()
                  if WORSE[k] * (inputs[k] - typical[k]) > 0}  # fmt: skip
        ranked = [k for k in sorted(raised, key=raised.get, reverse=True)[:most] if raised[k] > 0]
        return [k for k in ranked if raised[k] >= raised[ranked[0]] / 3]


def sure_doubts(numbers: Mapping[str, ArrayLike]) -> dict[str, np.ndarray]:
    """The doubts no other number outweighs, by the number that raises them (elementwise): a
    silhouette IoU below :data:`MIN_IOU`, no image edge along the outline, less than
    :data:`MIN_INSIDE` of the robot in the image, a pixel of its size more than
    :data:`MAX_DEPTH_PER_PIXEL_MM` of depth."""
    x = {k: np.asarray(numbers[k], float) for k in NUMBERS}
    return {"iou": x["iou"] < MIN_IOU, "edge_distance": ~np.isfinite(x["edge_distance"]),
            "inside": x["inside"] < MIN_INSIDE,
            "depth_per_pixel": x["depth_per_pixel"] > MAX_DEPTH_PER_PIXEL_MM}  # fmt: skip


def surely_doubted(numbers: Mapping[str, ArrayLike]) -> np.ndarray:
    """Whether any of :func:`sure_doubts` holds (elementwise)."""
    return np.logical_or.reduce(list(sure_doubts(numbers).values()))


# Fitted on 1,200 hard frames of their own (seeds 7007, 9009, 11011, 13013) for 93 % recall
# (benchmarks/reliable_flag.py --features docs/results/reliable_flag_features.json): each seed's
# frames predicted by a model fitted on the other three, 93.0 % of the bad estimates are flagged
# with 6.8 % false alarms; without the inner edges' support, 91.6 % with 8.8 % (and threshold
# rules chosen alike on the 2,020 frames of seeds 3003-14014, 90.7 % with 9.0 %; docs/PIPELINE.md,
# stage 8). FLAG_MODEL_WITHOUT_INNER, fitted alike without it, judges fits that did not measure
# it (tracking's: from_pose.track_pose leaves the inner edges out).
FLAG_MODEL = DoubtModel(
    weights={"iou": -6.4518, "edge_distance": 8.0787, "support": 3.8392, "spread": 1.0467, "inside": -5.0635,
             "depth_per_pixel": 0.0014, "inner_support": -6.8285},
    bias=0.5547,
    threshold=0.2035,
    typical={"iou": 0.904, "edge_distance": 0.636, "support": 0.664, "spread": 2.177, "inside": 1.0,
             "depth_per_pixel": 11.048, "inner_support": 0.614},
)  # fmt: skip
FLAG_MODEL_WITHOUT_INNER = DoubtModel(
    weights={"iou": -7.7709, "edge_distance": 9.2007, "support": 0.5424, "spread": 1.0357, "inside": -4.5924,
             "depth_per_pixel": 0.0043},
    bias=-1.2537,
    threshold=0.1415,
    typical={"iou": 0.904, "edge_distance": 0.636, "support": 0.664, "spread": 2.177, "inside": 1.0,
             "depth_per_pixel": 11.048, "inner_support": 0.614},
)  # fmt: skip


def inside_fraction(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray, image_shape) -> float:
    """The share of the robot's surface points that ``pose`` puts in front of the camera and inside the image."""
    if not np.isfinite(pose).all():
        return 0.0
    cam = transform_points(pose, robot.surface_points(joints[None])[0])
    return float(np.mean((cam[:, 2] > 0) & inside_image(project(cam, K), image_shape[1::-1])))


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


def fit_reasons(fit: Fit, limits: Limits = SECOND_LOOK_LIMITS) -> list[str]:
    """Why ``fit`` falls short of ``limits`` by its own numbers, in words (empty: it does not)."""
    if not fit.found:
        return ["the robot was not found"]
    reasons = []
    if fit.iou < limits.iou:
        reasons.append(f"silhouette IoU {fit.iou:.2f} < {limits.iou}")
    if math.isinf(fit.edge_distance_px):
        return [*reasons, "no image edge along the outline"]
    if fit.edge_distance_px > limits.edge_distance_px:
        reasons.append(f"outline {fit.edge_distance_px:.2f} px off the image's edges > {limits.edge_distance_px}")
    if fit.edge_support < limits.edge_support:
        share = 100 * fit.edge_support
        reasons.append(f"{share:.0f} % of the outline on the image's edges < {100 * limits.edge_support:.0f} %")
    if fit.spread_mm > limits.spread_mm:
        reasons.append(f"restarts in depth ended {fit.spread_mm:.0f} mm apart > {limits.spread_mm:g} mm")
    return reasons


def fit_numbers(fit: Fit, robot: RobotModel, joints: np.ndarray, K: np.ndarray, image_shape) -> dict[str, float]:
    """What the flag reads of a fit (:data:`NUMBERS`): its IoU, its outline's RMS distance to
    the image's edges (view pixels) and share on them, its restarts' spread (mm), the share of
    the robot in the image (:func:`inside_fraction`), the depth a pixel of its size stands for
    (:func:`depth_per_pixel_mm`), how well its inner edges lie on the image's (``edges.inner_edge_support``)."""
    return {"iou": fit.iou, "edge_distance": fit.edge_distance_px, "support": fit.edge_support,
            "spread": fit.spread_mm, "inside": inside_fraction(robot, fit.pose, joints, K, image_shape),
            "depth_per_pixel": depth_per_pixel_mm(robot, fit.pose, joints, K),
            "inner_support": fit.inner_support}  # fmt: skip


NUMBER_WORDS = {
    "iou": "silhouette IoU {:.2f}",
    "edge_distance": "outline {:.2f} px off the image's edges",
    "support": "{:.0f} % of the outline on the image's edges",
    "spread": "restarts in depth {:.0f} mm apart",
    "inside": "{:.0f} % of the robot in the image",
    "depth_per_pixel": "a pixel of its size is {:.0f} mm of depth",
    "inner_support": "inner edges {:.0f} % on the image's edges",
}


TRACKED_SPREAD_WORDS = "moved {:.0f} mm from the previous frame's pose"  # a tracked fit's spread


def _shown(name: str, value: float) -> float:
    return 100 * value if name in ("support", "inside", "inner_support") else value  # shares in words are percentages


def fit_doubts(fit: Fit, robot: RobotModel, joints: np.ndarray, K: np.ndarray, image_shape) -> list[str]:
    """Why the fit is not to be trusted, in words, as :data:`FLAG_MODEL` flags it
    (:meth:`DoubtModel.doubted`; :data:`FLAG_MODEL_WITHOUT_INNER` where the fit did not measure
    its inner edges; empty: it is, as far as its numbers tell)."""
    if not fit.found:
        return ["the robot was not found"]
    numbers = fit_numbers(fit, robot, joints, K, image_shape)
    model = FLAG_MODEL if math.isfinite(fit.inner_support) else FLAG_MODEL_WITHOUT_INNER
    sure = sure_doubts(numbers)
    reasons = []
    if sure["iou"]:
        reasons.append(f"silhouette IoU {fit.iou:.2f} < {MIN_IOU}")
    if sure["edge_distance"]:
        reasons.append("no image edge along the outline")
    if sure["inside"]:
        reasons.append(f"only {100 * numbers['inside']:.0f} % of the robot in the image")
    if sure["depth_per_pixel"]:
        reasons.append(f"a pixel of the robot's size in the image is {numbers['depth_per_pixel']:.0f} mm of depth"
                       f" > {MAX_DEPTH_PER_PIXEL_MM:g} mm: too small to fix its distance")  # fmt: skip
    odds = float(model.odds(numbers))
    if odds >= model.threshold:
        words = {**NUMBER_WORDS, "spread": TRACKED_SPREAD_WORDS} if fit.tracked else NUMBER_WORDS
        causes = " and ".join(words[k].format(_shown(k, numbers[k])) for k in model.causes(numbers))
        reasons.append(f"{100 * odds:.0f} % odds of an error over {BAD_MM:g} mm ({100 * model.threshold:.0f} % flags)"
                       + (f", mostly for its {causes}" if causes else ""))  # fmt: skip
    return reasons


def pose_in_view(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray, image_shape) -> bool:
    """Whether ``pose`` puts the robot's centroid in front of the camera and inside the image."""
    if not np.isfinite(pose).all():
        return False
    cam = transform_points(pose, robot.centroid(robot.surface_points(joints[None])))[0]
    return bool(cam[2] > 0 and inside_image(project(cam[None], K)[0], image_shape[1::-1]))
