"""The robot parser (pretrained trunk, heads, losses, training data) and the geometric fit."""

import json

import cv2
import numpy as np
import pytest
import torch

import monose3
from monose3.apps.cli import main
from monose3.errors import Monose3Error
from monose3.geometry.camera import project
from monose3.geometry.poses import make_pose, transform_points
from monose3.geometry.rotations import axis_angle_to_matrix
from monose3.networks.backbone import FEATURE_CHANNELS, pretrained_lite0
from monose3.perception.config import ParserConfig
from monose3.perception.edges import edge_terms, find_edges, inner_edge_support, inner_edge_terms
from monose3.perception.fit_result import Fit
from monose3.perception.fitting import (
    best_fit,
    depth_restarts,
    distinct_poses,
    fit_pose,
    not_found,
    refine_coarse_to_fine,
    restarted_fit,
)
from monose3.perception.from_pose import TRACK_ITERATIONS, refine_from, track_pose, view_around
from monose3.perception.hypotheses import pnp_hypotheses, sphere_hypotheses
from monose3.perception.parser import decode_keypoints, keypoint_loss, mask_loss, pixel_to_cell
from monose3.perception.reliability import (
    FLAG_MODEL,
    FLAG_MODEL_WITHOUT_INNER,
    MAX_DEPTH_PER_PIXEL_MM,
    SECOND_LOOK_LIMITS,
    depth_per_pixel_mm,
    fit_doubts,
    fit_numbers,
    fit_reasons,
)
from monose3.perception.silhouette import Outline
from monose3.perception.views import (
    CONTEXT_SCALES,
    MIN_MASK_FRACTION,
    ViewEvidence,
    full_box,
    grown_box,
    image_tensor,
    logits_within,
    parse_image,
    parse_view,
)
from monose3.training.checkpoints import load_parser
from monose3.training.formats import BUNDLED_PARSER

SAMPLE = monose3.ASSETS / "sample"


@pytest.fixture(scope="module")
def sample():
    return monose3.load_image(SAMPLE / "image.jpg"), monose3.load_camera(SAMPLE / "camera.json").K


@pytest.fixture(scope="module")
def parser():
    return load_parser(BUNDLED_PARSER)


def _add(robot, joints, a, b) -> float:
    ka, kb = robot.keypoints(joints[None], a[None])[0], robot.keypoints(joints[None], b[None])[0]
    return float(np.linalg.norm(ka - kb, axis=1).mean())


def _moved(pose, deg, cm, seed=0):
    rng = np.random.default_rng(seed)
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    rot = axis_angle_to_matrix(axis / np.linalg.norm(axis), np.radians(deg)) @ pose[:3, :3]
    return make_pose(rot, pose[:3, 3] + shift / np.linalg.norm(shift) * cm / 100)


# ---- the network ----------------------------------------------------------------------------------


def test_pretrained_trunk_loads_strictly_and_gives_a_feature_pyramid():
    net = pretrained_lite0().eval()
    with torch.no_grad():
        feats = net.features(torch.rand(1, 3, 96, 128))
        logits = net(torch.rand(1, 3, 96, 128))
    assert [f.shape[1] for f in feats] == list(FEATURE_CHANNELS)
    assert [f.shape[-1] for f in feats] == [64, 32, 16, 8, 4] and logits.shape == (1, 1000)
    # ImageNet statistics, not an initialisation: the stem's batch norm has learnt running means.
    assert net._bn0.running_mean.abs().sum() > 1.0


def test_decode_keypoints_finds_a_sub_cell_peak():
    h, w = 30, 40
    ys, xs = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    cell = torch.tensor([12.3, 7.6])
    logits = -((xs - cell[0]) ** 2 + (ys - cell[1]) ** 2) / (2 * 0.8**2)
    uv, conf = decode_keypoints(logits[None, None])
    assert torch.allclose(pixel_to_cell(uv[0, 0]), cell, atol=0.1) and conf.item() > 0.9


def test_keypoint_loss_is_lowest_at_the_keypoint_and_skips_those_outside():
    h, w = 30, 40
    logits = torch.zeros(1, 2, h, w)
    logits[0, 0, 10, 20] = 8.0
    at = torch.tensor([[[41.0, 21.0], [-50.0, 5.0]]])  # the second keypoint lies outside the image
    away = torch.tensor([[[11.0, 41.0], [-50.0, 5.0]]])
    assert keypoint_loss(logits, at, 1.0) < keypoint_loss(logits, away, 1.0)
    assert torch.isfinite(keypoint_loss(logits, torch.full((1, 2, 2), -100.0), 1.0))


