"""The pose from the parser's evidence: PnP hypotheses, silhouette scoring, silhouette refinement.

Not in the paper; the stages EasyHeC and CtRNet use for a robot whose joints are known:

1. **Views.** The parser sees the whole image (padded to 4:3), then a zoomed view around the
   mask it found, so a small robot is parsed at a useful resolution (``views.parse_image``),
   with the context of wider boxes in its mask; each view's mask is the mean of the view's and
   its mirror image's (``views.parse_view``).
2. **Hypotheses.** PnP (OpenCV's SQPnP in RANSAC, and on leave-one-out subsets) from the
   keypoints, any poses the caller brings (a prior), and orientations over the sphere placed
   where the mask is and as large as it is (the fallback when PnP fails); ``hypotheses.py``.
3. **Scoring.** Each hypothesis is rendered (one batch) and scored by its silhouette's IoU with
   the mask, less its keypoint reprojection error.
4. **Refinement.** The best few are refined by damped Gauss-Newton on the keypoints' reprojection
   and on a symmetric chamfer between the rendered outline and the mask's (each outline pixel
   of the render, back-projected through its depth, is pulled to the nearest outline pixel of
   the mask, and each outline pixel of the mask pulls the nearest one of the render;
   re-rendered each iteration, so it is ICP on silhouettes). We chose this over a
   differentiable renderer or a derivative-free search: our rasteriser is exact but not
   differentiable, and correspondences make each iteration one render and a 6x6 solve, where a
   derivative-free search needs dozens of renders per step for the same precision.
   Everything is compared inside the image only (``ViewEvidence.valid_region``): where the
   image's border cuts the robot, the mask ends but the robot does not.
5. **Local search.** ICP follows the nearest outline, which a wrong part of the mask can lead
   astray; a derivative-free search on the whole silhouette's score from each start and each
   coarse result (``local_search.py``) gives the fine pass more starts (those that are copies
   of a better one to a few millimetres dropped: ``distinct_poses``).
6. **Edges.** At the view's resolution the render's outline is also pulled onto the image's
   own edges (``perception/edges.py``), with the mask's terms weighted down: the coarse pass on
   the mask brought the fit into its basin, the edges give it sub-pixel precision. So are the
   render's edges inside its silhouette, where its unlit colours change or a link passes in
   front of another, each by how far the image's edge lies from the render's own
   (``edges.inner_edge_terms``): they hold where the outline barely differs from the background.
7. **Restarts in depth.** The fit converges where the outline's edges hold it, which is not
   always where the robot is: along the line of sight (the robot's size in the image) a fit
   can stop a percent or two off, with each outline pixel on some edge. The edge refinement
   runs again from the best pose moved :data:`DEPTH_RESTART` of its distance nearer and
   further; each restart finds its own edges, and the better one is the pose. How far apart
   the two end (``Fit.spread_mm``) tells how firmly the image fixes the depth.
8. **Second look.** When the fit gives a reason to doubt it (``reliability.SECOND_LOOK_LIMITS``,
   more eager than the flag's), steps 3-7 run again from a denser sphere alone
   (``hypotheses.DENSE_AZIMUTHS`` x ``DENSE_ELEVATIONS``, each pose facing the robot along its
   ray; PnP's poses had their turn), and the better
   scoring of the two fits is the pose: the 16 poses of step 2 are often 20 degrees from a
   hard robot's orientation, too far for the refinement, and a doubted fit is where that shows.

The restarts start from the refined hypothesis with the best final fit (IoU, keypoint residual,
how much of the outline and of the inner edges the image's edges support), and the reported
pose is the restart that fits best by the same score (of both fits' restarts, after a second
look); the IoU is the confidence, and the ``reliable`` flag reads it with the fit's other
numbers (how its outline and inner edges lie on the image's edges, the restarts' spread;
``reliability.fit_doubts``).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from monose3.geometry.camera import project
from monose3.geometry.pose_solve import solve_pose
from monose3.geometry.poses import transform_points
from monose3.geometry.rotations import rotation_angle
from monose3.perception.edges import edge_agreement, edge_terms, inner_edge_support, inner_edge_terms
from monose3.perception.fit_result import Fit
from monose3.perception.hypotheses import DENSE_AZIMUTHS, DENSE_ELEVATIONS, pnp_hypotheses, sphere_hypotheses
from monose3.perception.local_search import DEFAULT_SEARCH, SearchConfig, search_locally
from monose3.perception.parser import RobotParser
from monose3.perception.reliability import SECOND_LOOK_LIMITS, fit_reasons
from monose3.perception.silhouette import (
    OUTLINE_SCALE,
    Outline,
    mask_ious,
    outline_terms,
    render_in_view,
    render_silhouettes,
    silhouette_ious,
)
from monose3.perception.views import MASK_THRESHOLD, MIN_MASK_FRACTION, ViewEvidence, parse_image, resized_view
from monose3.robot import RobotModel
from monose3.robot.renderer import RenderOutput, RobotRenderer

SCORE_SIZE = (160, 120)  # silhouettes of hypotheses are compared at this size
KEEP_HYPOTHESES = 2  # refined per image
COARSE_ITERATIONS = 12  # refinement at SCORE_SIZE, on the mask
REFINE_ITERATIONS = 16  # then at the view's resolution, with the image's edges
# Restarts (module step 7) from the best pose moved this share of its distance along the line
# of sight, each way (benchmarks/accuracy.py; 200 hard frames of seed 5005: 63 -> 54 estimates
# off by more than 30 mm, median 9.5 -> 8.9 mm).
DEPTH_RESTART = 0.02
# With the edges, the mask's terms weigh this share of their weight, and the edges up to
# EDGE_WEIGHT: where the image shows an edge it decides (benchmarks/accuracy.py).
MASK_SHARE_WITH_EDGES = 0.3
# Before the fine pass, poses closer than this (mean keypoint distance) are refined once: the
# local search often returns its start unchanged, and the two coarse results often meet, so half
# of the fine pass's six poses were copies (held-out frames: all six end within 5 mm in most).
DISTINCT_MM = 3.0
EDGE_WEIGHT = 1000.0
# The robot's edges inside its silhouette (a black joint ring on a white link, a link in front of
# another) pulled to the image's, as the outline's are (edges.inner_edge_terms): they fix the pose
# where the outline cannot, against the background (seeds 5005 / 7007, 40 / 60 hard frames: AUC
# 73.6 -> 76.6 and 74.8 -> 78.6, median 10.1 -> 5.8 and 7.9 -> 5.1 mm; weights 400 / 2500 did less).
INNER_EDGE_WEIGHT = 1000.0
KEYPOINT_PENALTY = 2.0  # score = IoU - this * (keypoint error / view width)
# The final choice adds this times the outline's edge support: of two refined hypotheses that fit
# the mask alike, the one the image's edges confirm (benchmarks/accuracy.py: held-out hard AUC 60.8 -> 62.8).
EDGE_SUPPORT_SCORE = 0.5
# And this times the inner edges' support (edges.inner_edge_support): they confirm a pose where
# the outline barely differs from the background (docs/PIPELINE.md, stage 8: hard frames of seeds
# 11011 / 9009, AUC 79.1 -> 79.9 and, on all the inner edges, 77.4 -> 79.2; reallike unchanged).
INNER_SUPPORT_SCORE = 0.5
KEYPOINT_ERROR_CAP = 0.1  # fraction of the view's width
KEYPOINT_SCALE = 0.02  # Cauchy scale of keypoint residuals in the refinement, fraction of the view's width
CONVERGED_MM, CONVERGED_DEG = 0.2, 0.02


def keypoint_distances(poses: np.ndarray, keypoints_base: np.ndarray, view: ViewEvidence) -> np.ndarray:
    """``[H, K]`` pixel distance of each keypoint, as each pose projects it, to where the parser saw it."""
    return np.linalg.norm(project(transform_points(poses, keypoints_base), view.K) - view.keypoints, axis=-1)


def keypoint_errors(poses: np.ndarray, keypoints_base: np.ndarray, view: ViewEvidence) -> np.ndarray:
    """Confidence-weighted mean reprojection error ``[H]`` (view pixels) of the keypoints at
    each pose, each error capped at :data:`KEYPOINT_ERROR_CAP` of the view's width (a keypoint
    the parser got wrong costs a bounded amount)."""
    err = np.minimum(keypoint_distances(poses, keypoints_base, view), KEYPOINT_ERROR_CAP * view.size[0])
    return (err * view.confidence).sum(-1) / max(view.confidence.sum(), 1e-6)


def fit_scores(ious: np.ndarray, kp_errors: np.ndarray, view: ViewEvidence) -> np.ndarray:
    return ious - KEYPOINT_PENALTY * np.minimum(kp_errors / view.size[0], 1.0)


def refine_poses(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                 keypoints_base: np.ndarray, iterations: int = REFINE_ITERATIONS, edges: bool = False,
                 inner_edges: bool = False, mask_share: float | None = None) -> np.ndarray:  # fmt: skip
    """Silhouette + keypoint refinement of ``poses`` ``[H, 4, 4]`` (see the module's step 4), and
    with ``edges`` the image's edges too (step 6; a view without pixels has none), for the
    outline and, with ``inner_edges``, for the robot's inner edges. The mask's terms weigh
    ``mask_share`` of their weight (default :data:`MASK_SHARE_WITH_EDGES` with edges, else all)."""
    edges = edges and view.image is not None
    inner_edges = inner_edges and edges
    if mask_share is None:
        mask_share = MASK_SHARE_WITH_EDGES if edges else 1.0
    target = Outline((view.mask > MASK_THRESHOLD).numpy(), view.valid)
    scale = OUTLINE_SCALE * view.size[0]
    rng = np.random.default_rng(0)
    n = len(poses)
    K = torch.from_numpy(view.K)[None].expand(n, 3, 3)
    for _ in range(iterations):
        kp_dist = keypoint_distances(poses, keypoints_base, view)
        kp_weights = view.confidence / (1 + (kp_dist / (KEYPOINT_SCALE * view.size[0])) ** 2)
        rendered = render_in_view(renderer, joints, poses, view)
        masks, depths = rendered.mask.cpu().numpy(), rendered.depth.cpu().numpy()
        colors = renderer.unlit_colors(rendered.face.cpu().numpy()) if inner_edges else [None] * n
        points, goals, weights = [], [], []
        for mask, depth, color, pose, kp_w in zip(masks, depths, colors, poses, kp_weights, strict=True):
            terms = [(keypoints_base, view.keypoints, kp_w)]
            pts, goal, w = outline_terms(target, mask, depth, pose, view.K, scale, rng, view.valid)
            terms.append((pts, goal, mask_share * w))
            if edges:
                terms.append(edge_terms(view.image, mask, depth, pose, view.K, EDGE_WEIGHT, rng, view.valid))
            if inner_edges:
                terms.append(inner_edge_terms(view.image, color, depth, mask, pose, view.K, INNER_EDGE_WEIGHT, rng,
                                              view.valid))  # fmt: skip
            points.append(np.concatenate([t[0] for t in terms]))
            goals.append(np.concatenate([t[1] for t in terms]))
            weights.append(np.concatenate([t[2] for t in terms]))
        new = solve_pose(torch.from_numpy(poses), K, _stack_padded(points), _stack_padded(goals),
                         _stack_padded(weights), iterations=2).numpy()  # fmt: skip
        moved_mm = 1000 * np.linalg.norm(new[:, :3, 3] - poses[:, :3, 3], axis=-1).max()
        moved_deg = np.degrees(rotation_angle(new[:, :3, :3], poses[:, :3, :3])).max()
        poses = new
        if moved_mm < CONVERGED_MM and moved_deg < CONVERGED_DEG:
            break
    return poses


def refine_coarse_to_fine(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                          keypoints_base: np.ndarray, coarse: int = COARSE_ITERATIONS, fine: int = REFINE_ITERATIONS,
                          edges: bool = True, search: SearchConfig | None = None,
                          pivot: np.ndarray | None = None, inner_edges: bool = True) -> np.ndarray:  # fmt: skip
    """:func:`refine_poses` on the mask at :data:`SCORE_SIZE` first (``coarse`` iterations:
    renders 4x cheaper, and ICP on silhouettes needs many small steps from afar), then ``fine``
    at the view's resolution, with the image's ``edges`` (for the outline, and with
    ``inner_edges`` for the robot's inner edges). With ``search``, the local search
    (module step 5) from each start and each coarse result goes between them, turning trial
    poses about ``pivot`` (the robot's centre in the base frame); all refined poses ``[H or 3H,
    4, 4]`` come back, for :func:`best_fit`."""
    refined = refine_poses(renderer, joints, poses, resized_view(view, SCORE_SIZE), keypoints_base, coarse)
    if search is not None:
        score = lambda trials: hypothesis_scores(renderer, joints, trials, view, keypoints_base, search.size)  # noqa: E731
        refined = np.concatenate([refined, search_locally(np.concatenate([poses, refined]), score, pivot, search)])
        refined = distinct_poses(refined, score(refined), keypoints_base)
    return refine_poses(renderer, joints, refined, view, keypoints_base, fine, edges, inner_edges)


def distinct_poses(poses: np.ndarray, scores: np.ndarray, keypoints_base: np.ndarray,
                   min_mm: float = DISTINCT_MM) -> np.ndarray:  # fmt: skip
    """``poses`` ``[H, 4, 4]`` best first by ``scores``, without those whose keypoints lie within
    ``min_mm`` (mean distance) of a better pose's: they would end where it ends."""
    order = np.argsort(-scores, kind="stable")
    cam = transform_points(poses[order], keypoints_base)
    kept: list[int] = []
    for i in range(len(order)):
        if all(1000 * np.linalg.norm(cam[i] - cam[j], axis=-1).mean() >= min_mm for j in kept):
            kept.append(i)
    return poses[order[kept]]


def depth_restarts(pose: np.ndarray, pivot: np.ndarray, share: float = DEPTH_RESTART) -> np.ndarray:
    """``[2, 4, 4]``: ``pose`` moved along the line of sight through ``pivot`` (a point of the
    robot, base frame) so that the pivot's depth is ``1 - share`` and ``1 + share`` of what it
    was and its pixel stays (module step 7)."""
    starts = np.stack([pose, pose])
    starts[:, :3, 3] += np.array([[-share], [share]]) * transform_points(pose, pivot[None])
    return starts


def restarted_fit(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                  keypoints_base: np.ndarray, pivot: np.ndarray, edges: bool = True) -> Fit:  # fmt: skip
    """The module's step 7: the best of the refined ``poses`` (:func:`best_fit`) restarted
    either side in depth (:func:`depth_restarts`) and refined again at the view's resolution;
    the better restart is the fit, and ``spread_mm`` is how far apart the two end."""
    best = best_fit(renderer, joints, poses, view, keypoints_base).pose
    starts = depth_restarts(best, pivot)
    ends = refine_poses(renderer, joints, starts, view, keypoints_base, edges=edges, inner_edges=edges)
    return best_fit(renderer, joints, ends, view, keypoints_base)


def _stack_padded(arrays: list[np.ndarray]) -> torch.Tensor:
    """Rows of different lengths stacked, zero-padded (zero weight: padding does not count)."""
    n = max(len(a) for a in arrays)
    return torch.from_numpy(np.stack([np.pad(a, [(0, n - len(a))] + [(0, 0)] * (a.ndim - 1)) for a in arrays]))


def fit_pose(
    parser: RobotParser,
    renderer: RobotRenderer,
    robot: RobotModel,
    image: np.ndarray,
    K: np.ndarray,
    joints: np.ndarray,
    extra_poses: np.ndarray | None = None,
    sphere: bool = True,
    refine: bool = True,
    edges: bool = True,
    search: bool = True,
    restart: bool = True,
    second_look: bool = True,
) -> Fit:
    """The module's stages on one image (``[H, W, 3]`` uint8 RGB, its K, the joints).
    ``sphere`` / ``refine`` / ``search`` / ``restart`` / ``second_look`` off leave out the
    sphere's hypotheses / the refinement / its local search / its restarts in depth / the second
    look, ``edges`` off refines on the mask alone (ablations)."""
    clock = _Clock()
    view = parse_image(parser, image, K)
    if view.robot_fraction < MIN_MASK_FRACTION:
        return not_found(view)
    clock.lap("parse")
    kp_base = robot.keypoints(joints[None])[0]
    hyps = pnp_hypotheses(view, kp_base)
    if extra_poses is not None:
        hyps += list(extra_poses)
    surface = robot.surface_points(joints[None])[0]
    stages = dict(joints=joints, view=view, kp_base=kp_base, pivot=robot.centroid(surface), refine=refine,
                  edges=edges, search=search, restart=restart)  # fmt: skip
    first = hyps + sphere_hypotheses(view, surface) if sphere or not hyps else hyps
    if not first:
        return not_found(view)
    fit = _fit_hypotheses(renderer, np.stack(first), clock=clock, **stages)
    if second_look and refine and fit_reasons(fit, SECOND_LOOK_LIMITS):
        dense = sphere_hypotheses(view, surface, DENSE_AZIMUTHS, DENSE_ELEVATIONS, facing=True)
        other = _fit_hypotheses(renderer, np.stack(dense), clock=_Clock(), **stages) if dense else fit
        fit = other if other.score > fit.score else fit
        clock.lap("second look")
    fit.timings = clock.laps
    return fit


def _fit_hypotheses(renderer: RobotRenderer, hyps: np.ndarray, joints: np.ndarray, view: ViewEvidence,
                    kp_base: np.ndarray, pivot: np.ndarray, refine: bool, edges: bool, search: bool,
                    restart: bool, clock: _Clock) -> Fit:  # fmt: skip
    """The module's steps 3-7 from the hypotheses ``hyps`` ``[H, 4, 4]``, timed by ``clock``."""
    poses = best_hypotheses(renderer, joints, hyps, view, kp_base, KEEP_HYPOTHESES)
    clock.lap("search")
    if refine:
        local = DEFAULT_SEARCH if search else None
        poses = refine_coarse_to_fine(renderer, joints, poses, view, kp_base, edges=edges, search=local, pivot=pivot)
        clock.lap("refine")
    if refine and restart:
        fit = restarted_fit(renderer, joints, poses, view, kp_base, pivot, edges)
        clock.lap("restart")
    else:
        fit = best_fit(renderer, joints, poses, view, kp_base)
        clock.lap("score")
    return fit


def hypothesis_scores(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                      kp_base: np.ndarray, size: tuple[int, int] = SCORE_SIZE) -> np.ndarray:  # fmt: skip
    """Score ``[H]`` of ``poses`` ``[H, 4, 4]``: silhouette IoU at ``size`` less the keypoint term."""
    ious = silhouette_ious(renderer, joints, poses, view, size)
    return fit_scores(ious, keypoint_errors(poses, kp_base, view), view)


def best_hypotheses(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                    kp_base: np.ndarray, keep: int) -> np.ndarray:  # fmt: skip
    """The ``keep`` best of ``poses`` ``[H, 4, 4]`` by :func:`hypothesis_scores`."""
    return poses[np.argsort(-hypothesis_scores(renderer, joints, poses, view, kp_base))[:keep]]


def best_fit(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
             kp_base: np.ndarray, inner_edges: bool = True) -> Fit:  # fmt: skip
    """The best of ``poses`` by their fit in ``view`` (silhouette at full view size, keypoints,
    and how much of the outline and, with ``inner_edges``, of the inner edges lies on the image's
    edges), with what the ``reliable`` flag reads (the outline's distance to the image's edges)
    and the other poses' distance to the best."""
    # The inner edges need the render's depth and faces: its mask is then the silhouette (the
    # same, pixel for pixel), not rendered again.
    rendered = render_in_view(renderer, joints, poses, view) if inner_edges and view.image is not None else None
    silhouettes = render_silhouettes(renderer, joints, poses, view, view.size) if rendered is None else rendered.mask
    ious = mask_ious(silhouettes, view)
    errors = keypoint_errors(poses, kp_base, view)
    edges = np.array([[0.0, math.inf]] * len(poses))
    if view.image is not None:
        edges = np.array([edge_agreement(view.image, mask, view.valid) for mask in silhouettes.cpu().numpy()])
    inner = np.zeros(len(poses)) if rendered is None else inner_supports(renderer, rendered, view)
    scores = fit_scores(ious, errors, view) + EDGE_SUPPORT_SCORE * edges[:, 0] + INNER_SUPPORT_SCORE * inner
    order = np.argsort(-scores)
    best = order[0]
    fit = Fit(poses[best], float(ious[best]), float(errors[best]), float(scores[best]), view, poses[order],
              edge_support=float(edges[best, 0]), edge_distance_px=float(edges[best, 1]),
              inner_support=float(inner[best]) if rendered is not None else math.nan)  # fmt: skip
    cam = transform_points(poses[order], kp_base)
    fit.spread_mm = float(1000 * np.linalg.norm(cam[1:] - cam[:1], axis=-1).mean()) if len(poses) > 1 else 0.0
    return fit


def inner_supports(renderer: RobotRenderer, rendered: RenderOutput, view: ViewEvidence) -> np.ndarray:
    """``[H]``: how well each ``rendered`` pose's inner edges lie on the image's (``edges.inner_edge_support``)."""
    colors = renderer.unlit_colors(rendered.face.cpu().numpy())
    parts = zip(colors, rendered.depth.cpu().numpy(), rendered.mask.cpu().numpy(), strict=True)
    return np.array([inner_edge_support(view.image, color, depth, mask, view.valid) for color, depth, mask in parts])


class _Clock:
    def __init__(self):
        self.laps: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._last
        self._last = now


def not_found(view: ViewEvidence) -> Fit:
    return Fit(np.full((4, 4), np.nan), 0.0, math.inf, -math.inf, view, np.zeros((0, 4, 4)), found=False)
