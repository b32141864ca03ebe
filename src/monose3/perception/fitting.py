"""The pose from the parser's evidence: PnP hypotheses, silhouette scoring, silhouette refinement.

Not in the paper; the stages EasyHeC and CtRNet use for a robot whose joints are known:

1. **Views.** The parser sees the whole image (padded to 4:3), then a zoomed view around the
   mask it found, so a small robot is parsed at a useful resolution.
2. **Hypotheses.** PnP (OpenCV's SQPnP in RANSAC) from the keypoints, plus any poses the caller
   brings (the diffusion's chains, a prior); when neither gives one, orientations over the
   sphere placed where the mask is and as large as it is.
3. **Scoring.** Each hypothesis is rendered (one batch) and scored by its silhouette's IoU with
   the mask, less its keypoint reprojection error.
4. **Refinement.** The best few are refined by damped Gauss-Newton on the keypoints' reprojection
   and on the rendered outline's distance to the mask's outline (each outline pixel of the
   render, back-projected through its depth, is pulled to the nearest outline pixel of the
   mask; re-rendered each iteration, so it is ICP on silhouettes). We chose this over a
   differentiable renderer or a derivative-free search: our rasteriser is exact but not
   differentiable, and correspondences make each iteration one render and a 6x6 solve, where a
   derivative-free search needs dozens of renders per step for the same precision.

The reported pose is the refined hypothesis with the best final fit; the fit (IoU, keypoint
residual) is the confidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torchvision.ops import roi_align

from monose3.geometry.camera import crop_intrinsics, project
from monose3.geometry.poses import make_pose
from monose3.geometry.rotations import rotation_angle
from monose3.method.flow_pose import solve_pose
from monose3.perception.parser import RobotParser, decode_keypoints
from monose3.robot import RobotModel
from monose3.robot.renderer import RobotRenderer

MASK_THRESHOLD = 0.5
MIN_MASK_FRACTION = 2e-4  # of the view's pixels: fewer robot pixels than this is "no robot"
ZOOM_MARGIN = 1.3  # the zoomed view spans the mask's box grown by this factor
ZOOM_MAX_FRACTION = 0.7  # zoom only when the mask's box is smaller than this fraction of the view
MIN_KEYPOINT_CONFIDENCE = 0.2
PNP_ERROR_FRACTION = 0.02  # RANSAC inlier threshold, as a fraction of the view's width
SCORE_SIZE = (160, 120)  # silhouettes of hypotheses are compared at this size
KEEP_HYPOTHESES = 4  # refined per image
REFINE_ITERATIONS = 8
TRACK_ITERATIONS = 3
OUTLINE_POINTS = 300  # render outline pixels used per iteration
OUTLINE_WEIGHT = 7.0  # the outline's total weight in the solve (each keypoint weighs its confidence <= 1)
OUTLINE_SCALE = 0.015  # Cauchy scale of outline residuals, fraction of the view's width
KEYPOINT_PENALTY = 2.0  # score = IoU - this * (keypoint error / view width)
KEYPOINT_ERROR_CAP = 0.1  # fraction of the view's width
KEYPOINT_SCALE = 0.02  # Cauchy scale of keypoint residuals in the refinement, fraction of the view's width
CONVERGED_MM, CONVERGED_DEG = 0.2, 0.02
SPHERE_AZIMUTHS, SPHERE_ELEVATIONS = 12, (0.0, 30.0, 60.0)
# The fit flags an estimate unreliable below this IoU (benchmarks/accuracy.py measures what it catches).
RELIABLE_IOU = 0.9


@dataclass
class ViewEvidence:
    """What the parser sees in one view (a box of the image resized to the parser's input)."""

    mask: torch.Tensor  # [h, w] robot probability at the view's resolution
    keypoints: np.ndarray  # [K, 2] view pixels
    confidence: np.ndarray  # [K]
    K: np.ndarray  # [3, 3] the view's intrinsics
    box: np.ndarray  # [4] x1, y1, x2, y2 in the image (edge coordinates)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.mask.shape[1]), int(self.mask.shape[0])

    @property
    def robot_fraction(self) -> float:
        return float((self.mask > MASK_THRESHOLD).float().mean())


@dataclass
class Fit:
    """One image's result: the pose (camera-from-base), its fit and the view it was fitted in."""

    pose: np.ndarray
    iou: float
    keypoint_error: float  # mean reprojection error of confident keypoints, view pixels
    score: float
    view: ViewEvidence
    candidates: np.ndarray  # [H, 4, 4] the refined hypotheses, best first
    found: bool = True


def image_tensor(image: np.ndarray) -> torch.Tensor:
    """``[H, W, 3]`` uint8 to ``[1, 3, H, W]`` float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0)


@torch.no_grad()
def parse_view(parser: RobotParser, image: torch.Tensor, K: np.ndarray, box: np.ndarray) -> ViewEvidence:
    """Run the parser on ``box`` (edge coordinates; beyond the image is black, as padding) of
    ``image`` ``[1, 3, H, W]``, resized to the parser's input with anti-aliasing."""
    size = parser.config.input_size
    device = next(parser.parameters()).device
    rois = torch.tensor([[0.0, *box]], dtype=torch.float32)
    view = roi_align(image, rois, (size[1], size[0]), 1.0, sampling_ratio=0, aligned=True)
    mask_logits, kp_logits = parser(view.to(device))
    mask = F.interpolate(mask_logits, size=(size[1], size[0]), mode="bilinear", align_corners=False)
    uv, conf = decode_keypoints(kp_logits.float())
    K_view = crop_intrinsics(torch.from_numpy(K)[None], torch.from_numpy(box)[None].double(), size)[0].numpy()
    return ViewEvidence(mask[0, 0].float().sigmoid().cpu(), uv[0].cpu().double().numpy(), conf[0].cpu().numpy(),
                        K_view, np.asarray(box, np.float64))  # fmt: skip


def full_box(image_size: tuple[int, int], aspect: float) -> np.ndarray:
    """The whole image padded (right/bottom) to ``aspect`` (w/h), as the estimator standardises it."""
    w, h = image_size
    return np.array([0.0, 0.0, max(w, h * aspect), max(h, w / aspect)])


def zoom_box(view: ViewEvidence, aspect: float) -> np.ndarray | None:
    """The image box around the robot that ``view``'s mask shows, or None when the robot
    already fills the view."""
    ys, xs = np.nonzero((view.mask > MASK_THRESHOLD).numpy())
    w, h = view.size
    if (xs.max() + 1 - xs.min()) * ZOOM_MARGIN > ZOOM_MAX_FRACTION * w:
        return None
    scale = (view.box[2:] - view.box[:2]) / np.array([w, h])
    lo = view.box[:2] + np.array([xs.min(), ys.min()]) * scale
    hi = view.box[:2] + np.array([xs.max() + 1, ys.max() + 1]) * scale
    return box_around(lo, hi, aspect)


def box_around(lo: np.ndarray, hi: np.ndarray, aspect: float) -> np.ndarray:
    """The box (edge coordinates) centred on the box ``lo``-``hi``, grown by :data:`ZOOM_MARGIN` and to ``aspect``."""
    half = (hi - lo) / 2 * ZOOM_MARGIN
    half = np.maximum(half, [half[1] * aspect, half[0] / aspect])
    centre = (lo + hi) / 2
    return np.concatenate([centre - half, centre + half])


def pnp_hypotheses(view: ViewEvidence, keypoints_base: np.ndarray) -> list[np.ndarray]:
    """Camera-from-base poses from the confident keypoints: RANSAC + SQPnP, refined by LM on
    its inliers, and SQPnP on all confident keypoints."""
    good = view.confidence >= MIN_KEYPOINT_CONFIDENCE
    if good.sum() < 4:
        return []
    obj, img = keypoints_base[good].astype(np.float64), view.keypoints[good].astype(np.float64)
    poses = []
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj, img, view.K, None, reprojectionError=PNP_ERROR_FRACTION * view.size[0], flags=cv2.SOLVEPNP_SQPNP
    )
    if ok and inliers is not None and len(inliers) >= 4:
        idx = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], view.K, None, rvec, tvec)
        poses.append(_pose(rvec, tvec))
    subsets = [np.ones(len(obj), bool)]
    if len(obj) > 4:  # each keypoint left out in turn: one wrong keypoint then spoils one subset only
        subsets += [np.arange(len(obj)) != i for i in range(len(obj))]
    for keep in subsets:
        ok, rvec, tvec = cv2.solvePnP(obj[keep], img[keep], view.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            poses.append(_pose(rvec, tvec))
    return [p for p in poses if np.isfinite(p).all() and p[2, 3] > 0.05]


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))