def test_mask_loss_prefers_the_right_mask():
    target = torch.zeros(1, 1, 8, 8)
    target[..., 2:5, 3:6] = 1
    assert mask_loss(target * 20 - 10, target) < mask_loss(10 - target * 20, target)


def test_outline_nearest_matches_brute_force():
    mask = np.zeros((40, 50), bool)
    mask[10:25, 12:30] = True
    outline = Outline(mask)
    uv = np.random.default_rng(0).uniform(0, 49, (30, 2))
    found = outline.pixels[outline.nearest(np.round(uv))]
    brute = np.linalg.norm(outline.pixels[None] - np.round(uv)[:, None], axis=-1).min(1)
    assert np.allclose(np.linalg.norm(found - np.round(uv), axis=-1), brute, atol=0.5)


def test_valid_region_is_where_the_view_shows_the_image():
    view = ViewEvidence(torch.zeros(150, 200), np.zeros((7, 2)), np.ones(7), np.eye(3), np.array([-50.0, 0, 150, 150]),
                        image_size=(100, 80))  # fmt: skip
    assert view.valid == (50, 0, 150, 80)
    assert view.valid_region((100, 75)) == (25, 0, 75, 40)
    assert ViewEvidence(torch.zeros(4, 4), np.zeros((7, 2)), np.ones(7), np.eye(3), np.zeros(4)).valid == (0, 0, 4, 4)


def test_the_image_border_is_no_outline():
    mask = np.zeros((40, 50), bool)
    mask[10:25, 12:30] = True
    cut = Outline(mask, valid=(0, 0, 20, 40))  # the image ends at column 20, inside the mask
    right = cut.pixels[cut.pixels[:, 0] == 19]  # the last column inside: the square's top and bottom only
    assert len(cut) and cut.pixels[:, 0].max() == 19 and set(right[:, 1]) == {10, 24}
    assert len(cut) < len(Outline(mask))


# ---- image edges ----------------------------------------------------------------------------------


def test_find_edges_finds_a_blurred_step_to_a_tenth_of_a_pixel():
    x = np.arange(64, dtype=np.float32)
    step_at = 30.3  # the grey level changes between pixel centres 30 and 31, a third of the way
    row = 0.2 + 0.6 / (1 + np.exp(-(x - step_at) / 0.6))
    image = np.repeat(np.repeat(row[None, :, None], 16, 0), 3, 2)
    pixels = np.array([[28.6, 8.0], [31.9, 8.0]])  # the search starts 1.7 and 1.6 pixels away
    offsets, strength = find_edges(image, pixels, np.array([[1.0, 0.0], [1.0, 0.0]]))
    assert np.allclose(pixels[:, 0] + offsets, step_at, atol=0.1) and (strength > 0.3).all()


def test_a_flat_image_has_no_edges_to_pull_to():
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    depth = np.where(mask, 1.0, 0.0)
    K = np.array([[50.0, 0, 20], [0, 50.0, 20], [0, 0, 1]])
    image = np.full((40, 40, 3), 0.5, np.float32)
    _, _, weights = edge_terms(image, mask, depth, np.eye(4), K, 100.0, np.random.default_rng(0))
    assert len(weights) and not weights.any()
    image[mask] = 0.9
    _, goals, weights = edge_terms(image, mask, depth, np.eye(4), K, 100.0, np.random.default_rng(0))
    assert weights.sum() > 50  # a contrasted square: its outline is where the image's edges are
    assert np.abs(goals - np.clip(goals, 10, 29)).max() < 0.1  # the centres of its outline pixels


def test_inner_edges_pull_by_how_far_the_images_edge_lies_from_the_renders():
    """A robot half white, half black: the colour boundary inside the silhouette is pulled to
    where the image shows it (2 px to the right), not to the image's nearest edge."""
    mask = np.zeros((40, 60), bool)
    mask[8:32, 10:50] = True
    depth = np.where(mask, 1.0, 0.0)
    colors = np.zeros((40, 60, 3), np.float32)
    colors[mask] = 1.0
    colors[:, 30:][mask[:, 30:]] = 0.1  # the render's boundary: between pixels 29 and 30
    K = np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]])
    image = np.full((40, 60, 3), 0.5, np.float32)
    image[8:32, 10:32], image[8:32, 32:50] = 0.9, 0.2  # the image's: between 31 and 32
    points, goals, weights = inner_edge_terms(image, colors, depth, mask, np.eye(4), K, 100.0, np.random.default_rng(0))
    pixels = points[:, :2] / points[:, 2:] * 50 + [30, 20]  # each term's pixel, back-projected and projected again
    assert len(weights) and np.allclose(weights.sum(), 100 / (1 + (2 / 1.5) ** 2))  # a 2 px pull, Cauchy scale 1.5 px
    assert np.allclose(goals[:, 0] - pixels[:, 0], 2.0, atol=0.1) and np.allclose(goals[:, 1], pixels[:, 1])
    assert (np.abs(pixels[:, 0] - 29.5) < 1.5).all()  # the boundary's pixels, not the outline's
    off_view = inner_edge_terms(
        image, colors, depth, mask, np.eye(4), K, 100.0, np.random.default_rng(0), (52, 0, 60, 40)
    )
    assert not len(off_view[2])  # the robot outside the image's part of the view: no terms, no error
    image[8:32, 10:50] = 0.5  # no edge inside the robot in the image: nothing to pull to
    assert not inner_edge_terms(image, colors, depth, mask, np.eye(4), K, 100.0, np.random.default_rng(0))[2].any()


