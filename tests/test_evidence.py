"""The evidence denoiser's inputs (method/evidence.py, estimator.evidence_of): both sides land on
the same crop pixels, the parser's views come into the standardised image where the truth
projects, and the reverse process runs on them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import monose3
from monose3.estimator import PoseEstimator, evidence_of
from monose3.geometry.camera import project, standardize_image
from monose3.geometry.poses import perturb_poses
from monose3.method.config import get_preset, with_section
from monose3.method.designs import build_denoiser
from monose3.method.evidence import (
    EVIDENCE_CHANNELS,
    KEYPOINT_CHANNELS,
    Evidence,
    evidence_crops,
    keypoint_maps,
    render_maps,
)
from monose3.method.flow_pose import render_surface
from monose3.method.pose_space import base_frame, centroid_frame
from monose3.method.render_compare import crop_geometry
from monose3.method.update import apply_update, raw_to_update
from monose3.perception.views import parse_image
from monose3.training.checkpoints import load_parser
from monose3.training.formats import BUNDLED_PARSER

SAMPLE = monose3.ASSETS / "sample"
SIZE = (64, 48)


def test_keypoint_maps_peak_where_the_keypoints_are_and_pad_to_the_channel_count():
    uv = torch.tensor([[[10.0, 20.0], [40.5, 5.0]]])
    maps = keypoint_maps(uv, torch.tensor([[1.0, 0.5]]), SIZE)
    assert maps.shape == (1, KEYPOINT_CHANNELS, 48, 64) and not maps[:, 2:].any()
    peak = maps[0, 0].argmax()
    assert (int(peak % 64), int(peak // 64)) == (10, 20) and maps[0, 0].max() == pytest.approx(1.0)
    assert maps[0, 1].max() == pytest.approx(0.5 * np.exp(-0.25 / (2 * 1.5**2)), rel=1e-4)
    with pytest.raises(ValueError, match="at most"):
        keypoint_maps(torch.zeros(1, KEYPOINT_CHANNELS + 1, 2), torch.ones(1, KEYPOINT_CHANNELS + 1), SIZE)


def perfect_evidence(renderer, model, view, size) -> Evidence:
    """What a perfect parser would see: the true silhouette over the whole image, the true keypoints."""
    pose, K = torch.from_numpy(view.pose)[None], torch.from_numpy(view.K)[None]
    mask = renderer.render(view.joints[None], pose, K, size, shade=False).mask.float()[:, None]
    uv = project(view.keypoints @ view.pose[:3, :3].T + view.pose[:3, 3], view.K)
    return Evidence(mask, torch.tensor([[0.0, 0.0, *size]], dtype=torch.float64), torch.from_numpy(uv)[None],
                    torch.ones(1, len(view.keypoints)))  # fmt: skip


def test_the_untrained_evidence_solve_steps_toward_the_parsers_keypoints(renderers, models, sample_view):
    """Its head at zero, ``evidence-solve`` is a Gauss-Newton step of the keypoints onto their
    blobs: from 5 deg / 3 cm off, perfect evidence brings the pose most of the way to the truth."""
    model, renderer, size = models["panda"], renderers["panda"], (320, 240)
    view = sample_view(model, np.random.default_rng(7), size, (1.0, 1.6))
    truth = perfect_evidence(renderer, model, view, size)
    config = get_preset("evidence")
    net = build_denoiser(with_section(config, "network", design="evidence-solve").network).eval()
    centroid = torch.from_numpy(model.centroid(view.points))[None]
    points_ref = torch.from_numpy(view.points)[None] - centroid[:, None]
    start = centroid_frame(torch.from_numpy(perturb_poses(view.pose[None], np.random.default_rng(1), 0.03, 5.0)),
                           centroid)  # fmt: skip
    K = torch.from_numpy(view.K)[None]
    boxes, K_crop = crop_geometry(start, points_ref, K, SIZE)
    pose_base = base_frame(start, centroid)
    rendered = renderer.render(view.joints[None], pose_base, K_crop, SIZE, shade=False)
    kp_cam = torch.from_numpy(model.keypoints(view.joints[None], pose_base.numpy()))
    surface = render_surface(rendered.depth, start.float(), K_crop.float())
    surface.keypoints_ref = torch.from_numpy(view.keypoints - centroid.numpy())[None]
    with torch.no_grad():
        raw = net(render_maps(rendered.mask, kp_cam, K_crop), evidence_crops(truth, boxes, SIZE),
                  torch.tensor([10]), surface).raw.double()  # fmt: skip
    solved = base_frame(apply_update(start, *raw_to_update(raw, SIZE[0]), K_crop), centroid)[0].numpy()
    true_cam = view.keypoints @ view.pose[:3, :3].T + view.pose[:3, 3]

    def error(pose: np.ndarray) -> float:
        return float(np.linalg.norm(model.keypoints(view.joints[None], pose[None])[0] - true_cam, axis=-1).mean())

    assert error(solved) < 0.3 * error(pose_base[0].numpy())


def test_the_evidence_of_the_true_pose_lines_up_with_its_render(renderers, models, sample_view):
    """A perfect parser (the true silhouette over the whole image, the true keypoints) cropped at
    H_0 matches the render side at H_0 pixel for pixel, and not at a pose moved sideways."""
    model, renderer = models["panda"], renderers["panda"]
    size = (320, 240)
    view = sample_view(model, np.random.default_rng(4), size, (1.0, 1.6))
    pose, K = torch.from_numpy(view.pose)[None], torch.from_numpy(view.K)[None]
    truth = perfect_evidence(renderer, model, view, size)
    centroid = torch.from_numpy(model.centroid(view.points))[None]
    points_ref = torch.from_numpy(view.points)[None] - centroid[:, None]

    def sides(pose_base: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        boxes, K_crop = crop_geometry(centroid_frame(pose_base, centroid), points_ref, K, SIZE)
        rendered = renderer.render(view.joints[None], pose_base, K_crop, SIZE, shade=False)
        kp_cam = torch.from_numpy(model.keypoints(view.joints[None], pose_base.numpy()))
        return evidence_crops(truth, boxes, SIZE), render_maps(rendered.mask, kp_cam, K_crop)

    crop, render = sides(pose)
    assert crop.shape == render.shape == (1, EVIDENCE_CHANNELS, 48, 64)
    overlap = ((crop[0, 0] > 0.5) & render[0, 0].bool()).sum() / ((crop[0, 0] > 0.5) | render[0, 0].bool()).sum()
    assert overlap > 0.9 and torch.allclose(crop[:, 1:], render[:, 1:], atol=1e-3)
    moved = pose.clone()
    moved[0, 0, 3] += 0.05
    crop, render = sides(moved)
    assert not torch.allclose(crop[:, 1:], render[:, 1:], atol=0.1)


@pytest.fixture(scope="module")
def parsed():
    image, K = monose3.load_image(SAMPLE / "image.jpg"), monose3.load_camera(SAMPLE / "camera.json").K
    return image, K, parse_image(load_parser(BUNDLED_PARSER), image, K)


def test_evidence_of_brings_the_parsers_view_into_the_standardised_image(parsed, models):
    image, K, view = parsed
    joints = monose3.load_joints(SAMPLE / "joints.json", models["panda"])
    truth = np.array(json.loads((SAMPLE / "ground_truth.json").read_text())["camera_from_base"])
    for size in ((320, 240), (160, 120)):
        evidence = evidence_of([view], [(image.shape[1], image.shape[0])], size)
        _, K_std = standardize_image(image, K, size)
        expected = project(models["panda"].keypoints(joints[None], truth[None])[0], K_std)
        confident = view.confidence > 0.5
        error = np.linalg.norm(evidence.keypoints[0].numpy() - expected, axis=1)[confident]
        assert np.median(error) < 2.0 * size[0] / 320  # the parser's keypoints, in the standardised image's pixels
        assert evidence.mask.shape == (1, 1, *view.mask.shape)


def test_the_reverse_process_runs_on_the_parsers_evidence(parsed, models):
    image, K, _ = parsed
    config = with_section(get_preset("evidence"), "inference", ddim_steps=2, direct_steps=1)
    estimator = PoseEstimator(build_denoiser(config.network), config, parser=load_parser(BUNDLED_PARSER))
    joints = monose3.load_joints(SAMPLE / "joints.json", estimator.robot)
    try:
        est = estimator.estimate([image], K[None], joints[None], sampler="revdiff")
        assert est.poses.shape == (1, 4, 4) and est.found.tolist() == [True] and len(est.history) == 4
        # An untrained (zero-head) denoiser is the identity update: the DDIM steps alone move the pose.
        tracked = estimator.track([image], K[None], joints[None], est.poses, sampler="revdiff")
        assert tracked.poses.shape == (1, 4, 4)
    finally:
        estimator.close()
    blind = PoseEstimator(build_denoiser(config.network), config)
    with pytest.raises(monose3.Monose3Error, match="needs? (a|one)|evidence"):
        blind.estimate([image], K[None], joints[None], sampler="revdiff")