def sphere_hypotheses(view: ViewEvidence, surface_base: np.ndarray) -> list[np.ndarray]:
    """Orientations over the sphere (the camera looking at the robot from azimuths x elevations),
    each placed so the robot's centroid projects to the mask's centroid at the depth where its
    projected extent matches the mask's."""
    ys, xs = np.nonzero((view.mask > MASK_THRESHOLD).numpy())
    centre = np.array([xs.mean(), ys.mean()])
    extent = max(xs.max() - xs.min(), ys.max() - ys.min()) + 1
    centroid = surface_base.mean(0)
    f = (view.K[0, 0] + view.K[1, 1]) / 2
    ray = np.array([(centre[0] - view.K[0, 2]) / view.K[0, 0], (centre[1] - view.K[1, 2]) / view.K[1, 1], 1.0])
    poses = []
    for elevation in SPHERE_ELEVATIONS:
        for i in range(SPHERE_AZIMUTHS):
            az, el = 2 * math.pi * i / SPHERE_AZIMUTHS, math.radians(elevation)
            eye = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            rot = _look_at(eye)
            pts = (surface_base - centroid) @ rot.T
            size = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]))
            depth = f * size / extent
            poses.append(make_pose(rot, ray * depth - rot @ centroid))
    return poses


def _look_at(eye: np.ndarray) -> np.ndarray:
    """Camera-from-world rotation (OpenCV axes) of a camera at ``eye`` looking at the origin, z up."""
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    return np.stack([x, np.cross(z, x), z])