def test_inner_edge_support_is_one_where_the_image_shows_the_renders_inner_edges_and_less_off_them():
    mask = np.zeros((40, 60), bool)
    mask[8:32, 10:50] = True
    depth = np.where(mask, 1.0, 0.0)
    colors = np.where(mask[..., None], 1.0, 0.0).astype(np.float32)
    colors[:, 30:][mask[:, 30:]] = 0.1  # the render's inner edge: between pixels 29 and 30
    image = np.full((40, 60, 3), 0.5, np.float32)
    image[8:32, 10:30], image[8:32, 30:50] = 0.9, 0.2  # the image's, where the render's is
    assert inner_edge_support(image, colors, depth, mask) == pytest.approx(1.0)
    image[8:32, 30:32] = 0.9  # 2 px off: a Cauchy weight of scale 1.5 px
    assert inner_edge_support(image, colors, depth, mask) == pytest.approx(1 / (1 + (2 / 1.5) ** 2), abs=0.02)
    image[8:32, 10:50] = 0.5
    assert inner_edge_support(image, colors, depth, mask) == 0.0
    assert inner_edge_support(image, colors, depth, np.zeros_like(mask)) == 0.0  # nothing rendered


# ---- the fit ---------------------------------------------------------------------------------------


def _perfect_view(models, renderers, joints, pose, K, size=(320, 240)) -> ViewEvidence:
    """What a perfect parser would report: the rendered mask and the projected keypoints, with
    the render over a grey background as the view's pixels."""
    rendered = renderers["panda"].render(joints[None], torch.from_numpy(pose)[None], torch.from_numpy(K)[None], size)
    cam = models["panda"].keypoints(joints[None], pose[None])[0]
    uv = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    box = np.array([0.0, 0.0, *size])
    mask = rendered.mask[0]
    image = torch.where(mask[None], rendered.rgb[0], 0.4).permute(1, 2, 0).numpy().astype(np.float32)
    return ViewEvidence(mask.float(), uv, np.ones(len(uv)), K, box, image)


def test_refinement_recovers_the_pose_from_perfect_evidence(models, renderers, sample_view):
    view = sample_view(models["panda"], np.random.default_rng(3), size=(320, 240), dist=(1.0, 1.8))
    evidence = _perfect_view(models, renderers, view.joints, view.pose, view.K)
    start = _moved(view.pose, 5, 3)
    kp = models["panda"].keypoints(view.joints[None])[0]
    refined = refine_coarse_to_fine(renderers["panda"], view.joints, start[None], evidence, kp)[0]
    robot = models["panda"]
    assert _add(robot, view.joints, start, view.pose) > 0.02
    assert _add(robot, view.joints, refined, view.pose) < 0.002


def test_refinement_ignores_what_the_image_border_cuts(models, renderers, sample_view):
    """The view's right third lies beyond the image (padding: no mask, no pixels): the robot the
    border cuts is fitted on what the image shows, not pulled to make its silhouette end there."""
    view = sample_view(models["panda"], np.random.default_rng(3), size=(320, 240), dist=(1.0, 1.8))
    evidence = _perfect_view(models, renderers, view.joints, view.pose, view.K)
    width = int(np.nonzero(evidence.mask.numpy().any(0))[0].mean())  # the border through the robot
    evidence.mask[:, width:] = 0
    evidence.image[:, width:] = 0
    evidence.image_size = (width, 240)
    kp = models["panda"].keypoints(view.joints[None])[0]
    evidence.confidence[evidence.keypoints[:, 0] >= width] = 0  # the parser cannot see those keypoints
    start = _moved(view.pose, 5, 3)
    refined = refine_coarse_to_fine(renderers["panda"], view.joints, start[None], evidence, kp)[0]
    assert _add(models["panda"], view.joints, refined, view.pose) < 0.015  # 180 mm when the border is an outline


def test_the_mirrored_view_gives_the_mirrored_mask(parser, sample):
    """The mask is the mean of the view's and its mirror's, so the parser's view of a mirrored
    image is the mirror image of its view of the original (without the mean it is not)."""
    image, K = sample
    w = image.shape[1]
    box = np.array([40.0, 20.0, 40.0 + 0.8 * w, 20.0 + 0.6 * w])
    mirrored_box = np.array([w - box[2], box[1], w - box[0], box[3]])
    original, mirrored = image_tensor(image), image_tensor(np.ascontiguousarray(image[:, ::-1]))

    def mismatch(mirror: bool, context: tuple[float, ...] = ()) -> float:
        a = parse_view(parser, original, K, box, mirror, context).mask
        b = parse_view(parser, mirrored, K, mirrored_box, mirror, context).mask.flip(-1)
        return float((a - b).abs().max())

    assert mismatch(True) < 1e-4
    assert mismatch(True, CONTEXT_SCALES) < 1e-4  # the wider boxes share the view's centre
    assert mismatch(False) > 0.05


def test_logits_over_a_wider_box_are_resampled_onto_the_box():
    """A mask's logits that rise with the image's x over a box twice as wide, resampled onto the
    inner box's view grid, give at each view pixel the x of that pixel's centre in the image."""
    box = np.array([100.0, 50.0, 180.0, 110.0])
    wide = grown_box(box, 2.0)
    np.testing.assert_allclose(wide, [60.0, 20.0, 220.0, 140.0])
    w, h = 40, 30  # the wide box's logits grid: 4 image pixels per cell
    x_centres = wide[0] + (np.arange(w) + 0.5) * (wide[2] - wide[0]) / w
    logits = torch.from_numpy(np.tile(x_centres, (h, 1)))[None, None].float()
    resampled = logits_within(logits, wide, box, (16, 12))[0, 0].numpy()
    expected = box[0] + (np.arange(16) + 0.5) * (box[2] - box[0]) / 16
    np.testing.assert_allclose(resampled, np.tile(expected, (12, 1)), atol=1e-3)


def test_a_small_robot_is_parsed_in_a_view_zoomed_on_it(parser, sample):
    """The sample placed in the middle of a grey image three times as large: the robot is found
    in the whole image, then parsed again in a box around it, not in the whole image."""
    image, K = sample
    h, w = image.shape[:2]
    canvas = np.full((3 * h, 3 * w, 3), 127, np.uint8)
    canvas[h : 2 * h, w : 2 * w] = image
    K_canvas = K.copy()
    K_canvas[:2, 2] += [w, h]
    view = parse_image(parser, canvas, K_canvas)
    assert view.robot_fraction >= MIN_MASK_FRACTION
    whole = full_box((3 * w, 3 * h), view.size[0] / view.size[1])
    assert view.box[2] - view.box[0] < 0.5 * (whole[2] - whole[0])
    assert view.box[0] < 2 * w and view.box[2] > w and view.box[1] < 2 * h and view.box[3] > h


def test_an_image_without_a_robot_is_parsed_whole(parser):
    view = parse_image(
        parser, np.full((240, 320, 3), 127, np.uint8), np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    )
    assert view.robot_fraction < MIN_MASK_FRACTION
    np.testing.assert_allclose(view.box, full_box((320, 240), view.size[0] / view.size[1]))


def test_fit_pose_on_the_bundled_sample(parser, renderers, models, sample):
    image, K = sample
    joints = monose3.load_joints(SAMPLE / "joints.json", models["panda"])
    fit = fit_pose(parser, renderers["panda"], models["panda"], image, K, joints)
    assert fit.found and fit.iou > 0.9 and set(fit.timings) == {"parse", "search", "refine", "restart"}
    assert 0.5 < fit.edge_support <= 1 and 0 < fit.edge_distance_px < 0.8 and 0 <= fit.spread_mm < 5
    tracked = track_pose(parser, renderers["panda"], models["panda"], image, K, joints, _moved(fit.pose, 3, 2))
    assert _add(models["panda"], joints, tracked.pose, fit.pose) < 0.01
    refined = refine_from(parser, renderers["panda"], models["panda"], image, K, joints, _moved(fit.pose, 5, 3))
    assert _add(models["panda"], joints, refined.pose, fit.pose) < 0.005 and len(refined.candidates) == 2