def silhouette_ious(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                    size: tuple[int, int]) -> np.ndarray:  # fmt: skip
    """IoU ``[H]`` of each pose's rendered silhouette with the view's mask, compared at ``size``."""
    K = _scaled_K(view.K, view.size, size)
    n = len(poses)
    K = torch.from_numpy(K)[None].expand(n, 3, 3)
    rendered = renderer.render(np.repeat(joints[None], n, 0), torch.from_numpy(poses), K, size)
    mask = F.interpolate(view.mask[None, None], size=(size[1], size[0]), mode="bilinear", align_corners=False)[0, 0]
    mask = (mask > MASK_THRESHOLD).to(rendered.mask.device)
    inter = (rendered.mask & mask).flatten(1).sum(1).float()
    union = (rendered.mask | mask).flatten(1).sum(1).float().clamp_min(1)
    return (inter / union).cpu().numpy()


def _scaled_K(K: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    sx, sy = new_size[0] / size[0], new_size[1] / size[1]
    out = K.copy()
    out[0, 0], out[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    out[0, 2], out[1, 2] = (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5
    return out


def keypoint_errors(poses: np.ndarray, keypoints_base: np.ndarray, view: ViewEvidence) -> np.ndarray:
    """Confidence-weighted mean reprojection error ``[H]`` (view pixels) of the keypoints at
    each pose, each error capped at :data:`KEYPOINT_ERROR_CAP` of the view's width (a keypoint
    the parser got wrong costs a bounded amount)."""
    cam = np.einsum("hij,kj->hki", poses[:, :3, :3], keypoints_base) + poses[:, None, :3, 3]
    err = np.linalg.norm(project(cam, view.K) - view.keypoints, axis=-1)
    err = np.minimum(err, KEYPOINT_ERROR_CAP * view.size[0])
    return (err * view.confidence).sum(-1) / max(view.confidence.sum(), 1e-6)


def fit_scores(ious: np.ndarray, kp_errors: np.ndarray, view: ViewEvidence) -> np.ndarray:
    return ious - KEYPOINT_PENALTY * np.minimum(kp_errors / view.size[0], 1.0)


class OutlineTargets:
    """For every pixel of a view, the nearest pixel on the outline of the parser's mask."""

    def __init__(self, view: ViewEvidence):
        mask = (view.mask > MASK_THRESHOLD).numpy().astype(np.uint8)
        outline = mask - cv2.erode(mask, np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero(outline)
        self.empty = len(xs) == 0
        if self.empty:
            return
        # distanceTransformWithLabels labels each zero pixel of its input in raster order.
        _, labels = cv2.distanceTransformWithLabels(1 - outline, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        self.nearest = np.stack([xs, ys], -1).astype(np.float64)[labels - 1]  # [h, w, 2]

    def __call__(self, uv: np.ndarray) -> np.ndarray:
        u = np.clip(np.round(uv[:, 0]).astype(int), 0, self.nearest.shape[1] - 1)
        v = np.clip(np.round(uv[:, 1]).astype(int), 0, self.nearest.shape[0] - 1)
        return self.nearest[v, u]


def render_outline(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                   rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """Per pose, up to :data:`OUTLINE_POINTS` outline pixels of its render ``[N, 2]`` and their
    surface points in the base frame ``[N, 3]`` (back-projected through the render's depth)."""
    n = len(poses)
    K = torch.from_numpy(view.K)[None].expand(n, 3, 3)
    rendered = renderer.render(np.repeat(joints[None], n, 0), torch.from_numpy(poses), K, view.size)
    masks = rendered.mask.cpu().numpy().astype(np.uint8)
    depths = rendered.depth.cpu().numpy()
    out = []
    for mask, depth, pose in zip(masks, depths, poses, strict=True):
        ys, xs = np.nonzero(mask - cv2.erode(mask, np.ones((3, 3), np.uint8)))
        if len(xs) > OUTLINE_POINTS:
            pick = rng.choice(len(xs), OUTLINE_POINTS, replace=False)
            xs, ys = xs[pick], ys[pick]
        z = depth[ys, xs].astype(np.float64)
        cam = np.stack([(xs - view.K[0, 2]) / view.K[0, 0] * z, (ys - view.K[1, 2]) / view.K[1, 1] * z, z], -1)
        base = (cam - pose[:3, 3]) @ pose[:3, :3]  # R^T (X - t)
        out.append((np.stack([xs, ys], -1).astype(np.float64), base))
    return out


def refine_poses(renderer: RobotRenderer, joints: np.ndarray, poses: np.ndarray, view: ViewEvidence,
                 keypoints_base: np.ndarray, iterations: int = REFINE_ITERATIONS) -> np.ndarray:  # fmt: skip
    """Silhouette + keypoint refinement of ``poses`` ``[H, 4, 4]`` (see the module's step 4)."""
    targets = OutlineTargets(view)
    rng = np.random.default_rng(0)
    scale = OUTLINE_SCALE * view.size[0]
    for _ in range(iterations):
        points, goals, weights = [], [], []
        cam = np.einsum("hij,kj->hki", poses[:, :3, :3], keypoints_base) + poses[:, None, :3, 3]
        kp_dist = np.linalg.norm(project(cam, view.K) - view.keypoints, axis=-1)
        kp_weights = view.confidence / (1 + (kp_dist / (KEYPOINT_SCALE * view.size[0])) ** 2)
        outlines = render_outline(renderer, joints, poses, view, rng)
        for (uv, base), kp_w in zip(outlines, kp_weights, strict=True):
            if targets.empty or len(uv) == 0:
                w = np.zeros(len(uv))
                goal = uv
            else:
                goal = targets(uv)
                dist = np.linalg.norm(goal - uv, axis=-1)
                w = OUTLINE_WEIGHT / len(uv) / (1 + (dist / scale) ** 2)
            points.append(np.concatenate([keypoints_base, base]))
            goals.append(np.concatenate([view.keypoints, goal]))
            weights.append(np.concatenate([kp_w, w]))
        K = torch.from_numpy(view.K)[None].expand(len(poses), 3, 3)
        new = solve_pose(torch.from_numpy(poses), K, _stack_padded(points), _stack_padded(goals),
                         _stack_padded(weights), iterations=2).numpy()  # fmt: skip
        moved_mm = 1000 * np.linalg.norm(new[:, :3, 3] - poses[:, :3, 3], axis=-1).max()
        moved_deg = np.degrees(rotation_angle(new[:, :3, :3], poses[:, :3, :3])).max()
        poses = new
        if moved_mm < CONVERGED_MM and moved_deg < CONVERGED_DEG:
            break
    return poses


def pose_in_view(robot: RobotModel, pose: np.ndarray, joints: np.ndarray, K: np.ndarray, image_shape) -> bool:
    """Whether ``pose`` puts the robot's centroid in front of the camera and inside the image."""
    if not np.isfinite(pose).all():
        return False
    centroid = robot.centroid(robot.surface_points(joints[None]))[0]
    cam = pose[:3, :3] @ centroid + pose[:3, 3]
    if cam[2] <= 0:
        return False
    u, v = project(cam[None], K)[0]
    h, w = image_shape[:2]
    return bool(-0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5)


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
    refine: bool = True,
) -> Fit:
    """The module's stages on one image (``[H, W, 3]`` uint8 RGB, its K, the joints)."""
    size = parser.config.input_size
    aspect = size[0] / size[1]
    tensor = image_tensor(image)
    view = parse_view(parser, tensor, K, full_box((image.shape[1], image.shape[0]), aspect))
    if view.robot_fraction < MIN_MASK_FRACTION:
        return not_found(view)
    box = zoom_box(view, aspect)
    if box is not None:
        view = parse_view(parser, tensor, K, box)
    kp_base = robot.keypoints(joints[None])[0]
    hyps = pnp_hypotheses(view, kp_base)
    if extra_poses is not None:
        hyps += list(extra_poses)
    hyps += sphere_hypotheses(view, robot.surface_points(joints[None])[0])
    poses = np.stack(hyps)
    ious = silhouette_ious(renderer, joints, poses, view, SCORE_SIZE)
    scores = fit_scores(ious, keypoint_errors(poses, kp_base, view), view)
    poses = poses[np.argsort(-scores)[:KEEP_HYPOTHESES]]
    if refine:
        poses = refine_poses(renderer, joints, poses, view, kp_base)
    ious = silhouette_ious(renderer, joints, poses, view, view.size)
    errors = keypoint_errors(poses, kp_base, view)
    scores = fit_scores(ious, errors, view)
    order = np.argsort(-scores)
    best = order[0]
    return Fit(poses[best], float(ious[best]), float(errors[best]), float(scores[best]), view, poses[order])


def not_found(view: ViewEvidence) -> Fit:
    return Fit(np.full((4, 4), np.nan), 0.0, math.inf, -math.inf, view, np.zeros((0, 4, 4)), found=False)


def track_pose(
    parser: RobotParser,
    renderer: RobotRenderer,
    robot: RobotModel,
    image: np.ndarray,
    K: np.ndarray,
    joints: np.ndarray,
    previous: np.ndarray,
) -> Fit:
    """Tracking: :data:`TRACK_ITERATIONS` refinement iterations from the previous pose, in one
    parser view around where that pose puts the robot's surface."""
    size = parser.config.input_size
    aspect = size[0] / size[1]
    whole = full_box((image.shape[1], image.shape[0]), aspect)
    surface = robot.surface_points(joints[None])[0]
    uv = project(surface @ previous[:3, :3].T + previous[:3, 3], K)
    box = box_around(uv.min(0), uv.max(0), aspect) if np.isfinite(uv).all() else whole
    if box[2] - box[0] > whole[2] - whole[0]:
        box = whole
    view = parse_view(parser, image_tensor(image), K, box)
    if view.robot_fraction < MIN_MASK_FRACTION:
        return not_found(view)
    kp_base = robot.keypoints(joints[None])[0]
    poses = refine_poses(renderer, joints, previous[None], view, kp_base, TRACK_ITERATIONS)
    iou = silhouette_ious(renderer, joints, poses, view, view.size)
    error = keypoint_errors(poses, kp_base, view)
    score = fit_scores(iou, error, view)
    return Fit(poses[0], float(iou[0]), float(error[0]), float(score[0]), view, poses)