@pytest.mark.slow
def test_a_doubtful_fit_takes_a_second_look_and_keeps_the_better(parser, renderers, models, sample):
    """Blurred, the sample's outline finds no sharp edges: the fit is doubted, so the dense
    sphere is fitted too, and the better scoring of the two fits is the result."""
    image, K = sample
    blurred = cv2.GaussianBlur(image, (0, 0), 4)
    joints = monose3.load_joints(SAMPLE / "joints.json", models["panda"])
    args = (parser, renderers["panda"], models["panda"], blurred, K, joints)
    first = fit_pose(*args, second_look=False)
    assert fit_reasons(first) and "second look" not in first.timings
    fit = fit_pose(*args)
    assert "second look" in fit.timings and fit.score >= first.score


def test_distinct_poses_keep_the_best_of_each_cluster():
    base = np.array([[0.0, 0, 0], [0, 0, 0.5], [0.3, 0, 0.8]])
    pose = make_pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    shifted = lambda mm: make_pose(np.eye(3), pose[:3, 3] + [mm / 1000, 0, 0])  # noqa: E731
    poses = np.stack([pose, shifted(1.0), shifted(10.0), shifted(2.0)])
    kept = distinct_poses(poses, np.array([0.5, 0.9, 0.7, 0.1]), base, min_mm=3.0)
    np.testing.assert_allclose(kept, poses[[1, 2]])  # 1 mm beats 0 and 2 mm (within 3 mm of it), 10 mm stays
    np.testing.assert_allclose(distinct_poses(poses, np.zeros(4), base, min_mm=0.5), poses)


def test_sphere_poses_facing_the_robot_see_it_along_its_ray():
    """An off-centre mask: both kinds of sphere pose put the robot's centroid on the mask's
    centroid, and a facing pose sees it from its (azimuth, elevation) along the ray, as the
    plain pose sees it along the optical axis (the same direction in the robot's frame)."""
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    mask = torch.zeros(240, 320)
    mask[20:80, 220:300] = 1  # up and right of the centre
    view = ViewEvidence(mask, np.zeros((0, 2)), np.zeros(0), K, np.array([0.0, 0, 320, 240]))
    surface = np.random.default_rng(0).uniform([-0.2, -0.2, 0.0], [0.2, 0.2, 1.0], (500, 3))
    centroid = surface.mean(0)
    plain = np.stack(sphere_hypotheses(view, surface, 6, (0.0, 40.0)))
    facing = np.stack(sphere_hypotheses(view, surface, 6, (0.0, 40.0), facing=True))
    for poses in (plain, facing):
        np.testing.assert_allclose(project(transform_points(poses, centroid[None])[:, 0], K), [[259.5, 49.5]] * 12,
                                   atol=1e-6)  # fmt: skip
    ray = transform_points(facing, centroid[None])[:, 0]
    seen_along = np.einsum("nji,nj->ni", facing[:, :3, :3], ray / np.linalg.norm(ray, axis=1, keepdims=True))
    np.testing.assert_allclose(seen_along, plain[:, 2, :3], atol=1e-9)  # the optical axis in the robot's frame
    assert not np.allclose(facing[:, :3, :3], plain[:, :3, :3])


def test_the_restarts_start_either_side_along_the_line_of_sight():
    axis = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    pose = make_pose(axis_angle_to_matrix(axis, 0.8), np.array([0.2, -0.1, 2.0]))
    pivot, K = np.array([0.1, 0.0, 0.5]), np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    starts = depth_restarts(pose, pivot, 0.02)
    cam = starts[:, :3, :3] @ pivot + starts[:, :3, 3]
    original = pose[:3, :3] @ pivot + pose[:3, 3]
    np.testing.assert_allclose(cam[:, 2] / original[2], [0.98, 1.02])
    np.testing.assert_allclose(project(cam, K), np.repeat(project(original[None], K), 2, 0), atol=1e-9)
    np.testing.assert_array_equal(starts[:, :3, :3], np.stack([pose[:3, :3]] * 2))


def test_restarts_from_a_fit_off_in_depth_end_on_the_fit(parser, renderers, models, sample):
    """From the fit moved DEPTH_RESTART of its distance further (over 2 cm off), the restarts
    start on the fit and twice as far off: both end on the fit, close together."""
    image, K = sample
    robot, joints = models["panda"], monose3.load_joints(SAMPLE / "joints.json", models["panda"])
    fit = fit_pose(parser, renderers["panda"], robot, image, K, joints)
    pivot = robot.centroid(robot.surface_points(joints[None])[0])
    further = depth_restarts(fit.pose, pivot)[1]
    assert _add(robot, joints, further, fit.pose) > 0.02
    kp = robot.keypoints(joints[None])[0]
    restarted = restarted_fit(renderers["panda"], joints, further[None], fit.view, kp, pivot)
    assert len(restarted.candidates) == 2 and restarted.spread_mm < 5
    assert _add(robot, joints, restarted.pose, fit.pose) < 0.003


def test_a_lost_track_is_found_again(parser, renderers, models, sample):
    """From a previous pose 30 deg / 15 cm off, the refinement alone ends far away with a poor
    fit; tracking starts from the view's PnP hypothesis instead, which scores better, and ends on the fit."""
    image, K = sample
    joints = monose3.load_joints(SAMPLE / "joints.json", models["panda"])
    args = (parser, renderers["panda"], models["panda"], image, K, joints)
    fit = fit_pose(*args)
    start = _moved(fit.pose, 30, 15)
    found = track_pose(*args, start)
    assert _add(models["panda"], joints, found.pose, fit.pose) < 0.01
    # ... and the flag doubts it for the jump from the previous pose (a track that slips jumps too):
    # the tracker then judges it beside the previous pose (tracking.Tracker).
    numbers = fit_numbers(found, models["panda"], joints, K, image.shape)
    assert found.tracked and numbers["spread"] > 100
    assert FLAG_MODEL_WITHOUT_INNER.odds(numbers) > 2 * FLAG_MODEL_WITHOUT_INNER.odds({**numbers, "spread": 0.0})
    view = view_around(parser, models["panda"], image, K, joints, start)
    kp = models["panda"].keypoints(joints[None])[0]
    alone = refine_coarse_to_fine(renderers["panda"], joints, start[None], view, kp, *TRACK_ITERATIONS)
    lost = best_fit(renderers["panda"], joints, alone, view, kp)
    assert _add(models["panda"], joints, lost.pose, fit.pose) > 0.1
    assert fit_doubts(lost, models["panda"], joints, K, image.shape)


def test_no_robot_in_the_image_is_not_a_pose(sample, tmp_path, capsys):
    image, K = sample
    empty = np.clip(image.astype(float).mean((0, 1)) + np.zeros_like(image, float), 0, 255).astype(np.uint8)
    empty[::7] = 30  # stripes, so the image is not refused as uniform
    estimator = monose3.load_estimator()
    joints = monose3.load_joints(SAMPLE / "joints.json", estimator.robot)
    with pytest.raises(Monose3Error, match="robot was not found"):
        monose3.estimate_pose(estimator, empty, joints, K)
    monose3.save_image(tmp_path / "empty.png", empty)
    argv = ["estimate", "--image", str(tmp_path / "empty.png"), "--joints", str(SAMPLE / "joints.json")]
    assert main([*argv, "--camera", str(SAMPLE / "camera.json"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "robot was not found" in err[0]
    assert not (tmp_path / "o" / "pose.json").exists()


def test_robot_mostly_outside_the_image_is_flagged_unreliable(sample):
    """A 120 x 90 window around the principal point: most of the sample's robot lies outside it."""
    image, K = sample
    x0, y0 = int(K[0, 2]) - 60, int(K[1, 2]) - 45
    window = np.ascontiguousarray(image[y0 : y0 + 90, x0 : x0 + 120])
    K_window = K.copy()
    K_window[:2, 2] -= [x0, y0]
    estimator = monose3.load_estimator()
    joints = monose3.load_joints(SAMPLE / "joints.json", estimator.robot)
    try:
        result = monose3.estimate_pose(estimator, window, joints, K_window)
    except Monose3Error as err:  # also acceptable: refused as not found or out of view, never a crash
        assert "not found" in str(err) or "outside the image" in str(err)
        return
    assert result.reliable is False and result.doubts
    assert "UNRELIABLE: " + result.doubts[0] in result.overlay_label


def test_a_good_fit_is_reliable_and_says_what_it_read(sample):
    """The bundled sample through the API: reliable, no doubts, the edge support in pose.json."""
    image, K = sample
    estimator = monose3.load_estimator()
    try:
        joints = monose3.load_joints(SAMPLE / "joints.json", estimator.robot)
        result = monose3.estimate_pose(estimator, image, joints, K)
    finally:
        estimator.close()
    data = result.to_dict()
    assert result.reliable and result.doubts == [] and data["doubts"] == []
    assert 0.5 < data["edge_support"] <= 1 and 0 < data["edge_distance_px"] < 0.8
    assert result.overlay_label == result.confidence_text


def test_the_second_look_is_triggered_by_each_number_past_its_limit(sample):
    view = ViewEvidence(torch.zeros(4, 4), np.zeros((7, 2)), np.ones(7), sample[1], np.array([0.0, 0, 4, 4]))
    fit = Fit(np.eye(4), 0.95, 1.0, 0.9, view, np.eye(4)[None], edge_support=0.8, edge_distance_px=0.5)
    assert fit_reasons(fit) == []
    doubted = Fit(np.eye(4), 0.45, 1.0, 0.4, view, np.eye(4)[None], edge_support=0.1, edge_distance_px=1.3,
                  spread_mm=45.0)  # fmt: skip
    reasons = fit_reasons(doubted, SECOND_LOOK_LIMITS)
    assert len(reasons) == 4 and "IoU 0.45 < 0.5" in reasons[0] and "1.30 px off the image's edges" in reasons[1]
    assert reasons[2] == "10 % of the outline on the image's edges < 20 %"
    assert reasons[3] == f"restarts in depth ended 45 mm apart > {SECOND_LOOK_LIMITS.spread_mm:g} mm"
    no_edges = Fit(np.eye(4), 0.95, 1.0, 0.9, view, np.eye(4)[None])  # a flat image: nothing confirms the outline
    assert fit_reasons(no_edges) == ["no image edge along the outline"]
    assert fit_reasons(not_found(view)) == ["the robot was not found"]


def _numbers(**changed: float) -> dict[str, float]:
    """A good fit's numbers (the flag model's typical ones), some changed."""
    return {**FLAG_MODEL.typical, **changed}


def test_the_flag_weighs_the_fits_numbers_together():
    """A typical good fit is trusted; one number far off raises the odds past the flag's, and the
    words name it; two numbers each a little off, that alone are outweighed by the good others,
    are doubted together."""
    assert not FLAG_MODEL.doubted(_numbers()) and FLAG_MODEL.causes(_numbers()) == []
    for name, value in (("edge_distance", 2.0), ("spread", 300.0)):
        assert FLAG_MODEL.doubted(_numbers(**{name: value})) and FLAG_MODEL.causes(_numbers(**{name: value}))[0] == name
    assert not FLAG_MODEL.doubted(_numbers(inner_support=0.3)) and not FLAG_MODEL.doubted(_numbers(edge_distance=1.0))
    assert FLAG_MODEL.doubted(_numbers(inner_support=0.3, edge_distance=1.0))
    many = {k: np.array([v, v, v]) for k, v in _numbers().items()}
    many["edge_distance"], many["iou"] = np.array([0.5, 2.0, 0.5]), np.array([0.9, 0.9, 0.4])
    assert FLAG_MODEL.doubted(many).tolist() == [False, True, True]  # elementwise; an IoU of 0.4 is a sure doubt


def test_fit_doubts_say_why_in_words(panda, sample):
    """The model's odds with the numbers that raised them most; the sure doubts in their own words;
    a fit without the inner edges' support judged by the model fitted without it."""
    joints, K = np.zeros(len(panda.joint_names)), sample[1]
    view = ViewEvidence(torch.zeros(4, 4), np.zeros((7, 2)), np.ones(7), K, np.array([0.0, 0, 4, 4]))
    centre = panda.centroid(panda.surface_points(joints[None])[0])
    pose = make_pose(np.eye(3), np.array([0.0, 0.0, 1.5]) - centre)
    good = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8, edge_distance_px=0.5)
    assert fit_doubts(good, panda, joints, K, (480, 640)) == []
    off = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8, edge_distance_px=2.5)
    [reason] = fit_doubts(off, panda, joints, K, (480, 640))
    assert "odds of an error over 30 mm" in reason
    assert reason.endswith("mostly for its outline 2.50 px off the image's edges")
    inner = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8, edge_distance_px=1.0, inner_support=0.2)
    [reason] = fit_doubts(inner, panda, joints, K, (480, 640))
    assert "inner edges 20 % on the image's edges" in reason
    # a fit that did not measure its inner edges (tracking's) is judged by the model without them
    unmeasured = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8, edge_distance_px=1.0)
    assert fit_doubts(unmeasured, panda, joints, K, (480, 640)) == []
    flat = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8)
    assert fit_doubts(flat, panda, joints, K, (480, 640))[0] == "no image edge along the outline"
    assert fit_doubts(not_found(view), panda, joints, K, (480, 640)) == ["the robot was not found"]


def test_the_depth_per_pixel_is_the_depth_that_changes_the_robots_image_size_by_a_pixel(panda, sample):
    """Moved along the line of sight by what ``depth_per_pixel_mm`` says, the robot's extent in
    the image changes by one pixel; twice as far, a pixel is four times the depth."""
    joints = np.zeros(len(panda.joint_names))
    K = sample[1]
    surface = panda.surface_points(joints[None])[0]
    side_on = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the robot upright in the image, seen from the side
    pose = make_pose(side_on, np.array([0.0, 0.0, 2.0]) - side_on @ panda.centroid(surface))
    extent = lambda p: np.ptp(project(transform_points(p, surface), K), axis=0).max()  # noqa: E731
    step_mm = depth_per_pixel_mm(panda, pose, joints, K)
    nearer = pose.copy()
    nearer[2, 3] -= step_mm / 1000
    assert extent(nearer) - extent(pose) == pytest.approx(1.0, rel=0.05)  # to first order: the robot has depth too
    further = pose.copy()
    further[2, 3] += 2.0
    assert depth_per_pixel_mm(panda, further, joints, K) == pytest.approx(4 * step_mm, rel=0.05)
    assert depth_per_pixel_mm(panda, np.full((4, 4), np.nan), joints, K) == np.inf


def test_a_robot_too_small_for_its_distance_is_doubted(panda, sample):
    """Far enough that a pixel of its size is more depth than the flag allows, a fit that is otherwise
    good is doubted, with the reason in words; near, it is not."""
    joints, K = np.zeros(len(panda.joint_names)), sample[1]
    view = ViewEvidence(torch.zeros(4, 4), np.zeros((7, 2)), np.ones(7), K, np.array([0.0, 0, 4, 4]))
    centre = panda.centroid(panda.surface_points(joints[None])[0])
    for z, doubted in ((1.5, False), (7.0, True)):
        pose = make_pose(np.eye(3), np.array([0.0, 0.0, z]) - centre)
        fit = Fit(pose, 0.95, 1.0, 0.9, view, pose[None], edge_support=0.8, edge_distance_px=0.5)
        reasons = fit_doubts(fit, panda, joints, K, (480, 640))
        assert bool(reasons) == doubted
        if doubted:
            depth_mm = depth_per_pixel_mm(panda, pose, joints, K)
            assert reasons == [f"a pixel of the robot's size in the image is {depth_mm:.0f} mm of depth > "
                               f"{MAX_DEPTH_PER_PIXEL_MM:g} mm: "
                               "too small to fix its distance"]  # fmt: skip


def test_missing_or_corrupt_parser_weights_are_named(tmp_path, capsys):
    bad = tmp_path / "parser.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(Monose3Error, match="parser.pt"):
        load_parser(bad)
    argv = ["estimate", "--image", str(SAMPLE / "image.jpg"), "--joints", str(SAMPLE / "joints.json")]
    argv += ["--camera", str(SAMPLE / "camera.json"), "--out", str(tmp_path / "o")]
    assert main([*argv, "--parser", str(tmp_path / "nope.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.pt" in err[0]
    assert main([*argv, "--parser", str(bad)]) == 2
    assert "parser.pt" in capsys.readouterr().err


def test_a_parser_config_round_trips_through_its_dictionary():
    from dataclasses import asdict

    from monose3.perception.config import parser_config

    config = ParserConfig(input_size=(256, 192), decoder_width=32)
    assert parser_config(json.loads(json.dumps(asdict(config)))) == config


def test_keypoints_clustered_in_a_few_pixels_give_no_pnp_pose_and_no_crash():
    base = np.array([[0.0, 0, 0], [0, 0, 0.33], [0.08, 0, 0.6], [0, 0.1, 0.9], [0.2, 0.1, 0.7]])
    K = np.array([[1000.0, 0, 160], [0, 1000, 120], [0, 0, 1]])
    uv = np.array([[150.0, 100], [150.4, 100.2], [150.1, 100.5], [150.3, 99.8], [149.9, 100.1]])
    with pytest.raises(cv2.error):  # what OpenCV's SQPnP does with such points
        cv2.solvePnP(base[:4], uv[:4], K, None, flags=cv2.SOLVEPNP_SQPNP)
    view = ViewEvidence(torch.zeros(240, 320), uv, np.ones(len(uv)), K, np.array([0.0, 0, 320, 240]))
    assert all(np.isfinite(p).all() for p in pnp_hypotheses(view, base))
    view4 = ViewEvidence(torch.zeros(240, 320), uv[:4], np.ones(4), K, np.array([0.0, 0, 320, 240]))
    assert all(np.isfinite(p).all() for p in pnp_hypotheses(view4, base[:4]))
